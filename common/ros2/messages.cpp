#include "common/ros2/messages.hpp"

#include <limits>
#include <string>

#include "common/ros2/cdr.hpp"

namespace cvislam::ros2 {
namespace {

constexpr std::int64_t kNanosecondsPerSecond = 1'000'000'000;
constexpr std::uint64_t kMaxLength = std::numeric_limits<std::uint32_t>::max();

HeaderView readHeader(CdrReader& r) {
  HeaderView h;
  h.stamp.sec = r.primitive<std::int32_t>("header.stamp.sec");
  h.stamp.nanosec = r.primitive<std::uint32_t>("header.stamp.nanosec");
  h.frame_id = r.string("header.frame_id");
  return h;
}

void writeHeader(CdrWriter& w, const HeaderView& h) {
  w.primitive(h.stamp.sec);
  w.primitive(h.stamp.nanosec);
  w.string(h.frame_id);
}

Vector3 readVector3(CdrReader& r, const char* field) {
  Vector3 v;
  v.x = r.primitive<double>(field);
  v.y = r.primitive<double>(field);
  v.z = r.primitive<double>(field);
  return v;
}

void writeVector3(CdrWriter& w, const Vector3& v) {
  w.primitive(v.x);
  w.primitive(v.y);
  w.primitive(v.z);
}

Status tooLong(std::string_view type, std::string_view field) {
  return Error(ErrorCode::kInvalidArgument,
               "cdr: " + std::string(type) + ": " + std::string(field) + " is over 4 GiB, more than CDR can carry");
}

}  // namespace

std::int64_t toNanoseconds(const Time& t) {
  return std::int64_t{t.sec} * kNanosecondsPerSecond + t.nanosec;
}

Result<Time> timeFromNanoseconds(std::int64_t t_ns) {
  // Floor division: a time before the epoch has negative seconds and nanoseconds in [0, 1e9).
  std::int64_t sec = t_ns / kNanosecondsPerSecond;
  std::int64_t nanosec = t_ns % kNanosecondsPerSecond;
  if (nanosec < 0) {
    sec -= 1;
    nanosec += kNanosecondsPerSecond;
  }
  if (sec < std::numeric_limits<std::int32_t>::min() || sec > std::numeric_limits<std::int32_t>::max()) {
    return Error(ErrorCode::kInvalidArgument,
                 "time " + std::to_string(t_ns) + " ns does not fit builtin_interfaces/Time (int32 seconds)");
  }
  return Time{static_cast<std::int32_t>(sec), static_cast<std::uint32_t>(nanosec)};
}

Result<ImageView> decodeImage(std::span<const std::uint8_t> cdr) {
  auto reader = CdrReader::open(cdr, kImageType);
  if (!reader.ok()) return reader.error();
  CdrReader& r = reader.value();
  ImageView image;
  image.header = readHeader(r);
  image.height = r.primitive<std::uint32_t>("height");
  image.width = r.primitive<std::uint32_t>("width");
  image.encoding = r.string("encoding");
  image.is_bigendian = r.primitive<std::uint8_t>("is_bigendian");
  image.step = r.primitive<std::uint32_t>("step");
  image.data = r.byteSequence("data");
  if (Status s = r.finish(); !s.ok()) return s.error();
  return image;
}

Result<ImuView> decodeImu(std::span<const std::uint8_t> cdr) {
  auto reader = CdrReader::open(cdr, kImuType);
  if (!reader.ok()) return reader.error();
  CdrReader& r = reader.value();
  ImuView imu;
  imu.header = readHeader(r);
  imu.orientation.x = r.primitive<double>("orientation");
  imu.orientation.y = r.primitive<double>("orientation");
  imu.orientation.z = r.primitive<double>("orientation");
  imu.orientation.w = r.primitive<double>("orientation");
  r.doubles(imu.orientation_covariance, "orientation_covariance");
  imu.angular_velocity_rad_s = readVector3(r, "angular_velocity");
  r.doubles(imu.angular_velocity_covariance, "angular_velocity_covariance");
  imu.linear_acceleration_m_s2 = readVector3(r, "linear_acceleration");
  r.doubles(imu.linear_acceleration_covariance, "linear_acceleration_covariance");
  if (Status s = r.finish(); !s.ok()) return s.error();
  return imu;
}

Status encodeImage(const ImageView& image, std::vector<std::uint8_t>& out) {
  // A string's length counts its NUL.
  if (image.header.frame_id.size() >= kMaxLength) return tooLong(kImageType, "header.frame_id");
  if (image.encoding.size() >= kMaxLength) return tooLong(kImageType, "encoding");
  if (image.data.size() > kMaxLength) return tooLong(kImageType, "data");
  CdrWriter w(out);
  writeHeader(w, image.header);
  w.primitive(image.height);
  w.primitive(image.width);
  w.string(image.encoding);
  w.primitive(image.is_bigendian);
  w.primitive(image.step);
  w.byteSequence(image.data);
  return {};
}

Status encodeImu(const ImuView& imu, std::vector<std::uint8_t>& out) {
  if (imu.header.frame_id.size() >= kMaxLength) return tooLong(kImuType, "header.frame_id");
  CdrWriter w(out);
  writeHeader(w, imu.header);
  w.primitive(imu.orientation.x);
  w.primitive(imu.orientation.y);
  w.primitive(imu.orientation.z);
  w.primitive(imu.orientation.w);
  w.doubles(imu.orientation_covariance);
  writeVector3(w, imu.angular_velocity_rad_s);
  w.doubles(imu.angular_velocity_covariance);
  writeVector3(w, imu.linear_acceleration_m_s2);
  w.doubles(imu.linear_acceleration_covariance);
  return {};
}

std::uint32_t bytesPerPixel(std::string_view encoding) {
  if (encoding == "mono8" || encoding == "8UC1" || encoding == "8SC1" ||
      (encoding.starts_with("bayer_") && encoding.ends_with("8"))) {
    return 1;
  }
  if (encoding == "mono16" || encoding == "16UC1" || encoding == "16SC1" ||
      (encoding.starts_with("bayer_") && encoding.ends_with("16")) || encoding == "8UC2" || encoding == "yuv422" ||
      encoding == "uyvy" || encoding == "yuyv") {
    return 2;
  }
  if (encoding == "rgb8" || encoding == "bgr8" || encoding == "8UC3") return 3;
  if (encoding == "rgba8" || encoding == "bgra8" || encoding == "8UC4" || encoding == "32FC1" || encoding == "32SC1" ||
      encoding == "16UC2") {
    return 4;
  }
  if (encoding == "rgb16" || encoding == "bgr16" || encoding == "16UC3") return 6;
  if (encoding == "rgba16" || encoding == "bgra16" || encoding == "16UC4" || encoding == "64FC1" ||
      encoding == "32FC2") {
    return 8;
  }
  return 0;
}

Status checkImageLayout(const ImageView& image) {
  const std::uint64_t expected = std::uint64_t{image.step} * image.height;
  if (image.data.size() != expected) {
    return Error(ErrorCode::kDataError, "image " + std::to_string(image.width) + "x" + std::to_string(image.height) +
                                            " " + std::string(image.encoding) + ": " +
                                            std::to_string(image.data.size()) +
                                            " bytes of data, step x height = " + std::to_string(expected));
  }
  const std::uint32_t pixel_bytes = bytesPerPixel(image.encoding);
  if (pixel_bytes != 0 && std::uint64_t{image.width} * pixel_bytes > image.step) {
    return Error(ErrorCode::kDataError, "image " + std::to_string(image.width) + "x" + std::to_string(image.height) +
                                            " " + std::string(image.encoding) + ": a row needs " +
                                            std::to_string(std::uint64_t{image.width} * pixel_bytes) +
                                            " bytes, step is " + std::to_string(image.step));
  }
  return {};
}

// The minimal .msg texts: the fields of the ROS 2 definitions without their comments, which give the same bytes.
// Both messages end with std_msgs/Header and builtin_interfaces/Time, joined as literals by this macro.
#define CVISLAM_ROS2_HEADER_AND_TIME                                                   \
  "================================================================================\n" \
  "MSG: std_msgs/Header\n"                                                             \
  "builtin_interfaces/Time stamp\n"                                                    \
  "string frame_id\n"                                                                  \
  "================================================================================\n" \
  "MSG: builtin_interfaces/Time\n"                                                     \
  "int32 sec\n"                                                                        \
  "uint32 nanosec\n"

const std::string_view kImageDefinition =
    "std_msgs/Header header\n"
    "uint32 height\n"
    "uint32 width\n"
    "string encoding\n"
    "uint8 is_bigendian\n"
    "uint32 step\n"
    "uint8[] data\n" CVISLAM_ROS2_HEADER_AND_TIME;

const std::string_view kImuDefinition =
    "std_msgs/Header header\n"
    "geometry_msgs/Quaternion orientation\n"
    "float64[9] orientation_covariance\n"
    "geometry_msgs/Vector3 angular_velocity\n"
    "float64[9] angular_velocity_covariance\n"
    "geometry_msgs/Vector3 linear_acceleration\n"
    "float64[9] linear_acceleration_covariance\n"
    "================================================================================\n"
    "MSG: geometry_msgs/Quaternion\n"
    "float64 x 0\n"
    "float64 y 0\n"
    "float64 z 0\n"
    "float64 w 1\n"
    "================================================================================\n"
    "MSG: geometry_msgs/Vector3\n"
    "float64 x\n"
    "float64 y\n"
    "float64 z\n" CVISLAM_ROS2_HEADER_AND_TIME;

#undef CVISLAM_ROS2_HEADER_AND_TIME

}  // namespace cvislam::ros2

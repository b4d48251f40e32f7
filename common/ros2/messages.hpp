// sensor_msgs/msg/Image and sensor_msgs/msg/Imu in ROS 2's CDR (cdr.hpp), both ways, and the ros2msg schema texts
// an MCAP file needs so that rosbag2 and Foxglove can read what we write.
//
// Decoding returns views: frame_id, encoding and the pixels point into the message buffer, so a frame decodes
// without allocating; copy what must outlive the buffer.
#pragma once

#include <array>
#include <cstdint>
#include <span>
#include <string_view>
#include <vector>

#include "common/core/result.hpp"

namespace cvislam::ros2 {

// builtin_interfaces/msg/Time: seconds and nanoseconds since the Unix epoch (ROS time).
struct Time {
  std::int32_t sec = 0;
  std::uint32_t nanosec = 0;

  bool operator==(const Time&) const = default;
};
std::int64_t toNanoseconds(const Time& t);
// An error when t_ns lies outside what int32 seconds hold (before 1901 or after 2038).
Result<Time> timeFromNanoseconds(std::int64_t t_ns);

// std_msgs/msg/Header.
struct HeaderView {
  Time stamp;
  std::string_view frame_id;
};

// sensor_msgs/msg/Image: height rows of `step` bytes each.
struct ImageView {
  HeaderView header;
  std::uint32_t height = 0;
  std::uint32_t width = 0;
  std::string_view encoding;  // "mono8", "rgb8", "bgr8", "mono16", ...
  std::uint8_t is_bigendian = 0;
  std::uint32_t step = 0;  // bytes per row
  std::span<const std::uint8_t> data;
};

struct Quaternion {
  double x = 0;
  double y = 0;
  double z = 0;
  double w = 1;
};
struct Vector3 {
  double x = 0;
  double y = 0;
  double z = 0;
};

// sensor_msgs/msg/Imu, in the frame header.frame_id. A covariance is row-major 3x3; all zeros means unknown, and
// orientation_covariance[0] = -1 means the IMU gives no orientation. Field names carry the units of the ROS
// definition: angular_velocity in rad/s, linear_acceleration in m/s^2.
struct ImuView {
  HeaderView header;
  Quaternion orientation;
  std::array<double, 9> orientation_covariance{};
  Vector3 angular_velocity_rad_s;
  std::array<double, 9> angular_velocity_covariance{};
  Vector3 linear_acceleration_m_s2;
  std::array<double, 9> linear_acceleration_covariance{};
};

// Decoders: every length is checked against the buffer; a malformed message is an error naming the field.
Result<ImageView> decodeImage(std::span<const std::uint8_t> cdr);
Result<ImuView> decodeImu(std::span<const std::uint8_t> cdr);

// Encoders: replace `out` with the CDR message (the buffer's capacity is reused). Errors for strings or pixel data
// over 4 GiB.
Status encodeImage(const ImageView& image, std::vector<std::uint8_t>& out);
Status encodeImu(const ImuView& imu, std::vector<std::uint8_t>& out);

// Checks that the pixels are what the header fields say: data holds height * step bytes, and for the encodings
// named in sensor_msgs/image_encodings.hpp a row of `width` pixels fits in `step`. Decoding does not check this
// (it is about meaning, not the encoding); a consumer that indexes pixels by width and height must.
Status checkImageLayout(const ImageView& image);
// Bytes per pixel of a sensor_msgs image encoding; 0 when the encoding is not one we know.
std::uint32_t bytesPerPixel(std::string_view encoding);

// For MCAP: the Header profile, the schema and message encodings, the schema names and their ros2msg texts (the
// root definition, then each dependency after a line of 80 '=' and "MSG: <type>", in the order rosbag2 writes them).
inline constexpr std::string_view kProfile = "ros2";
inline constexpr std::string_view kSchemaEncoding = "ros2msg";
inline constexpr std::string_view kMessageEncoding = "cdr";
inline constexpr std::string_view kImageType = "sensor_msgs/msg/Image";
inline constexpr std::string_view kImuType = "sensor_msgs/msg/Imu";
extern const std::string_view kImageDefinition;
extern const std::string_view kImuDefinition;

}  // namespace cvislam::ros2

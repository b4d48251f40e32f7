#include "agent_rt/sources/mcap_recording.hpp"

#include <algorithm>
#include <array>
#include <map>
#include <string>
#include <vector>

#include "agent_rt/sources/kalibr_rig.hpp"
#include "common/mcap/reader.hpp"
#include "common/ros2/messages.hpp"

namespace cvislam::agent {
namespace {

enum class Stream { kOther, kCam0, kCam1, kImu };

// A bag's images can be large (a 4K colour stream); one chunk of several images must still fit.
mcap::ReaderOptions readerOptions() {
  mcap::ReaderOptions options;
  options.max_record_bytes = std::uint64_t{128} << 20;
  options.max_definition_bytes = std::uint64_t{8} << 20;
  return options;
}

// The stream a message belongs to, with its schema checked: a topic we read that carries another type is an error
// that names both.
Result<Stream> streamOf(const mcap::MessageView& m, const McapTopics& topics) {
  if (m.channel == nullptr) return Stream::kOther;
  const std::string& topic = m.channel->topic;
  const Stream stream = topic == topics.cam0                             ? Stream::kCam0
                        : (!topics.cam1.empty() && topic == topics.cam1) ? Stream::kCam1
                        : topic == topics.imu                            ? Stream::kImu
                                                                         : Stream::kOther;
  if (stream == Stream::kOther) return stream;
  const std::string_view expected = stream == Stream::kImu ? ros2::kImuType : ros2::kImageType;
  const std::string schema = m.schema != nullptr ? m.schema->name : std::string("no schema");
  if (m.schema == nullptr || m.schema->name != expected) {
    return Error{ErrorCode::kDataError, "topic " + topic + " carries " + schema + ", not " + std::string(expected)};
  }
  if (m.channel->message_encoding != ros2::kMessageEncoding) {
    return Error{ErrorCode::kDataError, "topic " + topic + " is encoded as '" + m.channel->message_encoding +
                                            "'; only ROS 2 CDR ('cdr') is read"};
  }
  return stream;
}

std::int64_t stampOf(const ros2::HeaderView& header, std::uint64_t log_time_ns, bool& fell_back) {
  const std::int64_t stamp = ros2::toNanoseconds(header.stamp);
  if (stamp != 0) return stamp;
  fell_back = true;
  return static_cast<std::int64_t>(log_time_ns);
}

// mono8 as it is; rgb8 and bgr8 to grey with the Rec. 601 weights (as OpenCV's cvtColor does).
Status imageToGrey(const ros2::ImageView& image, int width, int height, std::span<std::uint8_t> pixels,
                   const std::string& topic) {
  if (Status s = ros2::checkImageLayout(image); !s.ok()) return s.error().withContext("topic " + topic);
  if (static_cast<int>(image.width) != width || static_cast<int>(image.height) != height) {
    return Error{ErrorCode::kDataError, "topic " + topic + ": an image of " + std::to_string(image.width) + "x" +
                                            std::to_string(image.height) + " in a stream of " + std::to_string(width) +
                                            "x" + std::to_string(height)};
  }
  const bool mono = image.encoding == "mono8";
  const bool rgb = image.encoding == "rgb8";
  if (!mono && !rgb && image.encoding != "bgr8") {
    return Error{ErrorCode::kDataError, "topic " + topic + ": image encoding '" + std::string(image.encoding) +
                                            "' is not read (mono8, rgb8 or bgr8)"};
  }
  for (int y = 0; y < height; ++y) {
    const std::uint8_t* row = image.data.data() + static_cast<std::size_t>(y) * image.step;
    std::uint8_t* out = pixels.data() + static_cast<std::size_t>(y) * static_cast<std::size_t>(width);
    if (mono) {
      std::copy(row, row + width, out);
      continue;
    }
    const int r = rgb ? 0 : 2;
    const int b = rgb ? 2 : 0;
    for (int x = 0; x < width; ++x) {
      const std::uint8_t* p = row + 3 * x;
      out[x] = static_cast<std::uint8_t>((77 * p[r] + 150 * p[1] + 29 * p[b] + 128) >> 8);
    }
  }
  return Status::Ok();
}

struct ImageEntry {
  std::int64_t t_ns = 0;
  std::uint64_t ordinal = 0;  // among the file's cam0 and cam1 images, in file order
};

// What the first pass over the file finds.
struct Scan {
  std::array<std::vector<ImageEntry>, 2> cameras;
  std::array<int, 2> width{0, 0};
  std::array<int, 2> height{0, 0};
  std::vector<dataset::ImuSample> imu;
  Diagnostics diagnostics;
};

Status scanImage(const mcap::MessageView& m, int camera, std::uint64_t ordinal, bool& fell_back, Scan& scan) {
  auto image = ros2::decodeImage(m.data);
  if (!image) return image.error().withContext("topic " + m.channel->topic);
  if (scan.width[camera] == 0) {
    scan.width[camera] = static_cast<int>(image->width);
    scan.height[camera] = static_cast<int>(image->height);
  }
  scan.cameras[camera].push_back({stampOf(image->header, m.log_time_ns, fell_back), ordinal});
  return Status::Ok();
}

Status scanImu(const mcap::MessageView& m, bool& fell_back, Scan& scan) {
  auto imu = ros2::decodeImu(m.data);
  if (!imu) return imu.error().withContext("topic " + m.channel->topic);
  dataset::ImuSample s;
  s.t_ns = stampOf(imu->header, m.log_time_ns, fell_back);
  s.gyro_s = {imu->angular_velocity_rad_s.x, imu->angular_velocity_rad_s.y, imu->angular_velocity_rad_s.z};
  s.accel_s = {imu->linear_acceleration_m_s2.x, imu->linear_acceleration_m_s2.y, imu->linear_acceleration_m_s2.z};
  scan.imu.push_back(s);
  return Status::Ok();
}

// Sorted by time; of samples with one time the first in the file is kept, and how many went is reported.
template <typename T, typename Time>
void sortByTime(std::vector<T>& items, Time time_of, const std::string& what, Diagnostics& diagnostics,
                const std::string& file) {
  std::stable_sort(items.begin(), items.end(), [&](const T& a, const T& b) { return time_of(a) < time_of(b); });
  const auto end =
      std::unique(items.begin(), items.end(), [&](const T& a, const T& b) { return time_of(a) == time_of(b); });
  const auto repeated = static_cast<std::size_t>(items.end() - end);
  items.erase(end, items.end());
  if (repeated > 0) diagnostics.warn(file, 0, std::to_string(repeated) + " " + what + " repeat a time; dropped");
}

Result<Scan> scanFile(const RecordingOptions& options) {
  auto reader = mcap::Reader::open(options.mcap, readerOptions());
  if (!reader) return reader.error();
  Scan scan;
  std::uint64_t ordinal = 0;
  bool fell_back = false;
  mcap::MessageView m;
  for (;;) {
    auto more = reader->next(m);
    if (!more) return more.error();
    if (!*more) break;
    auto stream = streamOf(m, options.topics);
    if (!stream) return stream.error().withContext(options.mcap.string());
    Status s = Status::Ok();
    if (*stream == Stream::kCam0 || *stream == Stream::kCam1) {
      s = scanImage(m, *stream == Stream::kCam0 ? 0 : 1, ordinal++, fell_back, scan);
    } else if (*stream == Stream::kImu) {
      s = scanImu(m, fell_back, scan);
    }
    if (!s.ok()) return s.error().withContext(options.mcap.string());
  }
  const std::string file = options.mcap.string();
  if (scan.cameras[0].empty()) {
    return Error{ErrorCode::kDataError,
                 file + ": no sensor_msgs/msg/Image on topic " + options.topics.cam0 + " (--cam0-topic names another)"};
  }
  if (options.require_imu && scan.imu.empty()) {
    return Error{ErrorCode::kDataError, file + ": no sensor_msgs/msg/Imu on topic " + options.topics.imu +
                                            " (--imu-topic names another, or run without the IMU)"};
  }
  if (fell_back) {
    scan.diagnostics.warn(file, 0, "some messages have a zero header stamp: their log time is used instead");
  }
  for (auto& entries : scan.cameras) {
    sortByTime(
        entries, [](const ImageEntry& e) { return e.t_ns; }, "images", scan.diagnostics, file);
  }
  sortByTime(
      scan.imu, [](const dataset::ImuSample& s) { return s.t_ns; }, "IMU samples", scan.diagnostics, file);
  return scan;
}

// The frame rate the images were taken at: Kalibr's files do not give it.
double medianRateHz(const std::vector<ImageEntry>& entries) {
  if (entries.size() < 2) return 20.0;
  std::vector<std::int64_t> dt;
  for (std::size_t i = 1; i < entries.size(); ++i) dt.push_back(entries[i].t_ns - entries[i - 1].t_ns);
  std::nth_element(dt.begin(), dt.begin() + static_cast<std::ptrdiff_t>(dt.size() / 2), dt.end());
  const std::int64_t median = dt[dt.size() / 2];
  return median > 0 ? 1e9 / static_cast<double>(median) : 20.0;
}

class McapRecording final : public Recording {
 public:
  McapRecording(RecordingOptions options, Scan scan, SensorRig rig, std::vector<dataset::RigFrame> frames,
                mcap::Reader playback)
      : options_(std::move(options)),
        scan_(std::move(scan)),
        rig_(std::move(rig)),
        frames_(std::move(frames)),
        playback_(std::move(playback)) {}

  [[nodiscard]] const SensorRig& rig() const override { return rig_; }
  [[nodiscard]] std::span<const dataset::ImuSample> imu() const override { return scan_.imu; }
  [[nodiscard]] std::span<const dataset::RigFrame> rigFrames() const override { return frames_; }
  [[nodiscard]] const Diagnostics& diagnostics() const override { return scan_.diagnostics; }
  [[nodiscard]] std::string describe() const override { return "MCAP file " + options_.mcap.string(); }
  [[nodiscard]] bool simulated() const override { return false; }

  [[nodiscard]] Status loadImageInto(int camera, std::size_t frame, std::span<std::uint8_t> pixels) override {
    if (camera < 0 || camera > 1 || frame >= scan_.cameras[static_cast<std::size_t>(camera)].size()) {
      return Error{ErrorCode::kInvalidArgument,
                   "no frame " + std::to_string(frame) + " of cam" + std::to_string(camera)};
    }
    const ImageEntry& wanted = scan_.cameras[static_cast<std::size_t>(camera)][frame];
    const std::string& topic = camera == 0 ? options_.topics.cam0 : options_.topics.cam1;
    const int width = scan_.width[static_cast<std::size_t>(camera)];
    const int height = scan_.height[static_cast<std::size_t>(camera)];
    if (pixels.size() != static_cast<std::size_t>(width) * static_cast<std::size_t>(height)) {
      return Error{ErrorCode::kInvalidArgument, "the frame buffer does not fit " + topic + "'s images"};
    }
    forgetBefore(wanted.t_ns);
    if (const auto kept = stash_.find(wanted.ordinal); kept != stash_.end()) {
      std::copy(kept->second.pixels.begin(), kept->second.pixels.end(), pixels.begin());
      stash_.erase(kept);
      return Status::Ok();
    }
    return readForwardTo(wanted, topic, width, height, pixels);
  }

 private:
  // Requests come in time order, and a stereo partner within the pairing window: what lies further back than
  // that will not be asked for.
  void forgetBefore(std::int64_t t_ns) {
    constexpr std::int64_t kMarginNs = 10'000'000;
    for (auto it = stash_.begin(); it != stash_.end();) {
      it = it->second.t_ns < t_ns - kMarginNs ? stash_.erase(it) : std::next(it);
    }
  }

  Status readForwardTo(const ImageEntry& wanted, const std::string& topic, int width, int height,
                       std::span<std::uint8_t> pixels) {
    mcap::MessageView m;
    for (;;) {
      auto more = playback_.next(m);
      if (!more) return more.error();
      if (!*more) {
        return Error{ErrorCode::kDataError, describe() + ": the image of " + topic + " at t = " +
                                                std::to_string(wanted.t_ns) + " ns was not found on the second read"};
      }
      auto stream = streamOf(m, options_.topics);
      if (!stream) return stream.error();
      if (*stream != Stream::kCam0 && *stream != Stream::kCam1) continue;
      const std::uint64_t ordinal = next_ordinal_++;
      auto image = ros2::decodeImage(m.data);
      if (!image) return image.error().withContext("topic " + m.channel->topic);
      if (ordinal == wanted.ordinal) return imageToGrey(*image, width, height, pixels, topic);
      // An image the file holds before the one asked for but stamped after it: asked for later.
      bool fell_back = false;
      const std::int64_t t_ns = stampOf(image->header, m.log_time_ns, fell_back);
      if (t_ns < wanted.t_ns - 10'000'000) continue;  // a frame the run does not use
      const int other = *stream == Stream::kCam0 ? 0 : 1;
      if (stash_.size() >= kMaxStashed) {
        return Error{ErrorCode::kDataError, describe() + ": more than " + std::to_string(kMaxStashed) +
                                                " images are out of time order; sort the bag by header stamp"};
      }
      Stashed& s = stash_[ordinal];
      s.t_ns = t_ns;
      s.pixels.resize(static_cast<std::size_t>(scan_.width[static_cast<std::size_t>(other)]) *
                      static_cast<std::size_t>(scan_.height[static_cast<std::size_t>(other)]));
      const std::string& other_topic = other == 0 ? options_.topics.cam0 : options_.topics.cam1;
      if (Status st = imageToGrey(*image, scan_.width[static_cast<std::size_t>(other)],
                                  scan_.height[static_cast<std::size_t>(other)], s.pixels, other_topic);
          !st.ok()) {
        stash_.erase(ordinal);
        return st;
      }
    }
  }

  struct Stashed {
    std::int64_t t_ns = 0;
    std::vector<std::uint8_t> pixels;
  };
  static constexpr std::size_t kMaxStashed = 64;

  RecordingOptions options_;
  Scan scan_;
  SensorRig rig_;
  std::vector<dataset::RigFrame> frames_;
  mcap::Reader playback_;  // the loading thread's forward read
  std::uint64_t next_ordinal_ = 0;
  std::map<std::uint64_t, Stashed> stash_;  // by ordinal
};

}  // namespace

Result<std::unique_ptr<Recording>> openMcapRecording(const RecordingOptions& options) {
  auto scan = scanFile(options);
  if (!scan) return scan.error();
  const bool has_cam1 = !scan->cameras[1].empty();
  // The rig as the bag shows it (image sizes, frame rates), for Kalibr's files to fill in and check.
  SensorRig rig;
  rig.cam0.name = "cam0";
  rig.cam0.width = scan->width[0];
  rig.cam0.height = scan->height[0];
  rig.cam0.rate_hz = medianRateHz(scan->cameras[0]);
  if (has_cam1) {
    rig.cam1 = rig.cam0;
    rig.cam1->name = "cam1";
    rig.cam1->width = scan->width[1];
    rig.cam1->height = scan->height[1];
    rig.cam1->rate_hz = medianRateHz(scan->cameras[1]);
  }
  rig.imu = dataset::ImuCalibration{};
  auto shift_ns = applyKalibrFiles(options, rig);
  if (!shift_ns) return shift_ns.error();
  if (options.imu_calibration.empty()) rig.imu.reset();

  std::vector<std::int64_t> t0;
  std::vector<std::int64_t> t1;
  for (const ImageEntry& e : scan->cameras[0]) t0.push_back(e.t_ns);
  for (const ImageEntry& e : scan->cameras[1]) t1.push_back(e.t_ns);
  dataset::StereoPairing pairing =
      dataset::pairStereoFrames(t0, rig.cam1 ? std::optional(std::span<const std::int64_t>(t1)) : std::nullopt,
                                dataset::EurocReaderOptions{}.stereo_max_dt_ns);
  if (pairing.unpaired_cam0 > 0) {
    scan->diagnostics.warn(options.mcap.string(), 0,
                           std::to_string(pairing.unpaired_cam0) +
                               " cam0 image(s) have no cam1 image within 1 ms; a stereo run leaves them out");
  }
  for (dataset::RigFrame& f : pairing.frames) f.t_ns += *shift_ns;

  auto playback = mcap::Reader::open(options.mcap, readerOptions());
  if (!playback) return playback.error();
  return std::unique_ptr<Recording>(std::make_unique<McapRecording>(
      options, std::move(scan).value(), std::move(rig), std::move(pairing.frames), std::move(playback).value()));
}

}  // namespace cvislam::agent

#include "common/dataset/euroc.hpp"

#include <algorithm>
#include <cmath>
#include <sstream>

#include "common/core/text.hpp"
#include "common/dataset/calibration.hpp"
#include "common/dataset/csv.hpp"
#include "common/dataset/pose_fields.hpp"

namespace cvislam::dataset {
namespace {

std::string parseImuRow(const std::vector<std::string_view>& f, ImuSample& row) {
  std::string problem;
  if (!parseFieldNs(f, 0, row.t_ns, problem)) return problem;
  for (int i = 0; i < 3; ++i) {
    if (!parseFieldDouble(f, 1 + i, row.gyro_s(i), problem)) return problem;
    if (!parseFieldDouble(f, 4 + i, row.accel_s(i), problem)) return problem;
  }
  return {};
}

std::string parseGroundTruthRow(const std::vector<std::string_view>& f, GroundTruthState& row) {
  std::string problem;
  if (!parseFieldNs(f, 0, row.t_ns, problem)) return problem;
  if (!parsePositionQuaternionWxyz(f, 1, row.T_w_b, problem)) return problem;
  if (f.size() >= 17) {
    for (int i = 0; i < 3; ++i) {
      if (!parseFieldDouble(f, 8 + i, row.v_w(i), problem)) return problem;
      if (!parseFieldDouble(f, 11 + i, row.gyro_bias(i), problem)) return problem;
      if (!parseFieldDouble(f, 14 + i, row.accel_bias(i), problem)) return problem;
    }
    row.has_velocity_and_biases = true;
  }
  return {};
}

std::string parseImageRow(const std::vector<std::string_view>& f, ImageEntry& row) {
  std::string problem;
  if (!parseFieldNs(f, 0, row.t_ns, problem)) return problem;
  if (f[1].empty()) return "field 2 (image file name) is empty";
  if (f[1].find("..") != std::string_view::npos || f[1].front() == '/') {
    return "field 2 ('" + std::string(f[1]) + "') must be a file name inside the data/ folder";
  }
  row.filename = std::string(f[1]);
  return {};
}

std::string seconds(std::int64_t t_ns) {
  return text::formatDouble(1e-9 * static_cast<double>(t_ns));
}

// Pairs cam0 and cam1 frames by nearest timestamp within max_dt (each frame used once, both lists sorted).
std::vector<RigFrame> pairFrames(const CameraStream& cam0, const CameraStream* cam1, std::int64_t max_dt_ns,
                                 Diagnostics& diagnostics) {
  const auto times = [](const CameraStream& c) {
    std::vector<std::int64_t> t;
    t.reserve(c.frames.size());
    for (const ImageEntry& e : c.frames) t.push_back(e.t_ns);
    return t;
  };
  const std::vector<std::int64_t> t0 = times(cam0);
  const std::vector<std::int64_t> t1 = cam1 != nullptr ? times(*cam1) : std::vector<std::int64_t>{};
  StereoPairing pairing =
      pairStereoFrames(t0, cam1 != nullptr ? std::optional(std::span(t1)) : std::nullopt, max_dt_ns);
  if (pairing.unpaired_cam0 > 0) {
    diagnostics.warn(cam0.folder.string(), 0,
                     std::to_string(pairing.unpaired_cam0) + " cam0 frame(s) have no cam1 frame within " +
                         std::to_string(max_dt_ns) + " ns; a stereo run leaves them out, a mono run uses them");
  }
  if (pairing.unpaired_cam1 > 0) {
    diagnostics.warn(cam1->folder.string(), 0,
                     std::to_string(pairing.unpaired_cam1) + " cam1 frame(s) have no cam0 frame within " +
                         std::to_string(max_dt_ns) + " ns; they are not used");
  }
  return std::move(pairing.frames);
}

}  // namespace

StereoPairing pairStereoFrames(std::span<const std::int64_t> cam0_t_ns,
                               std::optional<std::span<const std::int64_t>> cam1_t_ns, std::int64_t max_dt_ns) {
  StereoPairing out;
  out.frames.reserve(cam0_t_ns.size());
  std::size_t j = 0;
  const std::span<const std::int64_t> f1 = cam1_t_ns.value_or(std::span<const std::int64_t>{});
  std::vector<bool> used1(f1.size(), false);
  for (std::size_t i = 0; i < cam0_t_ns.size(); ++i) {
    RigFrame frame{cam0_t_ns[i], i, std::nullopt};
    if (cam1_t_ns) {
      while (j < f1.size() && f1[j] < frame.t_ns - max_dt_ns) ++j;
      std::optional<std::size_t> best;
      for (std::size_t k = j; k < f1.size() && f1[k] <= frame.t_ns + max_dt_ns; ++k) {
        if (!used1[k] && (!best || std::llabs(f1[k] - frame.t_ns) < std::llabs(f1[*best] - frame.t_ns))) best = k;
      }
      if (best) {
        used1[*best] = true;
        frame.cam1 = best;
      } else {
        ++out.unpaired_cam0;
      }
    }
    out.frames.push_back(frame);
  }
  out.unpaired_cam1 = static_cast<std::size_t>(std::count(used1.begin(), used1.end(), false));
  return out;
}

Status EurocReaderOptions::validate() const {
  if (stereo_max_dt_ns < 0 || stereo_max_dt_ns > 1'000'000'000) {
    return Error{ErrorCode::kInvalidArgument, "stereo_max_dt_ns must be in [0, 1e9] ns"};
  }
  return Status::Ok();
}

Result<std::vector<ImuSample>> readImuCsv(const std::filesystem::path& path, bool strict, Diagnostics& diagnostics) {
  const CsvFormat format{true, 7, 7, "timestamp [ns], w_x, w_y, w_z [rad/s], a_x, a_y, a_z [m/s^2]"};
  return readTimestampedRows<ImuSample>(path, format, &parseImuRow, strict, diagnostics);
}

Result<std::vector<GroundTruthState>> readGroundTruthCsv(const std::filesystem::path& path, bool strict,
                                                         Diagnostics& diagnostics, bool as_trajectory) {
  const CsvFormat format{true, 8, 17, "timestamp [ns], p_x, p_y, p_z, q_w, q_x, q_y, q_z[, v, b_w, b_a]",
                         as_trajectory};
  return readTimestampedRows<GroundTruthState>(path, format, &parseGroundTruthRow, strict, diagnostics);
}

Result<std::vector<ImageEntry>> readImageListCsv(const std::filesystem::path& path, bool strict,
                                                 Diagnostics& diagnostics) {
  const CsvFormat format{true, 2, 2, "timestamp [ns], filename"};
  return readTimestampedRows<ImageEntry>(path, format, &parseImageRow, strict, diagnostics);
}

Result<std::filesystem::path> findMav0(const std::filesystem::path& path) {
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) {
    return Error{ErrorCode::kNotFound, "dataset folder '" + path.string() + "' does not exist"};
  }
  if (!std::filesystem::is_directory(path, ec)) {
    return Error{ErrorCode::kInvalidArgument, "'" + path.string() + "' is a file; expected the folder that holds mav0"};
  }
  if (std::filesystem::is_directory(path / "cam0", ec) ||
      std::filesystem::is_directory(path / "state_groundtruth_estimate0", ec)) {
    return path;
  }
  if (std::filesystem::is_directory(path / "mav0", ec)) return path / "mav0";
  return Error{ErrorCode::kNotFound, "'" + path.string() + "' is not a EuRoC/ASL sequence: expected " +
                                         (path / "mav0").string() +
                                         " with cam0/, imu0/ (and optionally cam1/, state_groundtruth_estimate0/)"};
}

Result<EurocSequence> EurocSequence::open(const std::filesystem::path& path, const EurocReaderOptions& options) {
  if (Status st = options.validate(); !st) return st.error();
  auto mav0 = findMav0(path);
  if (!mav0) return mav0.error();
  EurocSequence seq;
  seq.root_ = *mav0;
  Diagnostics& diag = seq.diagnostics_;
  std::error_code ec;

  for (const char* name : {"cam0", "cam1"}) {
    const std::filesystem::path folder = seq.root_ / name;
    if (!std::filesystem::is_directory(folder, ec)) {
      if (std::string(name) == "cam0") {
        return Error{ErrorCode::kNotFound, (folder).string() + ": missing; a sequence needs at least cam0"};
      }
      continue;
    }
    CameraStream stream;
    stream.folder = folder;
    auto calibration = readCameraCalibration(folder / "sensor.yaml", name);
    if (!calibration) return calibration.error();
    stream.calibration = std::move(*calibration);
    auto entries = readImageListCsv(folder / "data.csv", options.strict, diag);
    if (!entries) return entries.error();
    if (options.check_image_files) {
      const std::string csv = (folder / "data.csv").string();
      for (auto& entry : *entries) {
        if (std::filesystem::is_regular_file(folder / "data" / entry.filename, ec)) {
          stream.frames.push_back(std::move(entry));
          continue;
        }
        const std::string problem =
            "image '" + entry.filename + "' is listed but missing from " + (folder / "data").string();
        if (options.strict)
          return Error{ErrorCode::kNotFound, csv + ":" + std::to_string(entry.csv_line) + ": " + problem};
        diag.warn(csv, entry.csv_line, problem + "; frame skipped");
      }
    } else {
      stream.frames = std::move(*entries);
    }
    if (stream.frames.empty()) {
      return Error{ErrorCode::kDataError, (folder / "data.csv").string() + ": no usable image frames"};
    }
    seq.cameras_.push_back(std::move(stream));
  }

  const std::filesystem::path imu_folder = seq.root_ / "imu0";
  if (std::filesystem::is_directory(imu_folder, ec)) {
    auto calibration = readImuCalibration(imu_folder / "sensor.yaml");
    if (!calibration) return calibration.error();
    seq.imu_calibration_ = *calibration;
    auto samples = readImuCsv(imu_folder / "data.csv", options.strict, diag);
    if (!samples) return samples.error();
    if (samples->empty()) return Error{ErrorCode::kDataError, (imu_folder / "data.csv").string() + ": no IMU samples"};
    seq.imu_ = std::move(*samples);
  } else if (options.require_imu) {
    return Error{ErrorCode::kNotFound, imu_folder.string() +
                                           ": missing; visual-inertial input needs imu0 "
                                           "(or open with require_imu = false)"};
  }

  const std::filesystem::path gt_csv = seq.root_ / "state_groundtruth_estimate0" / "data.csv";
  if (std::filesystem::exists(gt_csv, ec)) {
    auto states = readGroundTruthCsv(gt_csv, options.strict, diag);
    if (!states) return states.error();
    seq.ground_truth_ = std::move(*states);
  }

  seq.rig_frames_ = pairFrames(seq.cameras_[0], seq.cam1(), options.stereo_max_dt_ns, diag);
  if (options.strict && !diag.empty()) {
    return Error{ErrorCode::kDataError, diag.findings().front().toString()};
  }
  return seq;
}

std::size_t EurocSequence::stereoPairCount() const {
  return static_cast<std::size_t>(
      std::count_if(rig_frames_.begin(), rig_frames_.end(), [](const RigFrame& f) { return f.cam1.has_value(); }));
}

Result<GrayImage> EurocSequence::loadImage(int camera, std::size_t frame) const {
  if (camera < 0 || camera >= cameraCount() || frame >= cameras_[static_cast<std::size_t>(camera)].frames.size()) {
    return Error{ErrorCode::kInvalidArgument,
                 "loadImage: no camera " + std::to_string(camera) + " frame " + std::to_string(frame)};
  }
  const CameraStream& cam = cameras_[static_cast<std::size_t>(camera)];
  auto image = readGrayImage(cam.imagePath(frame));
  if (!image) return image.error();
  if (image->width != cam.calibration.width || image->height != cam.calibration.height) {
    return Error{ErrorCode::kDataError, cam.imagePath(frame).string() + ": image is " + std::to_string(image->width) +
                                            "x" + std::to_string(image->height) + ", " + cam.calibration.name +
                                            "/sensor.yaml says " + std::to_string(cam.calibration.width) + "x" +
                                            std::to_string(cam.calibration.height)};
  }
  return image;
}

namespace {

Result<const CameraStream*> frameOf(const std::vector<CameraStream>& cameras, int camera, std::size_t frame) {
  if (camera < 0 || static_cast<std::size_t>(camera) >= cameras.size() ||
      frame >= cameras[static_cast<std::size_t>(camera)].frames.size()) {
    return Error{ErrorCode::kInvalidArgument,
                 "loadImageInto: no camera " + std::to_string(camera) + " frame " + std::to_string(frame)};
  }
  return &cameras[static_cast<std::size_t>(camera)];
}

}  // namespace

Status EurocSequence::loadImageInto(int camera, std::size_t frame, std::span<std::uint8_t> pixels) const {
  auto cam = frameOf(cameras_, camera, frame);
  if (!cam) return cam.error();
  const CameraStream& c = **cam;
  return readGrayImageInto(c.imagePath(frame), c.calibration.width, c.calibration.height, pixels);
}

Status EurocSequence::loadImageInto(int camera, std::size_t frame, std::span<std::uint8_t> pixels,
                                    GrayPngDecoder& png) const {
  auto cam = frameOf(cameras_, camera, frame);
  if (!cam) return cam.error();
  const CameraStream& c = **cam;
  return readGrayImageInto(c.imagePath(frame), c.calibration.width, c.calibration.height, pixels, png);
}

std::string EurocSequence::summary() const {
  std::ostringstream os;
  os << "EuRoC sequence " << root_.string() << "\n";
  for (const CameraStream& cam : cameras_) {
    const auto& f = cam.frames;
    os << "  " << cam.calibration.name << ": " << f.size() << " frames, " << cam.calibration.width << "x"
       << cam.calibration.height << " @ " << text::formatDouble(cam.calibration.rate_hz) << " Hz, "
       << seconds(f.front().t_ns) << " .. " << seconds(f.back().t_ns) << " s\n";
  }
  if (cam1() != nullptr) os << "  stereo pairs: " << stereoPairCount() << " of " << rig_frames_.size() << "\n";
  if (!imu_.empty()) {
    os << "  imu0: " << imu_.size() << " samples @ " << text::formatDouble(imu_calibration_->rate_hz) << " Hz, "
       << seconds(imu_.front().t_ns) << " .. " << seconds(imu_.back().t_ns) << " s\n";
  }
  if (!ground_truth_.empty()) {
    os << "  ground truth: " << ground_truth_.size() << " states"
       << (ground_truth_.front().has_velocity_and_biases ? " (pose, velocity, biases)" : " (pose only)") << ", "
       << seconds(ground_truth_.front().t_ns) << " .. " << seconds(ground_truth_.back().t_ns) << " s\n";
  }
  os << "  findings: " << diagnostics_.warningCount() << " warning(s), " << diagnostics_.errorCount() << " error(s)\n";
  return os.str();
}

}  // namespace cvislam::dataset

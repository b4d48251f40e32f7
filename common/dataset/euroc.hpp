// The EuRoC / ASL dataset layout: reading a sequence, and the CSV files it is made of.
//
//   SEQ/mav0/cam0/{data.csv, data/<t_ns>.png, sensor.yaml}     required
//   SEQ/mav0/cam1/...                                          optional (stereo)
//   SEQ/mav0/imu0/{data.csv, sensor.yaml}                      required unless require_imu = false
//   SEQ/mav0/state_groundtruth_estimate0/data.csv              optional
//
// Images are listed at open() and decoded only when asked for: a full sequence is gigabytes.
#pragma once

#include <cstdint>
#include <filesystem>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "common/core/diagnostics.hpp"
#include "common/core/result.hpp"
#include "common/dataset/image.hpp"
#include "common/dataset/types.hpp"

namespace cvislam::dataset {

struct EurocReaderOptions {
  bool strict = false;            // any defect (a bad row, a missing image) is an error instead of a warning
  bool require_imu = true;        // a sequence without imu0 is an error
  bool check_image_files = true;  // at open(), look for every listed image and drop (and report) missing ones
  // cam0 and cam1 frames whose timestamps differ by at most this much form a stereo pair.
  std::int64_t stereo_max_dt_ns = 1'000'000;

  [[nodiscard]] Status validate() const;
};

struct ImageEntry {
  std::int64_t t_ns = 0;
  std::string filename;       // relative to the camera's data/ folder
  std::int64_t csv_line = 0;  // where data.csv lists it, for error messages
};

struct CameraStream {
  CameraCalibration calibration;
  std::filesystem::path folder;    // .../mav0/camX
  std::vector<ImageEntry> frames;  // listed and present, time-ordered

  [[nodiscard]] std::filesystem::path imagePath(std::size_t frame) const {
    return folder / "data" / frames[frame].filename;
  }
};

// One time step of the camera rig: a cam0 frame and, when there is one, its cam1 partner.
struct RigFrame {
  std::int64_t t_ns = 0;
  std::size_t cam0 = 0;
  std::optional<std::size_t> cam1;
};

class EurocSequence {
 public:
  // `path` is the folder that holds mav0 (or mav0 itself).
  static Result<EurocSequence> open(const std::filesystem::path& path, const EurocReaderOptions& options = {});

  [[nodiscard]] const std::filesystem::path& root() const { return root_; }  // the mav0 folder
  [[nodiscard]] const CameraStream& cam0() const { return cameras_.front(); }
  [[nodiscard]] const CameraStream* cam1() const { return cameras_.size() > 1 ? &cameras_[1] : nullptr; }
  [[nodiscard]] const CameraStream& camera(int index) const { return cameras_.at(static_cast<std::size_t>(index)); }
  [[nodiscard]] int cameraCount() const { return static_cast<int>(cameras_.size()); }

  [[nodiscard]] const std::optional<ImuCalibration>& imuCalibration() const { return imu_calibration_; }
  [[nodiscard]] const std::vector<ImuSample>& imu() const { return imu_; }
  [[nodiscard]] const std::vector<GroundTruthState>& groundTruth() const { return ground_truth_; }

  // cam0 frames in time order, each with its cam1 partner when stereo.
  [[nodiscard]] const std::vector<RigFrame>& rigFrames() const { return rig_frames_; }
  [[nodiscard]] std::size_t stereoPairCount() const;

  // Everything found wrong but survivable while opening (missing images, skipped rows, unpaired frames).
  [[nodiscard]] const Diagnostics& diagnostics() const { return diagnostics_; }

  // Decodes one image. Errors name the file (missing since open(), unreadable, wrong size).
  [[nodiscard]] Result<GrayImage> loadImage(int camera, std::size_t frame) const;
  // Decodes into caller-owned storage of width*height bytes.
  [[nodiscard]] Status loadImageInto(int camera, std::size_t frame, std::span<std::uint8_t> pixels) const;
  // The same through the caller's PNG decoder (one per loading thread): 8-bit grey PNGs without OpenCV.
  [[nodiscard]] Status loadImageInto(int camera, std::size_t frame, std::span<std::uint8_t> pixels,
                                     GrayPngDecoder& png) const;

  // A few lines for humans: streams, rates, spans and findings.
  [[nodiscard]] std::string summary() const;

 private:
  EurocSequence() = default;

  std::filesystem::path root_;
  std::vector<CameraStream> cameras_;
  std::optional<ImuCalibration> imu_calibration_;
  std::vector<ImuSample> imu_;
  std::vector<GroundTruthState> ground_truth_;
  std::vector<RigFrame> rig_frames_;
  Diagnostics diagnostics_;
};

// The CSV files on their own (the evaluator reads ground truth without the rest of a sequence).
Result<std::vector<ImuSample>> readImuCsv(const std::filesystem::path& path, bool strict, Diagnostics& diagnostics);
// 17 columns (t, p, q wxyz, v, b_w, b_a) or 8 (t, p, q wxyz). `as_trajectory` keeps rows that repeat a
// timestamp (estimates written in this format do that); ground truth of a sequence must increase strictly.
Result<std::vector<GroundTruthState>> readGroundTruthCsv(const std::filesystem::path& path, bool strict,
                                                         Diagnostics& diagnostics, bool as_trajectory = false);
Result<std::vector<ImageEntry>> readImageListCsv(const std::filesystem::path& path, bool strict,
                                                 Diagnostics& diagnostics);

// cam0 frames (times ascending) each paired with the closest unused cam1 frame within max_dt_ns, when there is
// a cam1 stream. The counts are the frames of each camera left without a partner.
struct StereoPairing {
  std::vector<RigFrame> frames;
  std::size_t unpaired_cam0 = 0;
  std::size_t unpaired_cam1 = 0;
};
StereoPairing pairStereoFrames(std::span<const std::int64_t> cam0_t_ns,
                               std::optional<std::span<const std::int64_t>> cam1_t_ns, std::int64_t max_dt_ns);

// Locates the mav0 folder: `path` itself when it holds cam0 or state_groundtruth_estimate0, else path/mav0.
Result<std::filesystem::path> findMav0(const std::filesystem::path& path);

}  // namespace cvislam::dataset

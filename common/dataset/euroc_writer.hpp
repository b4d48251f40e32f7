// Writes a sequence in the EuRoC / ASL layout that EurocSequence reads (the simulator's output format).
#pragma once

#include <cstdint>
#include <filesystem>
#include <fstream>
#include <memory>
#include <optional>
#include <vector>

#include "common/core/result.hpp"
#include "common/dataset/image.hpp"
#include "common/dataset/types.hpp"

namespace cvislam::dataset {

struct EurocWriterOptions {
  std::vector<CameraCalibration> cameras;  // cam0 and optionally cam1; names are taken from their index
  std::optional<ImuCalibration> imu;       // imu0, if any
  bool ground_truth = true;                // state_groundtruth_estimate0
  bool overwrite = false;                  // allow writing into an existing mav0 folder

  [[nodiscard]] Status validate() const;
};

class EurocWriter {
 public:
  // Creates SEQ/mav0 with the sensor.yaml files and CSV headers.
  static Result<EurocWriter> create(const std::filesystem::path& sequence_folder, const EurocWriterOptions& options);

  EurocWriter(EurocWriter&&) noexcept;
  EurocWriter& operator=(EurocWriter&&) noexcept;
  ~EurocWriter();

  // Each stream's timestamps must increase strictly; the image must match the camera's resolution.
  Status addImage(int camera, std::int64_t t_ns, const GrayImage& image);
  Status addImu(const ImuSample& sample);
  Status addGroundTruth(const GroundTruthState& state);

  // Flushes and closes every file; reports a write failure (a full disk) here.
  Status close();

  [[nodiscard]] const std::filesystem::path& mav0() const;

 private:
  struct Impl;
  explicit EurocWriter(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace cvislam::dataset

// Reading typed fields from calibration YAML files (ASL sensor.yaml, Kalibr camchain and IMU files), with
// errors that name the file, the key and, where known, the line.
#pragma once

#include <filesystem>
#include <string>
#include <vector>

#include <yaml-cpp/yaml.h>
#include <Eigen/Core>

#include "common/core/result.hpp"
#include "common/dataset/types.hpp"
#include "common/geometry/lie.hpp"

namespace cvislam::dataset::yaml {

// Context for error messages: the file, plus the line of a YAML node when it has one.
struct YamlFile {
  std::string path;

  [[nodiscard]] Error error(const YAML::Node& node, const std::string& message) const;
  [[nodiscard]] Error missing(const std::string& key, const std::string& what) const;
};

// The file's top-level mapping. OpenCV's "%YAML:1.0" first line (ASL files) is accepted.
Result<YAML::Node> loadMapping(const std::filesystem::path& path);

Result<double> getNumber(const YamlFile& file, const YAML::Node& parent, const std::string& key,
                         const std::string& what);
// `node` is parent[key]; `key` names it in errors.
Result<std::vector<double>> getNumbers(const YamlFile& file, const YAML::Node& node, const std::string& key,
                                       std::size_t count, const std::string& what);
Result<std::string> getString(const YamlFile& file, const YAML::Node& parent, const std::string& key,
                              const std::string& what);
// A 4x4 homogeneous matrix as a rigid transform: last row [0 0 0 1], top-left block a rotation (projected onto
// SO(3) so that it is exactly orthonormal).
Result<geometry::SE3d> rigidTransform(const YamlFile& file, const YAML::Node& node, const std::string& key,
                                      const Eigen::Matrix4d& T);

// The key names of a pinhole camera's fields, which differ between ASL sensor.yaml and Kalibr.
struct PinholeKeys {
  const char* distortion_coefficients = "distortion_coefficients";
};
// camera_model (pinhole only), resolution, intrinsics, distortion_model and its coefficients into `camera`.
Status readPinhole(const YamlFile& file, const YAML::Node& parent, const PinholeKeys& keys, CameraCalibration& camera);

}  // namespace cvislam::dataset::yaml

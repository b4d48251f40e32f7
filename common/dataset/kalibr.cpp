#include "common/dataset/kalibr.hpp"

#include <cmath>

#include "common/dataset/calibration.hpp"
#include "common/dataset/yaml_fields.hpp"

namespace cvislam::dataset {
namespace {

using yaml::YamlFile;

// Kalibr writes matrices as a list of four rows of four numbers.
Result<geometry::SE3d> getMatrix(const YamlFile& file, const YAML::Node& parent, const std::string& key,
                                 const std::string& what) {
  const YAML::Node node = parent[key];
  if (!node) return file.missing(key, what);
  if (!node.IsSequence() || node.size() != 4) return file.error(node, key + " must be 4 rows of 4 numbers");
  Eigen::Matrix4d T;
  for (std::size_t r = 0; r < 4; ++r) {
    auto row = yaml::getNumbers(file, node[r], key + " row " + std::to_string(r + 1), 4, what);
    if (!row) return row.error();
    for (std::size_t c = 0; c < 4; ++c) T(static_cast<int>(r), static_cast<int>(c)) = (*row)[c];
  }
  return yaml::rigidTransform(file, node, key, T);
}

std::string optionalString(const YAML::Node& parent, const std::string& key) {
  const YAML::Node node = parent[key];
  return node && node.IsScalar() ? node.Scalar() : std::string();
}

Result<KalibrCamera> readCamera(const YamlFile& file, const YAML::Node& node, const std::string& name) {
  if (!node.IsMap()) return file.error(node, name + " must be a mapping of the camera's keys");
  const YamlFile camera_file{file.path + " (" + name + ")"};
  KalibrCamera camera;
  camera.calibration.name = name;
  camera.calibration.comment = "Kalibr " + name + " from " + file.path;
  if (Status st = yaml::readPinhole(camera_file, node, {"distortion_coeffs"}, camera.calibration); !st.ok()) {
    return st.error();
  }
  auto T_cam_imu = getMatrix(camera_file, node, "T_cam_imu", "IMU to camera, 4x4");
  if (!T_cam_imu) return T_cam_imu.error();
  camera.calibration.T_b_c = T_cam_imu->inverse();
  if (node["timeshift_cam_imu"]) {
    auto shift_s = yaml::getNumber(camera_file, node, "timeshift_cam_imu", "seconds, t_imu = t_cam + shift");
    if (!shift_s) return shift_s.error();
    if (!(std::abs(*shift_s) <= 1.0)) {
      return camera_file.error(node["timeshift_cam_imu"],
                               "timeshift_cam_imu must be within +-1 s, got " + std::to_string(*shift_s));
    }
    camera.timeshift_cam_imu_ns = static_cast<std::int64_t>(std::llround(*shift_s * 1e9));
  }
  camera.rostopic = optionalString(node, "rostopic");
  if (Status st = validate(camera.calibration); !st.ok()) return st.error().withContext(file.path);
  return camera;
}

}  // namespace

Result<std::vector<KalibrCamera>> readKalibrCamchain(const std::filesystem::path& path) {
  auto root = yaml::loadMapping(path);
  if (!root) return root.error();
  const YamlFile file{path.string()};
  std::vector<KalibrCamera> cameras;
  for (int i = 0;; ++i) {
    const std::string name = "cam" + std::to_string(i);
    const YAML::Node node = (*root)[name];
    if (!node) break;
    auto camera = readCamera(file, node, name);
    if (!camera) return camera.error();
    cameras.push_back(std::move(*camera));
  }
  if (cameras.empty()) {
    return Error{ErrorCode::kParseError,
                 path.string() + ": no camera: a Kalibr camera chain lists cam0 (and cam1, ...) at the top level"};
  }
  return cameras;
}

Result<KalibrImu> readKalibrImu(const std::filesystem::path& path) {
  auto root = yaml::loadMapping(path);
  if (!root) return root.error();
  const YamlFile file{path.string()};
  // Kalibr's newer files put the IMU under imu0; older ones have its keys at the top level.
  const YAML::Node imu = (*root)["imu0"] ? (*root)["imu0"] : *root;
  if (!imu.IsMap()) return file.error(imu, "imu0 must be a mapping of the IMU's keys");
  KalibrImu out;
  out.calibration.comment = "Kalibr IMU from " + path.string();
  const std::pair<const char*, double*> fields[] = {
      {"update_rate", &out.calibration.rate_hz},
      {"gyroscope_noise_density", &out.calibration.gyro_noise_density},
      {"gyroscope_random_walk", &out.calibration.gyro_random_walk},
      {"accelerometer_noise_density", &out.calibration.accel_noise_density},
      {"accelerometer_random_walk", &out.calibration.accel_random_walk},
  };
  for (const auto& [key, target] : fields) {
    auto value = yaml::getNumber(file, imu, key, "IMU noise model, continuous time");
    if (!value) return value.error();
    *target = *value;
  }
  out.rostopic = optionalString(imu, "rostopic");
  if (Status st = validate(out.calibration); !st.ok()) return st.error().withContext(path.string());
  return out;
}

}  // namespace cvislam::dataset

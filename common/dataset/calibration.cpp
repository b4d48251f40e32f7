#include "common/dataset/calibration.hpp"

#include <cmath>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "common/core/text.hpp"
#include "common/dataset/yaml_fields.hpp"

namespace cvislam::dataset {
namespace {

using yaml::getNumber;
using yaml::getNumbers;
using yaml::YamlFile;

// T_BS: {rows: 4, cols: 4, data: [16 numbers, row-major]} with a rigid top-left block.
Result<geometry::SE3d> getExtrinsics(const YamlFile& file, const YAML::Node& root) {
  const YAML::Node node = root["T_BS"];
  if (!node) return file.missing("T_BS", "4x4 sensor-to-body transform");
  if (!node.IsMap()) return file.error(node, "key 'T_BS' must be a mapping with rows, cols and data");
  auto rows = getNumber(file, node, "rows", "must be 4");
  auto cols = getNumber(file, node, "cols", "must be 4");
  if (!rows) return rows.error();
  if (!cols) return cols.error();
  if (*rows != 4.0 || *cols != 4.0) return file.error(node, "T_BS must be 4x4");
  auto data = getNumbers(file, node["data"], "T_BS.data", 16, "row-major 4x4 matrix");
  if (!data) return data.error();
  Eigen::Matrix4d T;
  for (int r = 0; r < 4; ++r) {
    for (int c = 0; c < 4; ++c) T(r, c) = (*data)[4 * static_cast<std::size_t>(r) + static_cast<std::size_t>(c)];
  }
  return yaml::rigidTransform(file, node, "T_BS", T);
}

std::string optionalComment(const YAML::Node& root) {
  const YAML::Node node = root["comment"];
  return node && node.IsScalar() ? node.Scalar() : std::string();
}

std::string listOf(const double* values, std::size_t n) {
  std::string out = "[";
  for (std::size_t i = 0; i < n; ++i) {
    if (i > 0) out += ", ";
    out += text::formatDouble(values[i]);
  }
  return out + "]";
}

std::string extrinsicsYaml(const geometry::SE3d& T) {
  const Eigen::Matrix4d M = T.matrix();
  std::string out = "T_BS:\n  cols: 4\n  rows: 4\n  data: [";
  for (int r = 0; r < 4; ++r) {
    for (int c = 0; c < 4; ++c) {
      out += text::formatDouble(M(r, c));
      if (r < 3 || c < 3) out += (c == 3 ? ",\n         " : ", ");
    }
  }
  return out + "]\n";
}

Status writeText(const std::filesystem::path& path, const std::string& contents) {
  std::error_code ec;
  std::filesystem::create_directories(path.parent_path(), ec);
  std::ofstream out(path, std::ios::binary);
  out << contents;
  out.close();
  if (!out) return Error{ErrorCode::kIoError, path.string() + ": cannot write"};
  return Status::Ok();
}

}  // namespace

std::string_view toString(DistortionModel model) {
  switch (model) {
    case DistortionModel::kNone:
      return "none";
    case DistortionModel::kRadialTangential:
      return "radial-tangential";
    case DistortionModel::kEquidistant:
      return "equidistant";
  }
  return "unknown";
}

Status validate(const CameraCalibration& camera) {
  const auto bad = [&](const std::string& message) {
    return Error{ErrorCode::kInvalidArgument, camera.name + ": " + message};
  };
  if (camera.width <= 0 || camera.height <= 0 || camera.width > 16384 || camera.height > 16384) {
    return bad("resolution must be positive and at most 16384, got " + std::to_string(camera.width) + "x" +
               std::to_string(camera.height));
  }
  if (!(camera.rate_hz > 0.0)) return bad("rate_hz must be > 0");
  if (!(camera.fx > 0.0 && camera.fy > 0.0)) return bad("focal lengths fu, fv must be > 0");
  if (!(camera.cx >= 0.0 && camera.cx <= camera.width && camera.cy >= 0.0 && camera.cy <= camera.height)) {
    return bad("principal point (cu, cv) must lie inside the " + std::to_string(camera.width) + "x" +
               std::to_string(camera.height) + " image");
  }
  for (double k : camera.distortion_coefficients) {
    if (!std::isfinite(k) || std::abs(k) > 10.0) return bad("distortion coefficients must be finite and |k| <= 10");
  }
  return Status::Ok();
}

Status validate(const ImuCalibration& imu) {
  const auto bad = [](const std::string& message) { return Error{ErrorCode::kInvalidArgument, "imu0: " + message}; };
  if (!(imu.rate_hz > 0.0)) return bad("rate_hz must be > 0");
  if (!(imu.gyro_noise_density > 0.0)) return bad("gyroscope_noise_density must be > 0");
  if (!(imu.gyro_random_walk > 0.0)) return bad("gyroscope_random_walk must be > 0");
  if (!(imu.accel_noise_density > 0.0)) return bad("accelerometer_noise_density must be > 0");
  if (!(imu.accel_random_walk > 0.0)) return bad("accelerometer_random_walk must be > 0");
  return Status::Ok();
}

Result<CameraCalibration> readCameraCalibration(const std::filesystem::path& sensor_yaml, const std::string& name) {
  auto root = yaml::loadMapping(sensor_yaml);
  if (!root) return root.error();
  const YamlFile file{sensor_yaml.string()};
  CameraCalibration camera;
  camera.name = name;
  camera.comment = optionalComment(*root);

  auto rate = getNumber(file, *root, "rate_hz", "frame rate");
  if (!rate) return rate.error();
  camera.rate_hz = *rate;
  if (Status st = yaml::readPinhole(file, *root, {}, camera); !st.ok()) return st.error();
  auto extrinsics = getExtrinsics(file, *root);
  if (!extrinsics) return extrinsics.error();
  camera.T_b_c = *extrinsics;
  if (Status st = validate(camera); !st) return st.error().withContext(file.path);
  return camera;
}

Result<ImuCalibration> readImuCalibration(const std::filesystem::path& sensor_yaml) {
  auto root = yaml::loadMapping(sensor_yaml);
  if (!root) return root.error();
  const YamlFile file{sensor_yaml.string()};
  ImuCalibration imu;
  imu.comment = optionalComment(*root);
  const std::pair<const char*, double*> fields[] = {
      {"rate_hz", &imu.rate_hz},
      {"gyroscope_noise_density", &imu.gyro_noise_density},
      {"gyroscope_random_walk", &imu.gyro_random_walk},
      {"accelerometer_noise_density", &imu.accel_noise_density},
      {"accelerometer_random_walk", &imu.accel_random_walk},
  };
  for (const auto& [key, target] : fields) {
    auto value = getNumber(file, *root, key, "IMU noise model");
    if (!value) return value.error();
    *target = *value;
  }
  auto extrinsics = getExtrinsics(file, *root);
  if (!extrinsics) return extrinsics.error();
  imu.T_b_i = *extrinsics;
  if (Status st = validate(imu); !st) return st.error().withContext(file.path);
  return imu;
}

namespace {

// A YAML double-quoted scalar: free text (a comment may hold ':' or '#') survives the round trip.
std::string yamlQuoted(const std::string& value) {
  std::string out = "\"";
  for (const char c : value) {
    switch (c) {
      case '"':
        out += "\\\"";
        break;
      case '\\':
        out += "\\\\";
        break;
      case '\n':
        out += "\\n";
        break;
      case '\t':
        out += "\\t";
        break;
      case '\r':
        out += "\\r";
        break;
      default:
        out += c;
    }
  }
  return out + "\"";
}

}  // namespace

Status writeCameraCalibration(const std::filesystem::path& sensor_yaml, const CameraCalibration& camera) {
  if (Status st = validate(camera); !st) return st;
  std::string out = "%YAML:1.0\n# General sensor definitions.\nsensor_type: camera\n";
  out += "comment: " + yamlQuoted(camera.comment.empty() ? camera.name : camera.comment) + "\n\n";
  out += "# Sensor extrinsics wrt. the body-frame.\n" + extrinsicsYaml(camera.T_b_c) + "\n";
  out += "# Camera specific definitions.\n";
  out += "rate_hz: " + text::formatDouble(camera.rate_hz) + "\n";
  out += "resolution: [" + std::to_string(camera.width) + ", " + std::to_string(camera.height) + "]\n";
  out += "camera_model: pinhole\n";
  const double intrinsics[] = {camera.fx, camera.fy, camera.cx, camera.cy};
  out += "intrinsics: " + listOf(intrinsics, 4) + " #fu, fv, cu, cv\n";
  out += "distortion_model: " + std::string(toString(camera.distortion)) + "\n";
  out += "distortion_coefficients: " + listOf(camera.distortion_coefficients.data(), 4) + "\n";
  return writeText(sensor_yaml, out);
}

Status writeImuCalibration(const std::filesystem::path& sensor_yaml, const ImuCalibration& imu) {
  if (Status st = validate(imu); !st) return st;
  std::string out = "%YAML:1.0\nsensor_type: imu\n";
  out += "comment: " + yamlQuoted(imu.comment.empty() ? std::string("imu0") : imu.comment) + "\n\n";
  out += "# Sensor extrinsics wrt. the body-frame.\n" + extrinsicsYaml(imu.T_b_i);
  out += "rate_hz: " + text::formatDouble(imu.rate_hz) + "\n\n";
  out += "# inertial sensor noise model parameters (static)\n";
  out += "gyroscope_noise_density: " + text::formatDouble(imu.gyro_noise_density) + "  # [ rad / s / sqrt(Hz) ]\n";
  out += "gyroscope_random_walk: " + text::formatDouble(imu.gyro_random_walk) + "  # [ rad / s^2 / sqrt(Hz) ]\n";
  out += "accelerometer_noise_density: " + text::formatDouble(imu.accel_noise_density) + "  # [ m / s^2 / sqrt(Hz) ]\n";
  out += "accelerometer_random_walk: " + text::formatDouble(imu.accel_random_walk) + "  # [ m / s^3 / sqrt(Hz) ]\n";
  return writeText(sensor_yaml, out);
}

}  // namespace cvislam::dataset

#include "common/dataset/calibration.hpp"

#include <cmath>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include <yaml-cpp/yaml.h>
#include <Eigen/SVD>

#include "common/core/text.hpp"

namespace cvislam::dataset {
namespace {

// Context for error messages: the file, plus the line of a YAML node when it has one.
struct YamlFile {
  std::string path;

  [[nodiscard]] Error error(const YAML::Node& node, const std::string& message) const {
    std::string where = path;
    if (node.IsDefined() && node.Mark().line >= 0) where += ":" + std::to_string(node.Mark().line + 1);
    return Error{ErrorCode::kParseError, where + ": " + message};
  }
  [[nodiscard]] Error missing(const std::string& key, const std::string& what) const {
    return Error{ErrorCode::kParseError, path + ": missing key '" + key + "' (" + what + ")"};
  }
};

Result<YAML::Node> loadYaml(const std::filesystem::path& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return Error{ErrorCode::kNotFound, path.string() + ": sensor.yaml does not exist"};
  }
  std::ifstream in(path);
  if (!in) return Error{ErrorCode::kIoError, path.string() + ": cannot open for reading"};
  std::stringstream ss;
  ss << in.rdbuf();
  std::string text = ss.str();
  // ASL files start with OpenCV's "%YAML:1.0", which is not a YAML directive; blank it out, keeping the
  // line so that reported line numbers still match the file.
  if (text.rfind("%YAML:", 0) == 0) text.replace(0, text.find('\n'), "");
  try {
    YAML::Node root = YAML::Load(text);
    if (!root.IsMap()) return Error{ErrorCode::kParseError, path.string() + ": expected a YAML mapping of keys"};
    return root;
  } catch (const YAML::Exception& e) {
    return Error{ErrorCode::kParseError,
                 path.string() + ":" + std::to_string(e.mark.line + 1) + ": invalid YAML: " + e.msg};
  }
}

Result<double> getNumber(const YamlFile& file, const YAML::Node& root, const std::string& key,
                         const std::string& what) {
  const YAML::Node node = root[key];
  if (!node) return file.missing(key, what);
  if (!node.IsScalar()) return file.error(node, "key '" + key + "' must be a number (" + what + ")");
  const auto value = text::parseDouble(node.Scalar());
  if (!value) return file.error(node, "key '" + key + "' must be a number (" + what + "), got '" + node.Scalar() + "'");
  return *value;
}

Result<std::vector<double>> getNumbers(const YamlFile& file, const YAML::Node& node, const std::string& key,
                                       std::size_t count, const std::string& what) {
  if (!node) return file.missing(key, what);
  if (!node.IsSequence() || node.size() != count) {
    return file.error(node, "key '" + key + "' must be a list of " + std::to_string(count) + " numbers (" + what + ")" +
                                (node.IsSequence() ? ", got " + std::to_string(node.size()) : std::string()));
  }
  std::vector<double> values;
  for (std::size_t i = 0; i < count; ++i) {
    const auto value = node[i].IsScalar() ? text::parseDouble(node[i].Scalar()) : std::nullopt;
    if (!value) return file.error(node, "key '" + key + "': element " + std::to_string(i + 1) + " is not a number");
    values.push_back(*value);
  }
  return values;
}

Result<std::string> getString(const YamlFile& file, const YAML::Node& root, const std::string& key,
                              const std::string& what) {
  const YAML::Node node = root[key];
  if (!node) return file.missing(key, what);
  if (!node.IsScalar()) return file.error(node, "key '" + key + "' must be text (" + what + ")");
  return node.Scalar();
}

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
  if ((T.row(3) - Eigen::RowVector4d(0, 0, 0, 1)).cwiseAbs().maxCoeff() > 1e-9) {
    return file.error(node, "T_BS: the last row must be [0, 0, 0, 1]");
  }
  const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
  const double orthonormality_error = (R.transpose() * R - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
  if (orthonormality_error > 1e-3 || R.determinant() <= 0.0) {
    return file.error(node, "T_BS: the top-left 3x3 block is not a rotation (|R^T R - I| = " +
                                text::formatDouble(orthonormality_error) +
                                ", det = " + text::formatDouble(R.determinant()) + ")");
  }
  // Project onto SO(3) so that the stored rotation is exactly orthonormal.
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(R, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Matrix3d R_projected = svd.matrixU() * svd.matrixV().transpose();
  return geometry::SE3d(geometry::SO3d(R_projected), T.topRightCorner<3, 1>());
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
  auto root = loadYaml(sensor_yaml);
  if (!root) return root.error();
  const YamlFile file{sensor_yaml.string()};
  CameraCalibration camera;
  camera.name = name;
  camera.comment = optionalComment(*root);

  auto model = getString(file, *root, "camera_model", "e.g. pinhole");
  if (!model) return model.error();
  if (*model != "pinhole") {
    return file.error((*root)["camera_model"], "camera_model '" + *model + "' is not supported (use pinhole)");
  }
  auto rate = getNumber(file, *root, "rate_hz", "frame rate");
  if (!rate) return rate.error();
  camera.rate_hz = *rate;
  auto resolution = getNumbers(file, (*root)["resolution"], "resolution", 2, "width, height");
  if (!resolution) return resolution.error();
  if ((*resolution)[0] != std::floor((*resolution)[0]) || (*resolution)[1] != std::floor((*resolution)[1])) {
    return file.error((*root)["resolution"], "resolution must be whole pixels");
  }
  camera.width = static_cast<int>((*resolution)[0]);
  camera.height = static_cast<int>((*resolution)[1]);
  auto intrinsics = getNumbers(file, (*root)["intrinsics"], "intrinsics", 4, "fu, fv, cu, cv");
  if (!intrinsics) return intrinsics.error();
  camera.fx = (*intrinsics)[0];
  camera.fy = (*intrinsics)[1];
  camera.cx = (*intrinsics)[2];
  camera.cy = (*intrinsics)[3];

  auto distortion = getString(file, *root, "distortion_model", "radial-tangential or equidistant");
  if (!distortion) return distortion.error();
  if (*distortion == "radial-tangential" || *distortion == "radtan") {
    camera.distortion = DistortionModel::kRadialTangential;
  } else if (*distortion == "equidistant") {
    camera.distortion = DistortionModel::kEquidistant;
  } else if (*distortion == "none") {
    camera.distortion = DistortionModel::kNone;
  } else {
    return file.error((*root)["distortion_model"],
                      "distortion_model '" + *distortion + "' is not supported (radial-tangential, equidistant, none)");
  }
  if (camera.distortion != DistortionModel::kNone) {
    auto coefficients =
        getNumbers(file, (*root)["distortion_coefficients"], "distortion_coefficients", 4,
                   camera.distortion == DistortionModel::kEquidistant ? "k1, k2, k3, k4" : "k1, k2, p1, p2");
    if (!coefficients) return coefficients.error();
    for (std::size_t i = 0; i < 4; ++i) camera.distortion_coefficients[i] = (*coefficients)[i];
  }
  auto extrinsics = getExtrinsics(file, *root);
  if (!extrinsics) return extrinsics.error();
  camera.T_b_c = *extrinsics;
  if (Status st = validate(camera); !st) return st.error().withContext(file.path);
  return camera;
}

Result<ImuCalibration> readImuCalibration(const std::filesystem::path& sensor_yaml) {
  auto root = loadYaml(sensor_yaml);
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

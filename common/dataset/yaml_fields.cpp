#include "common/dataset/yaml_fields.hpp"

#include <cmath>
#include <fstream>
#include <sstream>

#include <Eigen/SVD>

#include "common/core/text.hpp"

namespace cvislam::dataset::yaml {

Error YamlFile::error(const YAML::Node& node, const std::string& message) const {
  std::string where = path;
  if (node.IsDefined() && node.Mark().line >= 0) where += ":" + std::to_string(node.Mark().line + 1);
  return Error{ErrorCode::kParseError, where + ": " + message};
}

Error YamlFile::missing(const std::string& key, const std::string& what) const {
  return Error{ErrorCode::kParseError, path + ": missing key '" + key + "' (" + what + ")"};
}

Result<YAML::Node> loadMapping(const std::filesystem::path& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return Error{ErrorCode::kNotFound, path.string() + ": the file does not exist"};
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

Result<double> getNumber(const YamlFile& file, const YAML::Node& parent, const std::string& key,
                         const std::string& what) {
  const YAML::Node node = parent[key];
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

Result<std::string> getString(const YamlFile& file, const YAML::Node& parent, const std::string& key,
                              const std::string& what) {
  const YAML::Node node = parent[key];
  if (!node) return file.missing(key, what);
  if (!node.IsScalar()) return file.error(node, "key '" + key + "' must be text (" + what + ")");
  return node.Scalar();
}

Result<geometry::SE3d> rigidTransform(const YamlFile& file, const YAML::Node& node, const std::string& key,
                                      const Eigen::Matrix4d& T) {
  if ((T.row(3) - Eigen::RowVector4d(0, 0, 0, 1)).cwiseAbs().maxCoeff() > 1e-9) {
    return file.error(node, key + ": the last row must be [0, 0, 0, 1]");
  }
  const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
  const double orthonormality_error = (R.transpose() * R - Eigen::Matrix3d::Identity()).cwiseAbs().maxCoeff();
  if (!T.allFinite() || orthonormality_error > 1e-3 || R.determinant() <= 0.0) {
    return file.error(node, key + ": the top-left 3x3 block is not a rotation (|R^T R - I| = " +
                                text::formatDouble(orthonormality_error) +
                                ", det = " + text::formatDouble(R.determinant()) + ")");
  }
  // Project onto SO(3) so that the stored rotation is exactly orthonormal.
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(R, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Matrix3d R_projected = svd.matrixU() * svd.matrixV().transpose();
  return geometry::SE3d(geometry::SO3d(R_projected), T.topRightCorner<3, 1>());
}

Status readPinhole(const YamlFile& file, const YAML::Node& parent, const PinholeKeys& keys, CameraCalibration& camera) {
  auto model = getString(file, parent, "camera_model", "e.g. pinhole");
  if (!model) return model.error();
  if (*model != "pinhole") {
    return file.error(parent["camera_model"], "camera_model '" + *model + "' is not supported (use pinhole)");
  }
  auto resolution = getNumbers(file, parent["resolution"], "resolution", 2, "width, height");
  if (!resolution) return resolution.error();
  if ((*resolution)[0] != std::floor((*resolution)[0]) || (*resolution)[1] != std::floor((*resolution)[1])) {
    return file.error(parent["resolution"], "resolution must be whole pixels");
  }
  camera.width = static_cast<int>((*resolution)[0]);
  camera.height = static_cast<int>((*resolution)[1]);
  auto intrinsics = getNumbers(file, parent["intrinsics"], "intrinsics", 4, "fu, fv, cu, cv");
  if (!intrinsics) return intrinsics.error();
  camera.fx = (*intrinsics)[0];
  camera.fy = (*intrinsics)[1];
  camera.cx = (*intrinsics)[2];
  camera.cy = (*intrinsics)[3];

  auto distortion = getString(file, parent, "distortion_model", "radial-tangential or equidistant");
  if (!distortion) return distortion.error();
  if (*distortion == "radial-tangential" || *distortion == "radtan") {
    camera.distortion = DistortionModel::kRadialTangential;
  } else if (*distortion == "equidistant") {
    camera.distortion = DistortionModel::kEquidistant;
  } else if (*distortion == "none") {
    camera.distortion = DistortionModel::kNone;
  } else {
    return file.error(parent["distortion_model"],
                      "distortion_model '" + *distortion + "' is not supported (radial-tangential, equidistant, none)");
  }
  if (camera.distortion != DistortionModel::kNone) {
    auto coefficients =
        getNumbers(file, parent[keys.distortion_coefficients], keys.distortion_coefficients, 4,
                   camera.distortion == DistortionModel::kEquidistant ? "k1, k2, k3, k4" : "k1, k2, p1, p2");
    if (!coefficients) return coefficients.error();
    for (std::size_t i = 0; i < 4; ++i) camera.distortion_coefficients[i] = (*coefficients)[i];
  }
  return Status::Ok();
}

}  // namespace cvislam::dataset::yaml

// The camera models against OpenCV's independent implementations (projectPoints, fisheye::projectPoints),
// their Jacobians against numeric differentiation, undistortion round trips, and the built-in EuRoC values.
#include "common/camera/camera_model.hpp"

#include <algorithm>
#include <random>
#include <string>
#include <vector>

#include <gtest/gtest.h>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>

#include "common/dataset/calibration.hpp"
#include "common/dataset/euroc_calibration.hpp"
#include "test/support/calibration_checks.hpp"
#include "test/support/numeric_diff.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::camera {
namespace {

using Eigen::Vector2d;
using Eigen::Vector3d;

// A wide-angle camera with Kalibr-like equidistant coefficients (TUM-VI's) on EuRoC's image size, with the
// focal length chosen so that the image corners stay in front of the camera (about 73 deg off axis).
dataset::CameraCalibration equidistantCamera() {
  dataset::CameraCalibration cal = dataset::eurocCam0();
  cal.name = "fisheye";
  cal.fx = 350.0;
  cal.fy = 350.0;
  cal.cx = 376.0;
  cal.cy = 240.0;
  cal.distortion = dataset::DistortionModel::kEquidistant;
  cal.distortion_coefficients = {0.0034823894, 0.0007150348, -0.0020532361, 0.0002029367};
  return cal;
}

std::vector<cv::Point3d> randomPointsInView(double half_width, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> unit(-1.0, 1.0);
  std::uniform_real_distribution<double> depth(0.5, 20.0);
  std::vector<cv::Point3d> points;
  for (int i = 0; i < 500; ++i) {
    const double z = depth(rng);
    points.emplace_back(half_width * unit(rng) * z, 0.7 * half_width * unit(rng) * z, z);
  }
  return points;
}

class CameraModelTest : public ::testing::TestWithParam<dataset::CameraCalibration> {};

TEST_P(CameraModelTest, UnprojectInvertsProjectAcrossTheWholeImage) {
  auto sut = CameraModel::create(GetParam());
  ASSERT_TRUE(sut.ok()) << sut.error().toString();
  for (int y = 0; y < sut->height(); y += 17) {
    for (int x = 0; x < sut->width(); x += 19) {
      const Vector2d pixel(x, y);
      const Vector3d ray = sut->unproject(pixel);
      EXPECT_NEAR(ray.norm(), 1.0, 1e-12);
      const auto back = sut->project(3.7 * ray);
      ASSERT_TRUE(back.has_value());
      EXPECT_LT((*back - pixel).norm(), 1e-8) << "pixel " << x << "," << y;
    }
  }
}

TEST_P(CameraModelTest, ProjectionJacobianMatchesNumeric) {
  auto sut = CameraModel::create(GetParam());
  ASSERT_TRUE(sut.ok());
  for (const cv::Point3d& p : randomPointsInView(0.8, 5)) {
    const Vector3d p_c(p.x, p.y, p.z);
    Eigen::Matrix<double, 2, 3> J;
    ASSERT_TRUE(sut->project(p_c, &J).has_value());
    const Eigen::Matrix<double, 2, 3> J_numeric =
        test::numericJacobian<2, 3>([&](const Vector3d& q) { return *sut->project(q); }, p_c, 1e-7);
    EXPECT_LT((J - J_numeric).cwiseAbs().maxCoeff(), 1e-5 * std::max(1.0, J_numeric.cwiseAbs().maxCoeff()));
  }
}

TEST_P(CameraModelTest, UndistortedPixelsAreWhatAnIdealPinholeSees) {
  auto sut = CameraModel::create(GetParam());
  ASSERT_TRUE(sut.ok());
  const dataset::CameraCalibration& cal = GetParam();
  std::vector<Vector2d> measured;
  std::vector<Vector2d> ideal;
  for (const cv::Point3d& p : randomPointsInView(0.6, 6)) {
    const Vector3d p_c(p.x, p.y, p.z);
    measured.push_back(*sut->project(p_c));
    ideal.emplace_back(cal.fx * p.x / p.z + cal.cx, cal.fy * p.y / p.z + cal.cy);
  }
  std::vector<Vector2d> undistorted(measured.size());
  sut->undistortPixels(measured, undistorted);
  for (std::size_t i = 0; i < measured.size(); ++i) EXPECT_LT((undistorted[i] - ideal[i]).norm(), 1e-7);
}

INSTANTIATE_TEST_SUITE_P(Models, CameraModelTest,
                         ::testing::Values(dataset::eurocCam0(), equidistantCamera(),
                                           [] {
                                             dataset::CameraCalibration pinhole = dataset::eurocCam0();
                                             pinhole.distortion = dataset::DistortionModel::kNone;
                                             return pinhole;
                                           }()),
                         [](const auto& param_info) {
                           std::string name(dataset::toString(param_info.param.distortion));
                           std::replace(name.begin(), name.end(), '-', '_');
                           return name;
                         });

// OpenCV's projectPoints is an independent implementation of the same model and pixel convention.
TEST(CameraModel, RadialTangentialProjectsLikeOpenCvProjectPoints) {
  const dataset::CameraCalibration cal = dataset::eurocCam0();
  auto sut = CameraModel::create(cal);
  ASSERT_TRUE(sut.ok());
  const std::vector<cv::Point3d> points = randomPointsInView(1.0, 23);
  const cv::Matx33d K(cal.fx, 0.0, cal.cx, 0.0, cal.fy, cal.cy, 0.0, 0.0, 1.0);
  const auto& k = cal.distortion_coefficients;
  const std::vector<double> dist = {k[0], k[1], k[2], k[3]};
  std::vector<cv::Point2d> reference;
  cv::projectPoints(points, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), K, dist, reference);
  for (std::size_t i = 0; i < points.size(); ++i) {
    const auto projected = sut->project(Vector3d(points[i].x, points[i].y, points[i].z));
    ASSERT_TRUE(projected.has_value());
    EXPECT_NEAR(projected->x(), reference[i].x, 1e-6);
    EXPECT_NEAR(projected->y(), reference[i].y, 1e-6);
  }
}

TEST(CameraModel, EquidistantProjectsLikeOpenCvFisheye) {
  const dataset::CameraCalibration cal = equidistantCamera();
  auto sut = CameraModel::create(cal);
  ASSERT_TRUE(sut.ok());
  const std::vector<cv::Point3d> points = randomPointsInView(2.0, 24);  // up to ~70 deg off axis
  const cv::Matx33d K(cal.fx, 0.0, cal.cx, 0.0, cal.fy, cal.cy, 0.0, 0.0, 1.0);
  const auto& k = cal.distortion_coefficients;
  const cv::Vec4d dist(k[0], k[1], k[2], k[3]);
  std::vector<cv::Point2d> reference;
  cv::fisheye::projectPoints(points, reference, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), K, dist);
  for (std::size_t i = 0; i < points.size(); ++i) {
    const auto projected = sut->project(Vector3d(points[i].x, points[i].y, points[i].z));
    ASSERT_TRUE(projected.has_value());
    EXPECT_NEAR(projected->x(), reference[i].x, 1e-6);
    EXPECT_NEAR(projected->y(), reference[i].y, 1e-6);
  }
}

TEST(CameraModel, PointsBehindTheCameraDoNotProject) {
  auto sut = CameraModel::create(dataset::eurocCam0());
  ASSERT_TRUE(sut.ok());
  EXPECT_FALSE(sut->project(Vector3d(0.1, 0.2, -1.0)).has_value());
  EXPECT_FALSE(sut->project(Vector3d(0.1, 0.2, 0.0)).has_value());
}

TEST(CameraModel, BadCalibrationIsRefusedNamingTheCameraAndTheField) {
  dataset::CameraCalibration cal = dataset::eurocCam0();
  cal.fx = -1.0;
  auto negative_focal = CameraModel::create(cal);
  ASSERT_FALSE(negative_focal.ok());
  EXPECT_NE(negative_focal.error().message().find("camera 'cam0'"), std::string::npos);
  EXPECT_NE(negative_focal.error().message().find("fx"), std::string::npos);
  cal = dataset::eurocCam0();
  cal.distortion_coefficients[1] = std::nan("");
  EXPECT_FALSE(CameraModel::create(cal).ok());
}

void expectSameCamera(const dataset::CameraCalibration& built_in, const dataset::CameraCalibration& file) {
  test::expectSameIntrinsics(built_in, file);
  EXPECT_DOUBLE_EQ(built_in.rate_hz, file.rate_hz);
  EXPECT_LT((built_in.T_b_c.matrix() - file.T_b_c.matrix()).cwiseAbs().maxCoeff(), 1e-9);
}

TEST(EurocDefaults, BuiltInCalibrationEqualsTheSharedSensorYaml) {
  CVISLAM_REQUIRE_DATA(root, "euroc-calibration/asl_sensor_yaml");
  auto cam0 = dataset::readCameraCalibration(root / "cam0_sensor.yaml", "cam0");
  auto cam1 = dataset::readCameraCalibration(root / "cam1_sensor.yaml", "cam1");
  auto imu = dataset::readImuCalibration(root / "imu0_sensor.yaml");
  ASSERT_TRUE(cam0.ok() && cam1.ok() && imu.ok());
  expectSameCamera(dataset::eurocCam0(), *cam0);
  expectSameCamera(dataset::eurocCam1(), *cam1);
  const dataset::ImuCalibration built_in = dataset::eurocImu();
  EXPECT_DOUBLE_EQ(built_in.rate_hz, imu->rate_hz);
  EXPECT_DOUBLE_EQ(built_in.gyro_noise_density, imu->gyro_noise_density);
  EXPECT_DOUBLE_EQ(built_in.gyro_random_walk, imu->gyro_random_walk);
  EXPECT_DOUBLE_EQ(built_in.accel_noise_density, imu->accel_noise_density);
  EXPECT_DOUBLE_EQ(built_in.accel_random_walk, imu->accel_random_walk);
}

}  // namespace
}  // namespace cvislam::camera

#include "test/sim/camera_model.hpp"

#include <gtest/gtest.h>
#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>

#include "common/dataset/calibration.hpp"
#include "test/sim/random.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::sim {
namespace {

TEST(CameraModel, UnprojectInvertsProjectAcrossTheWholeImage) {
  auto sut = CameraModel::create(eurocCam0());
  ASSERT_TRUE(sut.ok());
  for (int y = 0; y < sut->height(); y += 17) {
    for (int x = 0; x < sut->width(); x += 19) {
      const Eigen::Vector2d pixel(x, y);
      const Eigen::Vector3d ray = sut->unproject(pixel);
      EXPECT_NEAR(ray.norm(), 1.0, 1e-12);
      const auto back = sut->project(3.7 * ray);
      ASSERT_TRUE(back.has_value());
      EXPECT_LT((*back - pixel).norm(), 1e-8) << "pixel " << x << "," << y;
    }
  }
}

// OpenCV's projectPoints is an independent implementation of the same model and pixel convention.
TEST(CameraModel, ProjectsLikeOpenCvProjectPoints) {
  const dataset::CameraCalibration cal = eurocCam0();
  auto sut = CameraModel::create(cal);
  ASSERT_TRUE(sut.ok());
  Rng rng(23);
  std::vector<cv::Point3d> points;
  for (int i = 0; i < 500; ++i) {
    const double z = rng.uniform(0.5, 20.0);
    points.emplace_back(rng.uniform(-1.0, 1.0) * z, rng.uniform(-0.7, 0.7) * z, z);
  }
  const cv::Matx33d K(cal.fx, 0.0, cal.cx, 0.0, cal.fy, cal.cy, 0.0, 0.0, 1.0);
  const auto& k = cal.distortion_coefficients;
  const std::vector<double> dist = {k[0], k[1], k[2], k[3]};
  std::vector<cv::Point2d> reference;
  cv::projectPoints(points, cv::Vec3d(0, 0, 0), cv::Vec3d(0, 0, 0), K, dist, reference);
  for (std::size_t i = 0; i < points.size(); ++i) {
    const auto projected = sut->project(Eigen::Vector3d(points[i].x, points[i].y, points[i].z));
    ASSERT_TRUE(projected.has_value());
    EXPECT_NEAR(projected->x(), reference[i].x, 1e-6);
    EXPECT_NEAR(projected->y(), reference[i].y, 1e-6);
  }
}

TEST(CameraModel, RefusesEquidistantDistortionAndSaysWhy) {
  dataset::CameraCalibration cal = eurocCam0();
  cal.distortion = dataset::DistortionModel::kEquidistant;
  auto sut = CameraModel::create(cal);
  ASSERT_FALSE(sut.ok());
  EXPECT_NE(sut.error().message().find("radial-tangential"), std::string::npos);
}

void expectSameCamera(const dataset::CameraCalibration& built_in, const dataset::CameraCalibration& file) {
  EXPECT_EQ(built_in.width, file.width);
  EXPECT_EQ(built_in.height, file.height);
  EXPECT_DOUBLE_EQ(built_in.rate_hz, file.rate_hz);
  EXPECT_DOUBLE_EQ(built_in.fx, file.fx);
  EXPECT_DOUBLE_EQ(built_in.fy, file.fy);
  EXPECT_DOUBLE_EQ(built_in.cx, file.cx);
  EXPECT_DOUBLE_EQ(built_in.cy, file.cy);
  EXPECT_EQ(built_in.distortion, file.distortion);
  for (std::size_t i = 0; i < 4; ++i) {
    EXPECT_DOUBLE_EQ(built_in.distortion_coefficients[i], file.distortion_coefficients[i]);
  }
  EXPECT_LT((built_in.T_b_c.matrix() - file.T_b_c.matrix()).cwiseAbs().maxCoeff(), 1e-9);
}

TEST(EurocDefaults, BuiltInCalibrationEqualsTheSharedSensorYaml) {
  CVISLAM_REQUIRE_DATA(root, "euroc-calibration/asl_sensor_yaml");
  auto cam0 = dataset::readCameraCalibration(root / "cam0_sensor.yaml", "cam0");
  auto cam1 = dataset::readCameraCalibration(root / "cam1_sensor.yaml", "cam1");
  auto imu = dataset::readImuCalibration(root / "imu0_sensor.yaml");
  ASSERT_TRUE(cam0.ok() && cam1.ok() && imu.ok());
  expectSameCamera(eurocCam0(), *cam0);
  expectSameCamera(eurocCam1(), *cam1);
  const dataset::ImuCalibration built_in = eurocImu();
  EXPECT_DOUBLE_EQ(built_in.rate_hz, imu->rate_hz);
  EXPECT_DOUBLE_EQ(built_in.gyro_noise_density, imu->gyro_noise_density);
  EXPECT_DOUBLE_EQ(built_in.gyro_random_walk, imu->gyro_random_walk);
  EXPECT_DOUBLE_EQ(built_in.accel_noise_density, imu->accel_noise_density);
  EXPECT_DOUBLE_EQ(built_in.accel_random_walk, imu->accel_random_walk);
}

}  // namespace
}  // namespace cvislam::sim

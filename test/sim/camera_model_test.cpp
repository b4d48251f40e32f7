#include "test/sim/camera_model.hpp"

#include <gtest/gtest.h>

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

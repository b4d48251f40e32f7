// Kalibr's camera chain and IMU files read into the project's calibrations: the same values as EuRoC's
// sensor.yaml describe, the frames converted (T_cam_imu is the inverse of T_BS), and every bad value named.
#include "common/dataset/kalibr.hpp"

#include <string>

#include <gtest/gtest.h>

#include "common/dataset/euroc_calibration.hpp"
#include "test/support/calibration_checks.hpp"
#include "test/support/kalibr_files.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::dataset {
namespace {

std::filesystem::path write(const test::TempDir& dir, const std::string& name, const std::string& text) {
  const auto path = dir.path() / name;
  test::writeTextFile(path, text);
  return path;
}

// Kalibr's files carry no frame rate: intrinsics and extrinsics only.
void expectSameCamera(const CameraCalibration& a, const CameraCalibration& b) {
  test::expectSameIntrinsics(a, b);
  EXPECT_LT((a.T_b_c.translation() - b.T_b_c.translation()).norm(), 1e-12);
  EXPECT_LT((a.T_b_c.so3().matrix() - b.T_b_c.so3().matrix()).cwiseAbs().maxCoeff(), 1e-9);
}

TEST(Kalibr, AStereoChainGivesTheCalibrationsItWasMadeFrom) {
  const test::TempDir dir;
  const auto path = write(dir, "camchain-imucam.yaml", test::kalibrCamchainYaml(eurocCam0(), eurocCam1(), -0.0125));
  auto chain = readKalibrCamchain(path);
  ASSERT_TRUE(chain.ok()) << chain.error().toString();
  ASSERT_EQ(chain->size(), 2U);
  EXPECT_EQ((*chain)[0].calibration.name, "cam0");
  EXPECT_EQ((*chain)[1].calibration.name, "cam1");
  expectSameCamera((*chain)[0].calibration, eurocCam0());
  expectSameCamera((*chain)[1].calibration, eurocCam1());
  EXPECT_EQ((*chain)[0].timeshift_cam_imu_ns, -12'500'000);
  EXPECT_EQ((*chain)[1].rostopic, "/cam1/image_raw");
}

TEST(Kalibr, TheImuFileIsReadNestedUnderImu0AndFlat) {
  const test::TempDir dir;
  for (const bool nested : {true, false}) {
    const auto path = write(dir, nested ? "imu_nested.yaml" : "imu_flat.yaml", test::kalibrImuYaml(eurocImu(), nested));
    auto imu = readKalibrImu(path);
    ASSERT_TRUE(imu.ok()) << imu.error().toString();
    EXPECT_DOUBLE_EQ(imu->calibration.rate_hz, eurocImu().rate_hz);
    EXPECT_DOUBLE_EQ(imu->calibration.gyro_noise_density, eurocImu().gyro_noise_density);
    EXPECT_DOUBLE_EQ(imu->calibration.gyro_random_walk, eurocImu().gyro_random_walk);
    EXPECT_DOUBLE_EQ(imu->calibration.accel_noise_density, eurocImu().accel_noise_density);
    EXPECT_DOUBLE_EQ(imu->calibration.accel_random_walk, eurocImu().accel_random_walk);
    EXPECT_EQ(imu->rostopic, "/imu0");
  }
}

// Each broken file is refused with a message that names what to fix.
TEST(Kalibr, BadFilesAreRefusedNamingTheKey) {
  const test::TempDir dir;
  const std::string good = test::kalibrCamchainYaml(eurocCam0(), std::nullopt);
  struct Case {
    std::string from;
    std::string to;
    std::string expected;
  };
  const Case cases[] = {
      {"camera_model: pinhole", "camera_model: omni", "camera_model 'omni' is not supported"},
      {"distortion_model: radtan", "distortion_model: fov", "distortion_model 'fov' is not supported"},
      {"  intrinsics: [", "  intrinsic: [", "missing key 'intrinsics'"},
      {"  resolution: [752, 480]", "  resolution: [752.5, 480]", "resolution must be whole pixels"},
      {"  timeshift_cam_imu: 0", "  timeshift_cam_imu: 3", "timeshift_cam_imu must be within +-1 s"},
      {"cam0:", "camera0:", "no camera"},
  };
  for (const Case& c : cases) {
    std::string text = good;
    const auto at = text.find(c.from);
    ASSERT_NE(at, std::string::npos) << c.from;
    text.replace(at, c.from.size(), c.to);
    const auto path = write(dir, "bad.yaml", text);
    auto chain = readKalibrCamchain(path);
    ASSERT_FALSE(chain.ok()) << c.to;
    EXPECT_NE(chain.error().message().find(c.expected), std::string::npos) << chain.error().message();
    EXPECT_NE(chain.error().message().find("bad.yaml"), std::string::npos) << chain.error().message();
  }
  // A first row of T_cam_imu that makes the top-left block no rotation.
  std::string scaled = good;
  const auto row = scaled.find("  - [", scaled.find("T_cam_imu:"));
  scaled.replace(row, scaled.find('\n', row) - row, "  - [2, 0, 0, 0]");
  auto not_rigid = readKalibrCamchain(write(dir, "bad.yaml", scaled));
  ASSERT_FALSE(not_rigid.ok());
  EXPECT_NE(not_rigid.error().message().find("T_cam_imu: the top-left 3x3 block is not a rotation"), std::string::npos)
      << not_rigid.error().message();
  auto imu = readKalibrImu(write(dir, "imu.yaml", "imu0:\n  update_rate: 200\n"));
  ASSERT_FALSE(imu.ok());
  EXPECT_NE(imu.error().message().find("missing key 'gyroscope_noise_density'"), std::string::npos)
      << imu.error().message();
  auto missing = readKalibrCamchain(dir.path() / "nothing.yaml");
  ASSERT_FALSE(missing.ok());
  EXPECT_NE(missing.error().message().find("does not exist"), std::string::npos);
}

}  // namespace
}  // namespace cvislam::dataset

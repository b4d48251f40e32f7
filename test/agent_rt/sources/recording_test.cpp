// The agent's recordings: a EuRoC folder and the same recording as a ROS 2 bag in MCAP give the same rig, IMU
// samples, frames and pixels; what a bag cannot give (a calibration) or gives wrongly (another message type on a
// topic, a truncated file) is refused with an error that says what to fix. On the real EuRoC V1_01 excerpt.
#include "agent_rt/sources/recording.hpp"

#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "common/dataset/calibration.hpp"
#include "test/support/euroc_to_mcap.hpp"
#include "test/support/kalibr_files.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::agent {
namespace {

namespace fs = std::filesystem;

struct KalibrPair {
  fs::path camchain;
  fs::path imu;
};

// Kalibr files made from the folder's own sensor.yaml files.
KalibrPair kalibrOf(const fs::path& folder, const test::TempDir& dir) {
  const fs::path mav0 = folder / "mav0";
  auto cam0 = dataset::readCameraCalibration(mav0 / "cam0" / "sensor.yaml", "cam0");
  auto cam1 = dataset::readCameraCalibration(mav0 / "cam1" / "sensor.yaml", "cam1");
  auto imu = dataset::readImuCalibration(mav0 / "imu0" / "sensor.yaml");
  EXPECT_TRUE(cam0.ok() && cam1.ok() && imu.ok());
  KalibrPair files{dir.path() / "camchain-imucam.yaml", dir.path() / "imu.yaml"};
  test::writeTextFile(files.camchain, test::kalibrCamchainYaml(*cam0, *cam1));
  test::writeTextFile(files.imu, test::kalibrImuYaml(*imu));
  return files;
}

Result<std::unique_ptr<Recording>> openBag(const fs::path& bag, const KalibrPair& kalibr) {
  RecordingOptions options;
  options.mcap = bag;
  options.calibration = kalibr.camchain;
  options.imu_calibration = kalibr.imu;
  return openRecording(options);
}

void expectSameRecording(Recording& folder, Recording& bag) {
  EXPECT_EQ(bag.rig().cam0.width, folder.rig().cam0.width);
  ASSERT_TRUE(bag.rig().cam1.has_value());
  EXPECT_DOUBLE_EQ(bag.rig().cam1->fx, folder.rig().cam1->fx);
  ASSERT_EQ(bag.imu().size(), folder.imu().size());
  for (std::size_t i = 0; i < folder.imu().size(); ++i) {
    EXPECT_EQ(bag.imu()[i].t_ns, folder.imu()[i].t_ns);
    EXPECT_EQ(bag.imu()[i].gyro_s, folder.imu()[i].gyro_s);
    EXPECT_EQ(bag.imu()[i].accel_s, folder.imu()[i].accel_s);
  }
  ASSERT_EQ(bag.rigFrames().size(), folder.rigFrames().size());
  const auto n = static_cast<std::size_t>(folder.rig().cam0.width) * static_cast<std::size_t>(folder.rig().cam0.height);
  std::vector<std::uint8_t> a(n);
  std::vector<std::uint8_t> b(n);
  for (std::size_t i = 0; i < folder.rigFrames().size(); ++i) {
    const dataset::RigFrame& f = folder.rigFrames()[i];
    const dataset::RigFrame& g = bag.rigFrames()[i];
    ASSERT_EQ(g.t_ns, f.t_ns);
    ASSERT_EQ(g.cam1.has_value(), f.cam1.has_value());
    ASSERT_TRUE(folder.loadImageInto(0, f.cam0, a).ok());
    const Status loaded = bag.loadImageInto(0, g.cam0, b);
    ASSERT_TRUE(loaded.ok()) << loaded.error().toString();
    ASSERT_EQ(a, b) << "cam0 frame " << i;
    if (f.cam1) {
      ASSERT_TRUE(folder.loadImageInto(1, *f.cam1, a).ok());
      ASSERT_TRUE(bag.loadImageInto(1, *g.cam1, b).ok());
      ASSERT_EQ(a, b) << "cam1 frame " << i;
    }
  }
}

TEST(Recordings, AFolderAndTheSameRecordingAsABagAgreeSampleForSampleAndPixelForPixel) {
  CVISLAM_REQUIRE_DATA(excerpt, "euroc-v101-excerpt");
  const test::TempDir dir;
  const KalibrPair kalibr = kalibrOf(excerpt, dir);
  RecordingOptions folder_options;
  folder_options.dataset = excerpt;
  folder_options.calibration = kalibr.camchain;
  folder_options.imu_calibration = kalibr.imu;
  // Zstd chunks, uncompressed chunks, no chunks; colour images turned grey; stamps missing (log time used).
  struct Variant {
    const char* name;
    test::EurocToMcapOptions options;
  };
  std::vector<Variant> variants(5);
  variants[0].name = "zstd";
  variants[1].name = "uncompressed";
  variants[1].options.compression = mcap::Compression::kNone;
  variants[2].name = "unchunked";
  variants[2].options.use_chunks = false;
  variants[3].name = "bgr8";
  variants[3].options.image_encoding = "bgr8";
  variants[4].name = "zero stamps";
  variants[4].options.zero_header_stamps = true;
  for (const Variant& v : variants) {
    SCOPED_TRACE(v.name);
    const fs::path bag = dir.path() / (std::string(v.name) + ".mcap");
    const Status written = test::writeEurocAsMcap(excerpt, bag, v.options);
    ASSERT_TRUE(written.ok()) << written.error().toString();
    auto folder = openRecording(folder_options);
    ASSERT_TRUE(folder.ok()) << folder.error().toString();
    auto opened = openBag(bag, kalibr);
    ASSERT_TRUE(opened.ok()) << opened.error().toString();
    // bgr8 holds the grey in three channels; turned grey again it is the same grey.
    expectSameRecording(**folder, **opened);
    const bool said = !(*opened)->diagnostics().empty();
    EXPECT_EQ(said, v.options.zero_header_stamps) << "the log-time fallback is said once, and only then";
  }
}

// Kalibr's timeshift_cam_imu (t_imu = t_cam + shift) moves every frame of a folder and of a bag onto the IMU's
// clock; the IMU samples stay where they are.
TEST(Recordings, KalibrsTimeShiftMovesTheFramesOntoTheImuClock) {
  CVISLAM_REQUIRE_DATA(excerpt, "euroc-v101-excerpt");
  const test::TempDir dir;
  const fs::path mav0 = excerpt / "mav0";
  auto cam0 = dataset::readCameraCalibration(mav0 / "cam0" / "sensor.yaml", "cam0");
  auto cam1 = dataset::readCameraCalibration(mav0 / "cam1" / "sensor.yaml", "cam1");
  auto imu = dataset::readImuCalibration(mav0 / "imu0" / "sensor.yaml");
  ASSERT_TRUE(cam0.ok() && cam1.ok() && imu.ok());
  const fs::path shifted = dir.path() / "shifted.yaml";
  const fs::path imu_yaml = dir.path() / "imu.yaml";
  test::writeTextFile(shifted, test::kalibrCamchainYaml(*cam0, *cam1, -0.0125));
  test::writeTextFile(imu_yaml, test::kalibrImuYaml(*imu));
  const fs::path bag = dir.path() / "v101.mcap";
  ASSERT_TRUE(test::writeEurocAsMcap(excerpt, bag).ok());

  RecordingOptions plain;
  plain.dataset = excerpt;
  auto reference = openRecording(plain);
  ASSERT_TRUE(reference.ok()) << reference.error().toString();
  RecordingOptions folder = plain;
  folder.calibration = shifted;
  RecordingOptions mcap;
  mcap.mcap = bag;
  mcap.calibration = shifted;
  mcap.imu_calibration = imu_yaml;
  for (const RecordingOptions* options : {&folder, &mcap}) {
    auto moved = openRecording(*options);
    ASSERT_TRUE(moved.ok()) << moved.error().toString();
    ASSERT_EQ((*moved)->rigFrames().size(), (*reference)->rigFrames().size());
    for (std::size_t i = 0; i < (*reference)->rigFrames().size(); ++i) {
      EXPECT_EQ((*moved)->rigFrames()[i].t_ns, (*reference)->rigFrames()[i].t_ns - 12'500'000) << (*moved)->describe();
    }
    ASSERT_EQ((*moved)->imu().size(), (*reference)->imu().size());
    EXPECT_EQ((*moved)->imu().front().t_ns, (*reference)->imu().front().t_ns);
  }
}

TEST(Recordings, ABagIsRefusedWithWhatToFix) {
  CVISLAM_REQUIRE_DATA(excerpt, "euroc-v101-excerpt");
  const test::TempDir dir;
  const KalibrPair kalibr = kalibrOf(excerpt, dir);
  const fs::path bag = dir.path() / "v101.mcap";
  ASSERT_TRUE(test::writeEurocAsMcap(excerpt, bag).ok());

  RecordingOptions no_calibration;
  no_calibration.mcap = bag;
  auto refused = openRecording(no_calibration);
  ASSERT_FALSE(refused.ok());
  EXPECT_NE(refused.error().message().find("carries no calibration"), std::string::npos) << refused.error().message();

  RecordingOptions wrong_topic;
  wrong_topic.mcap = bag;
  wrong_topic.calibration = kalibr.camchain;
  wrong_topic.imu_calibration = kalibr.imu;
  wrong_topic.topics.cam0 = "/imu0";  // an Imu topic where images are expected
  wrong_topic.topics.imu = "/imu1";
  auto wrong = openRecording(wrong_topic);
  ASSERT_FALSE(wrong.ok());
  EXPECT_NE(wrong.error().message().find("topic /imu0 carries sensor_msgs/msg/Imu, not sensor_msgs/msg/Image"),
            std::string::npos)
      << wrong.error().message();

  RecordingOptions no_images;
  no_images.mcap = bag;
  no_images.calibration = kalibr.camchain;
  no_images.imu_calibration = kalibr.imu;
  no_images.topics.cam0 = "/camera/left";
  auto missing = openRecording(no_images);
  ASSERT_FALSE(missing.ok());
  EXPECT_NE(missing.error().message().find("no sensor_msgs/msg/Image on topic /camera/left"), std::string::npos)
      << missing.error().message();

  // Cut in the middle: an error naming the file, never a crash.
  const auto size = fs::file_size(bag);
  fs::resize_file(bag, size / 2);
  auto truncated = openBag(bag, kalibr);
  ASSERT_FALSE(truncated.ok());
  EXPECT_NE(truncated.error().message().find("v101.mcap"), std::string::npos) << truncated.error().message();
}

}  // namespace
}  // namespace cvislam::agent

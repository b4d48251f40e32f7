// EuRoC/ASL reading and writing: the real V1_01 excerpt, a writer round trip, and every kind of broken
// input the reader must name instead of crashing on.
#include "common/dataset/euroc.hpp"

#include <fstream>
#include <string>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "common/dataset/calibration.hpp"
#include "common/dataset/euroc_writer.hpp"
#include "common/dataset/image_codecs.hpp"
#include "test/common/dataset/sequence_fixture.hpp"
#include "test/support/temp_dir.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::dataset {
namespace {

using ::testing::HasSubstr;

std::string allFindings(const Diagnostics& d) {
  std::string out;
  for (const auto& f : d.findings()) out += f.toString() + "\n";
  return out;
}

// Replaces the first occurrence of `from` in a text file.
void editFile(const std::filesystem::path& path, const std::string& from, const std::string& to) {
  std::string text = test::readTextFile(path);
  const auto pos = text.find(from);
  ASSERT_NE(pos, std::string::npos) << from << " not in " << path;
  text.replace(pos, from.size(), to);
  test::writeTextFile(path, text);
}

// Appends a line to a text file.
void appendLine(const std::filesystem::path& path, const std::string& line) {
  std::ofstream out(path, std::ios::app);
  out << line << "\n";
}

// ------------------------------------------------------------------------------------------ real data

TEST(EurocRealData, ReadsTheV101ExcerptAndReportsTheFourMissingCam1Images) {
  CVISLAM_REQUIRE_DATA(seq_path, "euroc-v101-excerpt");
  auto seq = EurocSequence::open(seq_path);
  ASSERT_TRUE(seq.ok()) << seq.error().toString();
  EXPECT_EQ(seq->cam0().frames.size(), 95u);
  ASSERT_NE(seq->cam1(), nullptr);
  EXPECT_EQ(seq->cam1()->frames.size(), 95u);  // 99 listed, 4 without a file
  EXPECT_EQ(seq->stereoPairCount(), 95u);
  EXPECT_EQ(seq->imu().size(), 29120u);
  EXPECT_EQ(seq->groundTruth().size(), 2895u);
  EXPECT_TRUE(seq->groundTruth().front().has_velocity_and_biases);
  EXPECT_EQ(seq->cam0().frames.front().t_ns, 1403715273262142976LL);
  EXPECT_EQ(seq->cam0().frames.back().t_ns, 1403715277962142976LL);

  const Diagnostics& diag = seq->diagnostics();
  EXPECT_EQ(diag.warningCount(), 4u) << allFindings(diag);
  for (const auto& finding : diag.findings()) {
    EXPECT_THAT(finding.file, HasSubstr("cam1/data.csv"));
    EXPECT_THAT(finding.message, HasSubstr("listed but missing"));
    EXPECT_GE(finding.line, 97);  // the last four of 99 rows plus the header
  }
  EXPECT_THAT(diag.findings().front().message, HasSubstr("1403715278012143104.png"));
  EXPECT_THAT(seq->summary(), HasSubstr("stereo pairs: 95 of 95"));
}

TEST(EurocRealData, StrictModeRefusesTheExcerptAndNamesTheMissingFile) {
  CVISLAM_REQUIRE_DATA(seq_path, "euroc-v101-excerpt");
  EurocReaderOptions strict;
  strict.strict = true;
  auto seq = EurocSequence::open(seq_path, strict);
  ASSERT_FALSE(seq.ok());
  EXPECT_THAT(seq.error().message(), HasSubstr("cam1/data.csv:97"));
  EXPECT_THAT(seq.error().message(), HasSubstr("1403715278012143104.png"));
}

TEST(EurocRealData, CalibrationMatchesThePublishedEuRoCValues) {
  CVISLAM_REQUIRE_DATA(seq_path, "euroc-v101-excerpt");
  auto seq = EurocSequence::open(seq_path);
  ASSERT_TRUE(seq.ok());
  const CameraCalibration& c0 = seq->cam0().calibration;
  EXPECT_EQ(c0.width, 752);
  EXPECT_EQ(c0.height, 480);
  EXPECT_DOUBLE_EQ(c0.rate_hz, 20.0);
  EXPECT_DOUBLE_EQ(c0.fx, 458.654);
  EXPECT_DOUBLE_EQ(c0.cy, 248.375);
  EXPECT_EQ(c0.distortion, DistortionModel::kRadialTangential);
  EXPECT_DOUBLE_EQ(c0.distortion_coefficients[0], -0.28340811);
  EXPECT_NEAR(c0.T_b_c.translation().x(), -0.0216401454975, 1e-12);
  EXPECT_NEAR(c0.T_b_c.rotationMatrix()(0, 1), -0.999880929698, 1e-6);
  // The stereo baseline of the EuRoC rig is about 11 cm.
  const geometry::SE3d T_c0_c1 = c0.T_b_c.inverse() * seq->cam1()->calibration.T_b_c;
  EXPECT_NEAR(T_c0_c1.translation().norm(), 0.110, 0.002);
  ASSERT_TRUE(seq->imuCalibration().has_value());
  EXPECT_DOUBLE_EQ(seq->imuCalibration()->gyro_noise_density, 1.6968e-04);
  EXPECT_DOUBLE_EQ(seq->imuCalibration()->accel_random_walk, 3.0e-3);
  EXPECT_DOUBLE_EQ(seq->imuCalibration()->rate_hz, 200.0);
}

TEST(EurocRealData, LoadsImagesOnDemand) {
  CVISLAM_REQUIRE_DATA(seq_path, "euroc-v101-excerpt");
  auto seq = EurocSequence::open(seq_path);
  ASSERT_TRUE(seq.ok());
  for (int cam : {0, 1}) {
    auto image = seq->loadImage(cam, seq->camera(cam).frames.size() - 1);
    ASSERT_TRUE(image.ok()) << image.error().toString();
    EXPECT_EQ(image->width, 752);
    EXPECT_EQ(image->height, 480);
    const auto [lo, hi] = std::minmax_element(image->pixels.begin(), image->pixels.end());
    EXPECT_GT(*hi - *lo, 100);  // a real, textured image
  }
  std::vector<std::uint8_t> buffer(std::size_t{752} * 480);
  EXPECT_TRUE(seq->loadImageInto(0, 0, buffer).ok());
  EXPECT_FALSE(seq->loadImage(2, 0).ok());
  EXPECT_FALSE(seq->loadImage(0, 95).ok());
}

// --------------------------------------------------------------------------------- writer round trip

TEST(EurocWriter, WhatItWritesReadsBackExactly) {
  test::TempDir dir;
  test::writeSmallSequence(dir / "seq");
  auto seq = EurocSequence::open(dir / "seq");
  ASSERT_TRUE(seq.ok()) << seq.error().toString();
  EXPECT_TRUE(seq->diagnostics().empty()) << allFindings(seq->diagnostics());
  EXPECT_EQ(seq->rigFrames().size(), 6u);
  EXPECT_EQ(seq->stereoPairCount(), 6u);
  EXPECT_EQ(seq->imu().size(), 60u);
  ASSERT_EQ(seq->groundTruth().size(), 6u);

  const test::SmallSequenceSpec spec;
  const CameraCalibration expected = test::smallCamera(spec, 1);
  const CameraCalibration& got = seq->cam1()->calibration;
  EXPECT_EQ(got.fx, expected.fx);
  EXPECT_EQ(got.distortion_coefficients, expected.distortion_coefficients);
  EXPECT_LT((got.T_b_c.matrix() - expected.T_b_c.matrix()).cwiseAbs().maxCoeff(), 1e-15);

  EXPECT_EQ(seq->imu()[13].t_ns, 1'000'000'000 + 50'000'000 + 3 * 5'000'000);
  EXPECT_EQ(seq->imu()[13].gyro_s, Eigen::Vector3d(0.01, -0.02, 0.1 + 1e-3 * 3));  // exact: shortest round trip
  const GroundTruthState& gt = seq->groundTruth()[3];
  EXPECT_EQ(gt.T_w_b.translation(), Eigen::Vector3d(0.1 * 3, 1.0, 1.5));
  EXPECT_EQ(gt.accel_bias, Eigen::Vector3d(-0.01, 0.1, 0.09));

  auto image = seq->loadImage(1, 4);
  ASSERT_TRUE(image.ok());
  EXPECT_EQ(image->at(10, 20), static_cast<std::uint8_t>((10 * 7 + 20 * 3 + 4 * 11 + 1) & 0xff));
}

TEST(EurocWriter, CommentsWithYamlSyntaxRoundTrip) {
  test::TempDir dir;
  const std::string comment = "cam0: EuRoC # \"MT9M034\", back\\slash\nsecond line";
  CameraCalibration camera;
  camera.comment = comment;
  ASSERT_TRUE(writeCameraCalibration(dir / "cam.yaml", camera).ok());
  auto camera_back = readCameraCalibration(dir / "cam.yaml", "cam0");
  ASSERT_TRUE(camera_back.ok()) << camera_back.error().toString();
  EXPECT_EQ(camera_back->comment, comment);
  ImuCalibration imu;
  imu.comment = comment;
  ASSERT_TRUE(writeImuCalibration(dir / "imu.yaml", imu).ok());
  auto imu_back = readImuCalibration(dir / "imu.yaml");
  ASSERT_TRUE(imu_back.ok()) << imu_back.error().toString();
  EXPECT_EQ(imu_back->comment, comment);
}

TEST(EurocWriter, OutputIsByteIdenticalAcrossRuns) {
  test::TempDir dir;
  test::writeSmallSequence(dir / "a");
  test::writeSmallSequence(dir / "b");
  for (const char* file : {"mav0/cam0/data.csv", "mav0/cam1/sensor.yaml", "mav0/imu0/data.csv",
                           "mav0/state_groundtruth_estimate0/data.csv", "mav0/cam0/data/1000000000.png"}) {
    EXPECT_EQ(test::readTextFile(dir / "a" / file), test::readTextFile(dir / "b" / file)) << file;
  }
}

TEST(EurocWriter, RejectsBackwardsTimeWrongImageSizeAndExistingOutput) {
  test::TempDir dir;
  EurocWriterOptions options;
  options.cameras.push_back(test::smallCamera({}, 0));
  options.imu = ImuCalibration{};
  auto writer = EurocWriter::create(dir / "seq", options);
  ASSERT_TRUE(writer.ok());
  ImuSample s;
  s.t_ns = 10;
  EXPECT_TRUE(writer->addImu(s).ok());
  EXPECT_THAT(writer->addImu(s).error().message(), HasSubstr("after the previous one"));
  EXPECT_THAT(writer->addImage(0, 5, GrayImage(10, 10)).error().message(), HasSubstr("10x10"));
  EXPECT_FALSE(writer->addImage(1, 5, GrayImage(64, 48)).ok());
  EXPECT_TRUE(writer->close().ok());
  EXPECT_THAT(EurocWriter::create(dir / "seq", options).error().message(), HasSubstr("already exists"));
}

// ----------------------------------------------------------------------------------- broken folders

TEST(EurocBrokenInput, MissingFolderIsNamed) {
  test::TempDir dir;
  auto seq = EurocSequence::open(dir / "no_such_sequence");
  ASSERT_FALSE(seq.ok());
  EXPECT_EQ(seq.error().code(), ErrorCode::kNotFound);
  EXPECT_THAT(seq.error().message(), HasSubstr("no_such_sequence"));
}

TEST(EurocBrokenInput, AFolderWithoutMav0SaysWhatLayoutIsExpected) {
  test::TempDir dir;
  std::filesystem::create_directories(dir / "seq" / "images");
  auto seq = EurocSequence::open(dir / "seq");
  ASSERT_FALSE(seq.ok());
  EXPECT_THAT(seq.error().message(), HasSubstr("mav0"));
  EXPECT_THAT(seq.error().message(), HasSubstr("cam0/"));
}

TEST(EurocBrokenInput, MissingCam0OrImuIsAnError) {
  test::TempDir dir;
  test::writeSmallSequence(dir / "seq");
  std::filesystem::remove_all(dir / "seq/mav0/imu0");
  auto no_imu = EurocSequence::open(dir / "seq");
  ASSERT_FALSE(no_imu.ok());
  EXPECT_THAT(no_imu.error().message(), HasSubstr("imu0"));
  EurocReaderOptions vision_only;
  vision_only.require_imu = false;
  EXPECT_TRUE(EurocSequence::open(dir / "seq", vision_only).ok());

  std::filesystem::remove_all(dir / "seq/mav0/cam0");
  std::filesystem::create_directories(dir / "seq/mav0/imu0");  // still looks like a sequence
  auto no_cam0 = EurocSequence::open(dir / "seq/mav0", vision_only);
  ASSERT_FALSE(no_cam0.ok());
  EXPECT_THAT(no_cam0.error().message(), HasSubstr("cam0"));
}

TEST(EurocBrokenInput, ATruncatedImuLineIsSkippedAndReportedWithItsLine) {
  test::TempDir dir;
  test::writeSmallSequence(dir / "seq");
  appendLine(dir / "seq/mav0/imu0/data.csv", "1300000000,0.01,-0.02");  // line 62: header + 60 rows + this
  auto seq = EurocSequence::open(dir / "seq");
  ASSERT_TRUE(seq.ok());
  EXPECT_EQ(seq->imu().size(), 60u);
  ASSERT_EQ(seq->diagnostics().warningCount(), 1u);
  const Finding& f = seq->diagnostics().findings().front();
  EXPECT_THAT(f.file, HasSubstr("imu0/data.csv"));
  EXPECT_EQ(f.line, 62);
  EXPECT_THAT(f.message, HasSubstr("truncated"));

  EurocReaderOptions strict;
  strict.strict = true;
  auto refused = EurocSequence::open(dir / "seq", strict);
  ASSERT_FALSE(refused.ok());
  EXPECT_THAT(refused.error().message(), HasSubstr("imu0/data.csv:62"));
}

TEST(EurocBrokenInput, ANonNumericFieldIsNamed) {
  test::TempDir dir;
  test::writeSmallSequence(dir / "seq");
  editFile(dir / "seq/mav0/imu0/data.csv", ",9.81,", ",9.8l,");  // a typo on the first data row
  auto seq = EurocSequence::open(dir / "seq");
  ASSERT_TRUE(seq.ok());
  EXPECT_EQ(seq->imu().size(), 59u);
  ASSERT_EQ(seq->diagnostics().warningCount(), 1u);
  const Finding& f = seq->diagnostics().findings().front();
  EXPECT_EQ(f.line, 2);
  EXPECT_THAT(f.message, HasSubstr("field 5 ('9.8l') is not a finite number"));
}

TEST(EurocBrokenInput, TimestampsGoingBackwardsAreReported) {
  test::TempDir dir;
  test::writeSmallSequence(dir / "seq");
  appendLine(dir / "seq/mav0/state_groundtruth_estimate0/data.csv", "1000000001,0,0,0,1,0,0,0,0,0,0,0,0,0,0,0,0");
  auto seq = EurocSequence::open(dir / "seq");
  ASSERT_TRUE(seq.ok());
  EXPECT_EQ(seq->groundTruth().size(), 6u);
  ASSERT_EQ(seq->diagnostics().warningCount(), 1u);
  EXPECT_THAT(seq->diagnostics().findings().front().message, HasSubstr("is not after the previous row"));
  EXPECT_EQ(seq->diagnostics().findings().front().line, 8);
}

TEST(EurocBrokenInput, AnImageListedButMissingIsSkippedAndNamed) {
  test::TempDir dir;
  test::writeSmallSequence(dir / "seq");
  std::filesystem::remove(dir / "seq/mav0/cam0/data/1100000000.png");
  auto seq = EurocSequence::open(dir / "seq");
  ASSERT_TRUE(seq.ok());
  EXPECT_EQ(seq->cam0().frames.size(), 5u);
  EXPECT_EQ(seq->stereoPairCount(), 5u);
  const std::string findings = allFindings(seq->diagnostics());
  EXPECT_THAT(findings, HasSubstr("cam0/data.csv:4: warning: image '1100000000.png' is listed but missing"));
  EXPECT_THAT(findings, HasSubstr("1 cam1 frame(s) have no cam0 frame"));
}

TEST(EurocBrokenInput, AnUnreadableImageGivesAnErrorNamingTheFile) {
  test::TempDir dir;
  test::writeSmallSequence(dir / "seq");
  test::writeTextFile(dir / "seq/mav0/cam0/data/1050000000.png", "this is not a PNG file");
  test::writeTextFile(dir / "seq/mav0/cam0/data/1100000000.png", "");
  auto seq = EurocSequence::open(dir / "seq");
  ASSERT_TRUE(seq.ok());
  auto garbage = seq->loadImage(0, 1);
  ASSERT_FALSE(garbage.ok());
  EXPECT_THAT(garbage.error().message(), HasSubstr("1050000000.png: not a PNG file"));
  EXPECT_THAT(garbage.error().message(), HasSubstr("Convert the images"));
  auto empty = seq->loadImage(0, 2);
  ASSERT_FALSE(empty.ok());
  EXPECT_THAT(empty.error().message(), HasSubstr("1100000000.png: image file is empty"));
  EXPECT_TRUE(seq->loadImage(0, 3).ok());  // the rest of the sequence is still usable
  // A PNG cut short after its header.
  const auto good = dir / "seq/mav0/cam0/data/1150000000.png";
  std::ifstream in(good, std::ios::binary);
  std::string head(60, '\0');
  in.read(head.data(), static_cast<std::streamsize>(head.size()));
  test::writeTextFile(dir / "seq/mav0/cam0/data/1050000000.png", head);
  auto truncated = seq->loadImage(0, 1);
  ASSERT_FALSE(truncated.ok());
  EXPECT_THAT(truncated.error().message(), HasSubstr("1050000000.png: PNG truncated"));
}

TEST(EurocBrokenInput, AnImageOfTheWrongSizeIsNamed) {
  test::TempDir dir;
  test::writeSmallSequence(dir / "seq");
  ASSERT_TRUE(writeGrayPng(dir / "seq/mav0/cam1/data/1000000000.png", GrayImage(32, 24, 128)).ok());
  auto seq = EurocSequence::open(dir / "seq");
  ASSERT_TRUE(seq.ok());
  auto image = seq->loadImage(1, 0);
  ASSERT_FALSE(image.ok());
  EXPECT_THAT(image.error().message(), HasSubstr("image is 32x24, cam1/sensor.yaml says 64x48"));
}

struct BrokenYamlCase {
  friend void PrintTo(const BrokenYamlCase& c, std::ostream* os) { *os << c.name; }
  const char* name;
  const char* from;
  const char* to;
  const char* expected;  // in the error message
};

class EurocBrokenSensorYaml : public ::testing::TestWithParam<BrokenYamlCase> {};

TEST_P(EurocBrokenSensorYaml, IsRefusedWithAMessageNamingTheFileAndTheProblem) {
  test::TempDir dir;
  test::writeSmallSequence(dir / "seq");
  editFile(dir / "seq/mav0/cam0/sensor.yaml", GetParam().from, GetParam().to);
  auto seq = EurocSequence::open(dir / "seq");
  ASSERT_FALSE(seq.ok());
  EXPECT_THAT(seq.error().message(), HasSubstr("cam0/sensor.yaml"));
  EXPECT_THAT(seq.error().message(), HasSubstr(GetParam().expected));
}

INSTANTIATE_TEST_SUITE_P(
    Cases, EurocBrokenSensorYaml,
    ::testing::Values(
        BrokenYamlCase{"MissingIntrinsics", "intrinsics:", "intrinsix:", "missing key 'intrinsics'"},
        BrokenYamlCase{"ThreeIntrinsics", "intrinsics: [40, 41,", "intrinsics: [41,",
                       "'intrinsics' must be a list of 4 numbers (fu, fv, cu, cv), got 3"},
        BrokenYamlCase{"TextRate", "rate_hz: 20", "rate_hz: fast", "'rate_hz' must be a number"},
        BrokenYamlCase{"InvalidYaml", "resolution: [64, 48]", "resolution: [64, 48", "invalid YAML"},
        BrokenYamlCase{"UnsupportedModel", "camera_model: pinhole", "camera_model: omni", "'omni' is not supported"},
        BrokenYamlCase{"UnknownDistortion", "distortion_model: radial-tangential", "distortion_model: fisheye9",
                       "distortion_model 'fisheye9' is not supported"},
        BrokenYamlCase{"NegativeFocalLength", "intrinsics: [40,", "intrinsics: [-40,", "focal lengths"},
        BrokenYamlCase{"ShortExtrinsics", "data: [", "data: [1, ", "T_BS.data' must be a list of 16 numbers"}),
    [](const ::testing::TestParamInfo<BrokenYamlCase>& case_info) { return std::string(case_info.param.name); });

TEST(EurocBrokenInput, AnExtrinsicThatIsNotARotationIsRefused) {
  test::TempDir dir;
  test::writeSmallSequence(dir / "seq");
  const auto yaml = dir / "seq/mav0/cam0/sensor.yaml";
  std::string text = test::readTextFile(yaml);
  const auto begin = text.find("data: [");
  const auto end = text.find(']', begin);
  text.replace(begin, end + 1 - begin, "data: [2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]");
  test::writeTextFile(yaml, text);
  auto seq = EurocSequence::open(dir / "seq");
  ASSERT_FALSE(seq.ok());
  EXPECT_THAT(seq.error().message(), HasSubstr("cam0/sensor.yaml:"));
  EXPECT_THAT(seq.error().message(), HasSubstr("T_BS: the top-left 3x3 block is not a rotation"));
}

TEST(EurocBrokenInput, ABrokenImuYamlIsNamed) {
  test::TempDir dir;
  test::writeSmallSequence(dir / "seq");
  editFile(dir / "seq/mav0/imu0/sensor.yaml", "gyroscope_noise_density: ", "gyroscope_noise_density: -");
  auto seq = EurocSequence::open(dir / "seq");
  ASSERT_FALSE(seq.ok());
  EXPECT_THAT(seq.error().message(), HasSubstr("imu0/sensor.yaml"));
  EXPECT_THAT(seq.error().message(), HasSubstr("gyroscope_noise_density must be > 0"));
}

TEST(EurocStereoPairing, PairsByNearestTimestampWithinTheTolerance) {
  test::TempDir dir;
  test::writeSmallSequence(dir / "seq");
  // Shift one cam1 frame by 0.4 ms (still a pair) and another by 3 ms (no longer a pair).
  const auto csv = dir / "seq/mav0/cam1/data.csv";
  editFile(csv, "1050000000,1050000000.png", "1050400000,1050000000.png");
  editFile(csv, "1100000000,1100000000.png", "1103000000,1100000000.png");
  auto seq = EurocSequence::open(dir / "seq");
  ASSERT_TRUE(seq.ok());
  EXPECT_EQ(seq->stereoPairCount(), 5u);
  EXPECT_EQ(seq->rigFrames()[1].cam1, std::optional<std::size_t>(1));
  EXPECT_FALSE(seq->rigFrames()[2].cam1.has_value());
  EXPECT_THAT(allFindings(seq->diagnostics()), HasSubstr("1 cam0 frame(s) have no cam1 frame within 1000000 ns"));
}

}  // namespace
}  // namespace cvislam::dataset

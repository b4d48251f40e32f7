// ORB extraction and matching on real EuRoC V1_01 stereo frames: spread over the image, and stereo matches
// that agree with the calibrated epipolar geometry.
#include "common/features/orb.hpp"

#include <algorithm>
#include <cstdio>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "common/camera/camera_model.hpp"
#include "common/dataset/euroc.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::features {
namespace {

struct Frame {
  std::vector<Keypoint> keypoints;
  std::vector<Descriptor> descriptors;
};

Frame extractFrom(OrbExtractor& extractor, const dataset::GrayImage& image) {
  Frame f;
  f.keypoints.resize(static_cast<std::size_t>(extractor.options().max_features));
  f.descriptors.resize(f.keypoints.size());
  const int n = extractor.extract(image.pixels, image.width, image.height, f.keypoints, f.descriptors);
  f.keypoints.resize(static_cast<std::size_t>(n));
  f.descriptors.resize(static_cast<std::size_t>(n));
  return f;
}

double coveredCellFraction(const Frame& f, int width, int height, int columns, int rows) {
  std::vector<char> covered(static_cast<std::size_t>(columns * rows), 0);
  for (const Keypoint& k : f.keypoints) {
    const int cx =
        std::min(columns - 1, static_cast<int>(k.px.x() * static_cast<float>(columns) / static_cast<float>(width)));
    const int cy =
        std::min(rows - 1, static_cast<int>(k.px.y() * static_cast<float>(rows) / static_cast<float>(height)));
    covered[static_cast<std::size_t>(cy) * static_cast<std::size_t>(columns) + static_cast<std::size_t>(cx)] = 1;
  }
  return static_cast<double>(std::count(covered.begin(), covered.end(), 1)) / static_cast<double>(covered.size());
}

class OrbRealData : public ::testing::Test {
 protected:
  void SetUp() override {
    const std::filesystem::path path = test::findData("euroc-v101-excerpt");
    if (path.empty()) GTEST_SKIP() << "test data 'euroc-v101-excerpt' not found under " << test::dataRoot();
    auto seq = dataset::EurocSequence::open(path);
    ASSERT_TRUE(seq.ok()) << seq.error().toString();
    sequence_ = std::make_unique<dataset::EurocSequence>(std::move(*seq));
  }
  std::unique_ptr<dataset::EurocSequence> sequence_;
};

TEST_F(OrbRealData, FiveHundredFeaturesSpreadOverTheImageInEveryFrame) {
  auto extractor = OrbExtractor::create({});
  ASSERT_TRUE(extractor.ok());
  double worst_coverage = 1.0;
  int fewest = 1 << 20;
  for (std::size_t i = 0; i < sequence_->rigFrames().size(); i += 5) {
    auto image = sequence_->loadImage(0, i);
    ASSERT_TRUE(image.ok()) << image.error().toString();
    const Frame f = extractFrom(*extractor, *image);
    fewest = std::min(fewest, static_cast<int>(f.keypoints.size()));
    worst_coverage = std::min(worst_coverage, coveredCellFraction(f, image->width, image->height, 8, 6));
  }
  std::printf("V1_01 cam0: at least %d features per frame; at least %.0f %% of 8x6 cells covered\n", fewest,
              100.0 * worst_coverage);
  EXPECT_GE(fewest, 490);
  // EuRoC's Vicon room has dark, textureless corners; the grid still reaches most of the image.
  EXPECT_GE(worst_coverage, 0.8);
}

TEST_F(OrbRealData, StereoMatchesAgreeWithTheCalibratedEpipolarGeometry) {
  ASSERT_NE(sequence_->cam1(), nullptr);
  auto extractor = OrbExtractor::create({});
  ASSERT_TRUE(extractor.ok());
  auto cam0 = camera::CameraModel::create(sequence_->cam0().calibration);
  auto cam1 = camera::CameraModel::create(sequence_->cam1()->calibration);
  ASSERT_TRUE(cam0.ok() && cam1.ok());
  // Essential matrix of the rig: x1^T E x0 = 0 for bearings x0 (cam0) and x1 (cam1).
  const geometry::SE3d T_c1_c0 = sequence_->cam1()->calibration.T_b_c.inverse() * sequence_->cam0().calibration.T_b_c;
  const Eigen::Matrix3d E = geometry::hatSO3(T_c1_c0.translation()) * T_c1_c0.rotationMatrix();

  const dataset::RigFrame& rig = sequence_->rigFrames()[10];
  ASSERT_TRUE(rig.cam1.has_value());
  auto left = sequence_->loadImage(0, 10);
  auto right = sequence_->loadImage(1, *rig.cam1);
  ASSERT_TRUE(left.ok() && right.ok());
  const Frame f0 = extractFrom(*extractor, *left);
  const Frame f1 = extractFrom(*extractor, *right);
  std::vector<DescriptorMatch> matches(f0.descriptors.size());
  const int n = matchDescriptors(f0.descriptors, f1.descriptors, {}, matches);
  matches.resize(static_cast<std::size_t>(n));

  std::vector<double> epipolar_px;  // distance of the right point to the epipolar line, in pixels
  for (const DescriptorMatch& m : matches) {
    const Eigen::Vector3d x0 = cam0->unproject(f0.keypoints[static_cast<std::size_t>(m.query)].px.cast<double>());
    const Eigen::Vector3d x1 = cam1->unproject(f1.keypoints[static_cast<std::size_t>(m.train)].px.cast<double>());
    const Eigen::Vector3d line = E * (x0 / x0.z());
    const Eigen::Vector3d p1 = x1 / x1.z();
    epipolar_px.push_back(std::abs(line.dot(p1)) / line.head<2>().norm() * cam1->calibration().fx);
  }
  std::sort(epipolar_px.begin(), epipolar_px.end());
  const double median = epipolar_px[epipolar_px.size() / 2];
  const double inliers =
      static_cast<double>(std::count_if(epipolar_px.begin(), epipolar_px.end(), [](double e) { return e < 2.0; })) /
      static_cast<double>(epipolar_px.size());
  std::printf("stereo frame 10: %d mutual matches, median epipolar error %.2f px, %.0f %% within 2 px\n", n, median,
              100.0 * inliers);
  // Brute-force matching of two 500-feature sets finds about 150 mutual, unambiguous pairs here (the guided
  // epipolar search of tracking finds more); nearly all must be geometrically right.
  EXPECT_GE(n, 120);
  EXPECT_LT(median, 1.0);
  EXPECT_GT(inliers, 0.9);
}

TEST(Hamming, MatchesABitByBitCount) {
  std::mt19937_64 rng(17);
  std::uniform_int_distribution<int> byte(0, 255);
  for (int trial = 0; trial < 100; ++trial) {
    Descriptor a{};
    Descriptor b{};
    for (std::size_t i = 0; i < a.size(); ++i) {
      a[i] = static_cast<std::uint8_t>(byte(rng));
      b[i] = static_cast<std::uint8_t>(byte(rng));
    }
    int expected = 0;
    for (std::size_t i = 0; i < a.size(); ++i) {
      for (int bit = 0; bit < 8; ++bit) expected += ((a[i] >> bit) & 1) != ((b[i] >> bit) & 1) ? 1 : 0;
    }
    EXPECT_EQ(hammingDistance(a, b), expected);
  }
}

TEST(MatchDescriptors, RatioAndMutualChecksRejectAmbiguousMatches) {
  Descriptor base{};
  Descriptor near = base;
  near[0] = 0x01;  // 1 bit from base
  Descriptor twin = base;
  twin[1] = 0x01;  // also 1 bit from base
  Descriptor far{};
  far.fill(0xFF);
  std::vector<DescriptorMatch> out(4);
  // base is equally close to near and twin: the ratio test refuses it.
  EXPECT_EQ(matchDescriptors(std::vector<Descriptor>{base}, std::vector<Descriptor>{near, twin, far}, {}, out), 0);
  // Alone with a far descriptor, base matches near.
  const int n = matchDescriptors(std::vector<Descriptor>{base}, std::vector<Descriptor>{near, far}, {}, out);
  ASSERT_EQ(n, 1);
  EXPECT_EQ(out[0].train, 0);
  EXPECT_EQ(out[0].distance, 1);
  // Mutual: twin's best train is near (2 bits) only if no other query is closer; here base (1 bit) is.
  MatchOptions no_ratio;
  no_ratio.ratio = 1.0F;
  const int mutual =
      matchDescriptors(std::vector<Descriptor>{twin, near}, std::vector<Descriptor>{near}, no_ratio, out);
  ASSERT_EQ(mutual, 1);
  EXPECT_EQ(out[0].query, 1);
}

TEST(OrbOptions, ValidateNamesTheBadField) {
  OrbOptions options;
  EXPECT_TRUE(options.validate().ok());
  options.scale_factor = 0.9F;
  auto extractor = OrbExtractor::create(options);
  ASSERT_FALSE(extractor.ok());
  EXPECT_NE(extractor.error().message().find("scale_factor"), std::string::npos);
}

}  // namespace
}  // namespace cvislam::features

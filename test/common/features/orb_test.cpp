// ORB extraction and matching on real EuRoC V1_01 stereo frames: spread over the image, and stereo matches
// that agree with the calibrated epipolar geometry.
#include "common/features/orb.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <numbers>
#include <random>
#include <utility>
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

// The image rotated by `degrees` about its centre (counter-clockwise as displayed, y down) onto a canvas that
// holds all of it, by bilinear sampling; outside the source is black. `rotate` maps a source pixel to the canvas.
struct Rotated {
  dataset::GrayImage image;
  Eigen::Matrix2d R;
  Eigen::Vector2d source_centre;
  Eigen::Vector2d canvas_centre;
  [[nodiscard]] Eigen::Vector2d rotate(const Eigen::Vector2d& p) const {
    return R * (p - source_centre) + canvas_centre;
  }
};

Rotated rotateImage(const dataset::GrayImage& src, double degrees) {
  const double a = degrees * std::numbers::pi / 180.0;
  double c = std::cos(a);
  double s = std::sin(a);
  if (std::abs(c) < 1e-12) c = 0.0;  // 90 degrees: an exact permutation of the pixels
  if (std::abs(s) < 1e-12) s = 0.0;
  Rotated r;
  // y points down, so a counter-clockwise turn on screen is [c s; -s c].
  r.R << c, s, -s, c;
  const int w = static_cast<int>(std::lround(std::abs(c) * src.width + std::abs(s) * src.height));
  const int h = static_cast<int>(std::lround(std::abs(s) * src.width + std::abs(c) * src.height));
  r.image = dataset::GrayImage(w, h, 0);
  r.source_centre = Eigen::Vector2d((src.width - 1) / 2.0, (src.height - 1) / 2.0);
  r.canvas_centre = Eigen::Vector2d((w - 1) / 2.0, (h - 1) / 2.0);
  const Eigen::Matrix2d Rt = r.R.transpose();
  for (int y = 0; y < h; ++y) {
    for (int x = 0; x < w; ++x) {
      const Eigen::Vector2d p = Rt * (Eigen::Vector2d(x, y) - r.canvas_centre) + r.source_centre;
      const double fx = std::floor(p.x() + 1e-9);
      const double fy = std::floor(p.y() + 1e-9);
      const int x0 = static_cast<int>(fx);
      const int y0 = static_cast<int>(fy);
      if (x0 < 0 || y0 < 0 || x0 >= src.width || y0 >= src.height) continue;
      const int x1 = std::min(x0 + 1, src.width - 1);
      const int y1 = std::min(y0 + 1, src.height - 1);
      const double u = std::clamp(p.x() - fx, 0.0, 1.0);
      const double v = std::clamp(p.y() - fy, 0.0, 1.0);
      const double value = (1 - v) * ((1 - u) * src.at(x0, y0) + u * src.at(x1, y0)) +
                           v * ((1 - u) * src.at(x0, y1) + u * src.at(x1, y1));
      r.image.at(x, y) = static_cast<std::uint8_t>(std::lround(value));
    }
  }
  return r;
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

// Rotating the image rotates the keypoints' orientation with it, so the steered descriptors still match: the
// brute-force matches between a frame and the frame rotated by 30, 60 and 90 degrees land where the rotation
// puts them, and a majority of the keypoints found again at their rotated position are matched.
TEST_F(OrbRealData, DescriptorsMatchAcrossImageRotation) {
  OrbOptions options;
  auto extractor = OrbExtractor::create(options);
  ASSERT_TRUE(extractor.ok());
  auto image = sequence_->loadImage(0, 10);
  ASSERT_TRUE(image.ok());
  const Frame f0 = extractFrom(*extractor, *image);
  for (const double degrees : {30.0, 60.0, 90.0}) {
    const Rotated rotated = rotateImage(*image, degrees);
    ASSERT_TRUE(extractor->checkImageSize(rotated.image.width, rotated.image.height).ok());
    const Frame f1 = extractFrom(*extractor, rotated.image);
    ASSERT_GE(f1.keypoints.size(), 490U);
    const auto expected = [&](const Keypoint& k) { return rotated.rotate(k.px.cast<double>()); };
    // Position tolerance grows with the level: a pixel at level l spans 1.2^l level-0 pixels.
    const auto tolerance = [](const Keypoint& k) { return 2.0 * std::pow(1.2, k.octave) + 1.0; };

    // Keypoints detected again: one of the rotated frame's keypoints within tolerance, at the same level or
    // next to it. Of these, how many does descriptor matching pair with that keypoint?
    std::vector<DescriptorMatch> matches(f0.descriptors.size());
    const int n = matchDescriptors(f0.descriptors, f1.descriptors, {}, matches);
    matches.resize(static_cast<std::size_t>(n));
    std::vector<int> match_of(f0.keypoints.size(), -1);
    for (const DescriptorMatch& m : matches) match_of[static_cast<std::size_t>(m.query)] = m.train;
    int repeated = 0;
    int repeated_and_matched = 0;
    int nearest_is_right = 0;
    for (std::size_t i = 0; i < f0.keypoints.size(); ++i) {
      const Keypoint& k0 = f0.keypoints[i];
      int found = -1;
      for (std::size_t j = 0; j < f1.keypoints.size() && found < 0; ++j) {
        const Keypoint& k1 = f1.keypoints[j];
        if (std::abs(static_cast<int>(k1.octave) - static_cast<int>(k0.octave)) <= 1 &&
            (k1.px.cast<double>() - expected(k0)).norm() < tolerance(k0)) {
          found = static_cast<int>(j);
        }
      }
      if (found < 0) continue;
      ++repeated;
      if (match_of[i] >= 0 &&
          (f1.keypoints[static_cast<std::size_t>(match_of[i])].px.cast<double>() - expected(k0)).norm() <
              tolerance(k0)) {
        ++repeated_and_matched;
      }
      // Plain nearest neighbour (no ratio or mutual test) lands within tolerance.
      int best = 1 << 20;
      std::size_t best_j = 0;
      for (std::size_t j = 0; j < f1.descriptors.size(); ++j) {
        const int d = hammingDistance(f0.descriptors[i], f1.descriptors[j]);
        if (d < best) {
          best = d;
          best_j = j;
        }
      }
      if ((f1.keypoints[best_j].px.cast<double>() - expected(k0)).norm() < tolerance(k0)) ++nearest_is_right;
    }
    int right = 0;
    for (const DescriptorMatch& m : matches) {
      const Keypoint& k0 = f0.keypoints[static_cast<std::size_t>(m.query)];
      if ((f1.keypoints[static_cast<std::size_t>(m.train)].px.cast<double>() - expected(k0)).norm() < tolerance(k0)) {
        ++right;
      }
    }
    std::printf(
        "rotation %2.0f deg: %d of %zu keypoints found again; %d matched (mutual, ratio) to it, %d nearest "
        "descriptor right; %d matches, %d at the rotated position\n",
        degrees, repeated, f0.keypoints.size(), repeated_and_matched, nearest_is_right, n, right);
    EXPECT_GE(repeated, 150) << degrees << " deg";
    EXPECT_GT(repeated_and_matched, repeated / 2) << degrees << " deg";
    EXPECT_GT(nearest_is_right, repeated * 3 / 4) << degrees << " deg";
    EXPECT_GE(n, 100) << degrees << " deg";
    EXPECT_GT(static_cast<double>(right), 0.9 * n) << degrees << " deg";
  }
}

TEST_F(OrbRealData, SameImageGivesIdenticalOutput) {
  auto a = OrbExtractor::create({});
  auto b = OrbExtractor::create({});
  ASSERT_TRUE(a.ok() && b.ok());
  auto image = sequence_->loadImage(0, 20);
  auto other = sequence_->loadImage(1, 40);
  ASSERT_TRUE(image.ok() && other.ok());
  const Frame first = extractFrom(*a, *image);
  (void)extractFrom(*a, *other);  // state left by another frame must not leak into the next
  const Frame again = extractFrom(*a, *image);
  const Frame fresh = extractFrom(*b, *image);
  ASSERT_EQ(first.keypoints.size(), 500U);
  for (const Frame* f : {&again, &fresh}) {
    ASSERT_EQ(f->keypoints.size(), first.keypoints.size());
    for (std::size_t i = 0; i < first.keypoints.size(); ++i) {
      EXPECT_EQ(f->keypoints[i].px, first.keypoints[i].px) << i;
      EXPECT_EQ(f->keypoints[i].response, first.keypoints[i].response) << i;
      EXPECT_EQ(f->keypoints[i].angle_deg, first.keypoints[i].angle_deg) << i;
      EXPECT_EQ(f->keypoints[i].octave, first.keypoints[i].octave) << i;
      EXPECT_EQ(f->descriptors[i], first.descriptors[i]) << i;
    }
  }
}

// The corner detector runs 32 lanes with AVX2 and 16 without; both must give the same features, bit for bit.
TEST_F(OrbRealData, TheWideAndTheNarrowCornerDetectorsAgree) {
  ASSERT_EQ(setenv("CVISLAM_ORB_NARROW", "1", 1), 0);
  auto narrow = OrbExtractor::create({});
  ASSERT_EQ(unsetenv("CVISLAM_ORB_NARROW"), 0);
  auto wide = OrbExtractor::create({});
  ASSERT_TRUE(narrow.ok() && wide.ok());
  EXPECT_EQ(narrow->cornerLanes(), 16);
  if (wide->cornerLanes() != 32) GTEST_SKIP() << "this CPU has no AVX2: only the 16-lane detector runs here";
  for (const auto& [camera, frame] : {std::pair{0, 0}, std::pair{0, 33}, std::pair{1, 60}}) {
    auto image = sequence_->loadImage(camera, static_cast<std::size_t>(frame));
    ASSERT_TRUE(image.ok()) << image.error().toString();
    const Frame a = extractFrom(*narrow, *image);
    const Frame b = extractFrom(*wide, *image);
    ASSERT_EQ(a.keypoints.size(), 500U);
    ASSERT_EQ(b.keypoints.size(), a.keypoints.size());
    for (std::size_t i = 0; i < a.keypoints.size(); ++i) {
      EXPECT_EQ(b.keypoints[i].px, a.keypoints[i].px) << "camera " << camera << " frame " << frame << " feature " << i;
      EXPECT_EQ(b.keypoints[i].response, a.keypoints[i].response) << i;
      EXPECT_EQ(b.keypoints[i].octave, a.keypoints[i].octave) << i;
      EXPECT_EQ(b.descriptors[i], a.descriptors[i]) << i;
    }
  }
}

TEST_F(OrbRealData, KeypointsAreInsideTheImageOnTheirLevelAndStrongestFirst) {
  auto extractor = OrbExtractor::create({});
  ASSERT_TRUE(extractor.ok());
  auto image = sequence_->loadImage(0, 30);
  ASSERT_TRUE(image.ok());
  const Frame f = extractFrom(*extractor, *image);
  ASSERT_EQ(f.keypoints.size(), 500U);
  std::vector<int> per_level(8, 0);
  for (std::size_t i = 0; i < f.keypoints.size(); ++i) {
    const Keypoint& k = f.keypoints[i];
    ASSERT_LT(k.octave, 8);
    ++per_level[k.octave];
    const float border = 19.0F * std::pow(1.2F, static_cast<float>(k.octave)) - 1.0F;
    EXPECT_GE(k.px.x(), border);
    EXPECT_GE(k.px.y(), border);
    EXPECT_LE(k.px.x(), static_cast<float>(image->width) - border);
    EXPECT_LE(k.px.y(), static_cast<float>(image->height) - border);
    EXPECT_GE(k.angle_deg, 0.0F);
    EXPECT_LT(k.angle_deg, 360.0F);
    EXPECT_GT(k.response, static_cast<float>(extractor->options().fast_threshold));
    if (i > 0) {
      EXPECT_LE(k.response, f.keypoints[i - 1].response);
    }
  }
  std::printf("keypoints per level:");
  for (const int c : per_level) std::printf(" %d", c);
  std::printf("\n");
  EXPECT_GT(per_level[0], 0);
  EXPECT_GT(per_level[1] + per_level[2] + per_level[3], 0);  // the pyramid contributes
}

// Other option values than the defaults: few or many levels, few candidates, a coarse or fine grid, smaller output
// spans than max_features. Run under the asan preset, this checks that extract stays inside its buffers.
TEST_F(OrbRealData, OtherOptionsGiveAtMostTheRequestedFeatures) {
  auto image = sequence_->loadImage(0, 50);
  ASSERT_TRUE(image.ok());
  struct Case {
    int max_features, levels, candidates_per_feature, columns, rows;
    float scale_factor;
  };
  for (const Case c : {Case{50, 1, 1, 1, 1, 1.2F}, Case{50, 16, 1, 64, 64, 2.0F}, Case{1000, 4, 3, 16, 12, 1.5F},
                       Case{3, 8, 100, 2, 2, 1.1F}, Case{2000, 8, 50, 8, 6, 1.2F}}) {
    OrbOptions options;
    options.max_features = c.max_features;
    options.pyramid_levels = c.levels;
    options.candidates_per_feature = c.candidates_per_feature;
    options.grid_columns = c.columns;
    options.grid_rows = c.rows;
    options.scale_factor = c.scale_factor;
    options.max_width = image->width;
    options.max_height = image->height;
    auto extractor = OrbExtractor::create(options);
    ASSERT_TRUE(extractor.ok()) << extractor.error().toString();
    std::vector<Keypoint> keypoints(static_cast<std::size_t>(c.max_features));
    std::vector<Descriptor> descriptors(keypoints.size());
    const int n = extractor->extract(image->pixels, image->width, image->height, keypoints, descriptors);
    EXPECT_GT(n, 0);
    EXPECT_LE(n, c.max_features);
    for (int i = 0; i < n; ++i) EXPECT_LT(keypoints[static_cast<std::size_t>(i)].octave, c.levels);
    // Output spans shorter than max_features bound the count.
    const int m = extractor->extract(image->pixels, image->width, image->height, std::span(keypoints).first(2),
                                     std::span(descriptors).first(2));
    EXPECT_EQ(m, std::min(2, n));
  }
}

TEST(OrbExtractor, RefusesImagesLargerThanItsBuffers) {
  OrbOptions options;
  options.max_width = 640;
  options.max_height = 480;
  auto extractor = OrbExtractor::create(options);
  ASSERT_TRUE(extractor.ok());
  EXPECT_TRUE(extractor->checkImageSize(640, 480).ok());
  EXPECT_FALSE(extractor->checkImageSize(641, 480).ok());
  EXPECT_FALSE(extractor->checkImageSize(640, 481).ok());
  EXPECT_FALSE(extractor->checkImageSize(0, 480).ok());
  const dataset::GrayImage large(752, 480, 100);
  std::vector<Keypoint> keypoints(500);
  std::vector<Descriptor> descriptors(500);
  EXPECT_EQ(extractor->extract(large.pixels, large.width, large.height, keypoints, descriptors), 0);
  // Too few pixels for the stated size.
  EXPECT_EQ(extractor->extract(std::span(large.pixels).first(1000), 640, 480, keypoints, descriptors), 0);
  // A flat image has no corners; a tiny one has no room for them.
  const dataset::GrayImage flat(640, 480, 100);
  EXPECT_EQ(extractor->extract(flat.pixels, flat.width, flat.height, keypoints, descriptors), 0);
  const dataset::GrayImage tiny(8, 8, 100);
  EXPECT_EQ(extractor->extract(tiny.pixels, tiny.width, tiny.height, keypoints, descriptors), 0);
  options.max_width = 5000;
  EXPECT_FALSE(OrbExtractor::create(options).ok());
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

// Projection search on a real EuRoC frame's ORB features: map points predicted a few pixels off find their
// keypoint despite a changed descriptor; points predicted too far, or with a foreign descriptor, do not; a keypoint
// serves one point.
#include "agent_rt/tracking/projection_search.hpp"

#include <random>
#include <set>
#include <vector>

#include <gtest/gtest.h>

#include "common/dataset/euroc.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::agent {
namespace {

struct FrameFeatures {
  int width = 0;
  int height = 0;
  std::vector<features::Keypoint> keypoints;
  std::vector<features::Descriptor> descriptors;
};

FrameFeatures realFrame() {
  FrameFeatures f;
  const auto path = test::findData("euroc-v101-excerpt");
  if (path.empty()) return f;
  auto seq = dataset::EurocSequence::open(path);
  if (!seq.ok()) return f;
  auto image = seq->loadImage(0, 30);
  if (!image.ok()) return f;
  auto extractor = features::OrbExtractor::create({});
  f.keypoints.resize(500);
  f.descriptors.resize(500);
  const int n = extractor->extract(image->pixels, image->width, image->height, f.keypoints, f.descriptors);
  f.keypoints.resize(static_cast<std::size_t>(n));
  f.descriptors.resize(static_cast<std::size_t>(n));
  f.width = image->width;
  f.height = image->height;
  return f;
}

TEST(ProjectionSearch, PointsPredictedAFewPixelsOffFindTheirKeypoint) {
  const FrameFeatures frame = realFrame();
  if (frame.keypoints.empty()) GTEST_SKIP() << "test data 'euroc-v101-excerpt' not found under " << test::dataRoot();
  KeypointGrid grid;
  grid.build(frame.keypoints, frame.width, frame.height);

  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> offset(-4.0, 4.0);
  std::uniform_int_distribution<int> bit(0, 255);
  std::vector<ProjectedMapPoint> points;
  for (std::size_t i = 0; i < frame.keypoints.size(); ++i) {
    ProjectedMapPoint p;
    p.px = frame.keypoints[i].px.cast<double>() + Eigen::Vector2d(offset(rng), offset(rng));
    p.descriptor = frame.descriptors[i];
    for (int flip = 0; flip < 12; ++flip) {  // appearance change since the point was seen: 12 of 256 bits
      const int b = bit(rng);
      p.descriptor[static_cast<std::size_t>(b / 8)] ^= static_cast<std::uint8_t>(1U << (b % 8));
    }
    p.radius_px = 8.0;
    points.push_back(p);
  }
  ProjectionMatcher sut;
  std::vector<int> match(points.size());
  const int n = sut.search(points, grid, frame.descriptors, {}, match);
  int correct = 0;
  std::set<int> used;
  for (std::size_t i = 0; i < match.size(); ++i) {
    if (match[i] < 0) continue;
    correct += match[i] == static_cast<int>(i) ? 1 : 0;
    EXPECT_TRUE(used.insert(match[i]).second) << "keypoint " << match[i] << " matched twice";
  }
  std::printf("%d of %zu points matched, %d to their own keypoint\n", n, points.size(), correct);
  EXPECT_GE(n, static_cast<int>(0.9 * static_cast<double>(points.size())));
  EXPECT_GE(correct, static_cast<int>(0.99 * static_cast<double>(n)));
}

TEST(ProjectionSearch, PointsBeyondTheRadiusOrWithForeignDescriptorsStayUnmatched) {
  const FrameFeatures frame = realFrame();
  if (frame.keypoints.empty()) GTEST_SKIP() << "test data 'euroc-v101-excerpt' not found under " << test::dataRoot();
  KeypointGrid grid;
  grid.build(frame.keypoints, frame.width, frame.height);
  std::vector<ProjectedMapPoint> points(2);
  points[0].px = frame.keypoints[0].px.cast<double>() + Eigen::Vector2d(30.0, 0.0);  // 30 px off, radius 8
  points[0].descriptor = frame.descriptors[0];
  points[1].px = frame.keypoints[1].px.cast<double>();
  points[1].descriptor.fill(0xA5);  // nothing like any ORB descriptor of the frame... within 50 bits
  ProjectionMatcher sut;
  std::vector<int> match(points.size());
  sut.search(points, grid, frame.descriptors, {}, match);
  EXPECT_NE(match[0], 0);
  EXPECT_EQ(match[1], -1);
}

TEST(KeypointGrid, RadiusQueriesReturnExactlyTheKeypointsWithinTheRadius) {
  std::mt19937_64 rng(8);
  std::uniform_real_distribution<float> x(0.0F, 752.0F);
  std::uniform_real_distribution<float> y(0.0F, 480.0F);
  std::vector<features::Keypoint> keypoints(1000);
  for (auto& k : keypoints) k.px = Eigen::Vector2f(x(rng), y(rng));
  KeypointGrid grid;
  grid.build(keypoints, 752, 480, 16);
  for (int q = 0; q < 50; ++q) {
    const Eigen::Vector2d center(x(rng), y(rng));
    const double radius = 5.0 + q;
    std::set<int> found;
    grid.forEachWithin(center, radius, [&](int i) { found.insert(i); });
    std::set<int> expected;
    for (std::size_t i = 0; i < keypoints.size(); ++i) {
      if ((keypoints[i].px.cast<double>() - center).norm() <= radius) expected.insert(static_cast<int>(i));
    }
    EXPECT_EQ(found, expected) << "query " << q;
  }
}

}  // namespace
}  // namespace cvislam::agent

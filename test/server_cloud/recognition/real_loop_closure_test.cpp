// Place recognition on real EuRoC images (../shared/data/euroc-single-frames/vicon_room_stereo_loop_closure):
// four Vicon-room stereo pairs, where pairs 0/1 and 2/3 each view the same place from nearby poses. Each pair
// becomes a one-keyframe map (points triangulated from its stereo matches, in the left camera's frame). Both
// same-place pairs are found through the database and verified, in both directions; every cross pair is rejected.
//
// Single frames carry no gravity, so these maps are not gravity-aligned and the tilt check is off here (the
// simulated tests cover it).
#include <array>
#include <cstdio>

#include <gtest/gtest.h>

#include "common/camera/camera_model.hpp"
#include "common/dataset/euroc_calibration.hpp"
#include "common/dataset/image.hpp"
#include "common/features/orb.hpp"
#include "common/features/vocabulary.hpp"
#include "common/geometry/triangulation.hpp"
#include "server_cloud/recognition/place_recognition.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::server::recognition {
namespace {

constexpr int kFrames = 4;

struct Extracted {
  std::vector<features::Keypoint> keypoints;
  std::vector<features::Descriptor> descriptors;
};

Extracted extract(features::OrbExtractor& extractor, const dataset::GrayImage& image) {
  Extracted e;
  e.keypoints.resize(500);
  e.descriptors.resize(500);
  const int n = extractor.extract(image.pixels, image.width, image.height, e.keypoints, e.descriptors);
  e.keypoints.resize(static_cast<std::size_t>(n));
  e.descriptors.resize(static_cast<std::size_t>(n));
  return e;
}

class RealLoopClosureTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = test::findData("euroc-single-frames/vicon_room_stereo_loop_closure");
    if (dir_.empty()) GTEST_SKIP() << "euroc-single-frames not found under " << test::dataRoot();
    auto vocabulary = features::Vocabulary::load(CVISLAM_VOCABULARY_FILE);
    ASSERT_TRUE(vocabulary.ok()) << vocabulary.error().message();
    vocabulary_ = std::make_unique<features::Vocabulary>(std::move(vocabulary).value());
    auto cam0 = camera::CameraModel::create(dataset::eurocCam0());
    auto cam1 = camera::CameraModel::create(dataset::eurocCam1());
    ASSERT_TRUE(cam0.ok() && cam1.ok());
    camera_ = std::make_unique<AgentCamera>(AgentCamera{*cam0, geometry::SE3d()});
    const geometry::SE3d T_c1_c0 = dataset::eurocCam1().T_b_c.inverse() * dataset::eurocCam0().T_b_c;
    auto extractor = features::OrbExtractor::create({});
    ASSERT_TRUE(extractor.ok());
    database_ = std::make_unique<KeyframeDatabase>(vocabulary_->wordCount());
    for (int i = 0; i < kFrames; ++i) {
      auto left = dataset::readGrayImage(dir_ / ("left_img_" + std::to_string(i) + ".png"));
      auto right = dataset::readGrayImage(dir_ / ("right_img_" + std::to_string(i) + ".png"));
      ASSERT_TRUE(left.ok() && right.ok());
      const Extracted l = extract(*extractor, *left);
      const Extracted r = extract(*extractor, *right);
      maps_[static_cast<std::size_t>(i)] = std::make_unique<MapContent>(static_cast<MapId>(i));
      MapContent& map = *maps_[static_cast<std::size_t>(i)];
      ServerKeyframe kf;
      kf.id = KeyframeId{static_cast<AgentId>(i), 0};
      kf.keypoints = l.keypoints;
      kf.descriptors = l.descriptors;
      ASSERT_TRUE(map.addKeyframe(kf).ok());
      // Stereo: descriptor matches whose rays meet in front of both cameras within 1 deg.
      std::vector<features::DescriptorMatch> matches(l.descriptors.size());
      const int n = features::matchDescriptors(l.descriptors, r.descriptors, {}, matches);
      const std::array<geometry::SE3d, 2> T_c_w{geometry::SE3d(), T_c1_c0};
      geometry::TriangulationOptions tri;
      tri.max_bearing_error_rad = 1.0 * 3.14159265358979 / 180.0;
      std::uint32_t next_point = 0;
      for (int m = 0; m < n; ++m) {
        const auto& match = matches[static_cast<std::size_t>(m)];
        const std::array<Eigen::Vector3d, 2> bearings{
            cam0->unproject(l.keypoints[static_cast<std::size_t>(match.query)].px.cast<double>()),
            cam1->unproject(r.keypoints[static_cast<std::size_t>(match.train)].px.cast<double>())};
        auto p = geometry::triangulateLinear(T_c_w, bearings, tri);
        if (!p.ok() || p->z() > 15.0) continue;
        ServerMapPoint point;
        point.id = MapPointId{static_cast<AgentId>(i), next_point++};
        point.reference = kf.id;
        point.p_w = *p;
        point.descriptor = l.descriptors[static_cast<std::size_t>(match.query)];
        ASSERT_TRUE(map.addPoint(point).ok());
        ASSERT_TRUE(map.addObservation(kf.id, static_cast<std::uint16_t>(match.query), point.id).ok());
      }
      points_[static_cast<std::size_t>(i)] = static_cast<int>(next_point);
      features::BowVector bow;
      features::FeatureVector fv;
      vocabulary_->transform(l.descriptors, bow, &fv, options_.direct_level);
      ASSERT_TRUE(database_->add(kf.id, map.id(), std::move(bow), std::move(fv)).ok());
    }
    options_.max_tilt_deg = 180.0;  // no gravity in single frames
  }

  static bool samePlace(int a, int b) { return a / 2 == b / 2; }

  std::filesystem::path dir_;
  std::unique_ptr<features::Vocabulary> vocabulary_;
  std::unique_ptr<AgentCamera> camera_;
  std::unique_ptr<KeyframeDatabase> database_;
  std::array<std::unique_ptr<MapContent>, kFrames> maps_;
  std::array<int, kFrames> points_{};
  RecognitionOptions options_;
};

TEST_F(RealLoopClosureTest, VerifiesBothSamePlacePairsAndRejectsEveryCrossPair) {
  const CameraLookup cameras = [&](AgentId) { return camera_.get(); };
  std::printf("BoW scores (real, vicon_room_stereo_loop_closure left images; 0/1 and 2/3 are the same place):\n");
  for (int i = 0; i < kFrames; ++i) {
    std::printf("  %d:", i);
    for (int j = 0; j < kFrames; ++j) {
      std::printf(" %.3f", features::bowScore(database_->find(KeyframeId{static_cast<AgentId>(i), 0})->bow,
                                              database_->find(KeyframeId{static_cast<AgentId>(j), 0})->bow));
    }
    std::printf("   (%d stereo points)\n", points_[static_cast<std::size_t>(i)]);
  }
  for (int i = 0; i < kFrames; ++i) {
    for (int j = 0; j < kFrames; ++j) {
      if (i == j) continue;
      const KeyframeId q{static_cast<AgentId>(i), 0};
      const KeyframeId c{static_cast<AgentId>(j), 0};
      const double score = features::bowScore(database_->find(q)->bow, database_->find(c)->bow);
      const Verification v = verifyCandidate(*database_, *maps_[static_cast<std::size_t>(i)], q,
                                             *maps_[static_cast<std::size_t>(j)], c, score, cameras, options_);
      std::printf("  %d -> %d: %s, %s\n", i, j, std::string(toString(v.rejection)).c_str(), v.detail.c_str());
      if (samePlace(i, j)) {
        EXPECT_TRUE(v.accepted()) << i << " -> " << j << ": " << v.detail;
        if (v.accepted()) {
          EXPECT_LT(v.match->T_qmap_cmap.translation().norm(), 2.0);  // nearby poses
        }
      } else {
        EXPECT_FALSE(v.accepted()) << i << " -> " << j << ": " << v.detail;
      }
    }
  }
}

TEST_F(RealLoopClosureTest, TheDatabaseProposesTheSamePlaceAndItIsTheMatch) {
  const CameraLookup cameras = [&](AgentId) { return camera_.get(); };
  const MapLookup maps = [&](MapId id) -> const MapContent* { return id < kFrames ? maps_[id].get() : nullptr; };
  for (int i = 0; i < kFrames; ++i) {
    const KeyframeId q{static_cast<AgentId>(i), 0};
    auto result =
        recognize(*database_, *maps_[static_cast<std::size_t>(i)], q, QueryKind::kMapMatch, maps, cameras, options_);
    ASSERT_TRUE(result.ok()) << result.error().message();
    bool proposed = false;
    for (const Candidate& c : result->search.candidates) proposed = proposed || samePlace(i, static_cast<int>(c.map));
    EXPECT_TRUE(proposed) << "frame " << i << ": the same place is not among the BoW candidates";
    ASSERT_TRUE(result->best.has_value()) << "frame " << i;
    EXPECT_TRUE(samePlace(i, static_cast<int>(result->best->candidate_map))) << "frame " << i;
  }
}

}  // namespace
}  // namespace cvislam::server::recognition

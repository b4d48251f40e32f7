// ingestBatch: a checked batch lands in the agent's server maps (keyframes, points, observations, merges,
// updates, removals, IMU links rebuilt), a new agent map opens a new server map, and every malformed batch is
// refused with an error that names the problem while nothing at all changes.
#include "server_cloud/ingest/batch_ingest.hpp"

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <functional>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "common/camera/camera_model.hpp"
#include "cvislam/v1/agent_link.pb.h"
#include "proto/wire/wire.hpp"
#include "test/server_cloud/link_messages.hpp"

namespace cvislam::server {
namespace {

using test::addObservations;
using test::keyframeTime;
using test::makeKeyframe;
using test::makeKeyframeBatch;
using test::makePoint;
using test::makeState;
using ::testing::AllOf;
using ::testing::HasSubstr;

constexpr AgentId kAgent = 3;
constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr float kInf = std::numeric_limits<float>::infinity();
constexpr double kNaN64 = std::numeric_limits<double>::quiet_NaN();  // for the double fields of a pose
constexpr double kInf64 = std::numeric_limits<double>::infinity();

KeyframeId kfId(std::uint32_t counter) {
  return KeyframeId{kAgent, counter};
}
MapPointId ptId(std::uint32_t counter) {
  return MapPointId{kAgent, counter};
}

// A monocular-inertial agent with EuRoC's 752x480 cam0, as its Hello would have described it.
AgentSensors euRocMonoSensors() {
  dataset::CameraCalibration calibration;  // EuRoC cam0 by default
  auto cam0 = camera::CameraModel::create(calibration);
  EXPECT_TRUE(cam0.ok());
  return AgentSensors{.mode = SensorMode::kMono,
                      .uses_imu = true,
                      .cam0 = *cam0,
                      .cam1 = std::nullopt,
                      .T_s_c0 = geometry::SE3d(),
                      .T_s_c1 = geometry::SE3d(),
                      .imu_noise = imu::ImuNoise{},
                      .imu_rate_hz = 200.0};
}

// Everything the server holds of the agent, as text: equal snapshots mean nothing changed.
std::string snapshot(const AgentRecord& agent, const MapStack& stack) {
  std::ostringstream out;
  out.precision(17);
  out << "held keyframes " << agent.keyframes.size() << ", points " << agent.points.size() << ", agent maps "
      << agent.agent_maps.size() << "\n";
  for (const auto& map : stack.maps()) {
    auto content = map->read();
    out << "map " << map->id() << ": " << content->keyframes().size() << " keyframes, " << content->points().size()
        << " points, " << content->covisibilityEdges() << " edges\n";
    std::vector<KeyframeId> keyframes;
    for (const auto& [id, kf] : content->keyframes()) keyframes.push_back(id);
    std::sort(keyframes.begin(), keyframes.end());
    for (const KeyframeId& id : keyframes) {
      const ServerKeyframe& kf = *content->keyframe(id);
      out << " kf " << id.toString() << " p " << kf.T_w_s.translation().transpose() << " q "
          << kf.T_w_s.so3().quaternion().coeffs().transpose() << " v " << kf.v_w.transpose() << " bg "
          << kf.bias.gyro.transpose() << " ba " << kf.bias.accel.transpose() << " obs " << kf.observationCount()
          << "\n";
    }
    std::vector<MapPointId> points;
    for (const auto& [id, p] : content->points()) points.push_back(id);
    std::sort(points.begin(), points.end());
    for (const MapPointId& id : points) {
      const ServerMapPoint& p = *content->point(id);
      out << " pt " << id.toString() << " p " << p.p_w.transpose() << " ref " << p.reference.toString() << " obs "
          << p.observations.size() << "\n";
    }
  }
  return out.str();
}

class BatchIngestTest : public ::testing::Test {
 protected:
  BatchIngestTest() {
    agent_.id = kAgent;
    agent_.sensors = euRocMonoSensors();
  }

  Result<IngestReport> ingest(const v1::MapBatch& batch) { return ingestBatch(batch, agent_, stack_, limits_); }
  void ingestOk(const v1::MapBatch& batch) {
    auto report = ingest(batch);
    ASSERT_TRUE(report.ok()) << report.error().toString();
  }
  // The one server map of agent map 0.
  [[nodiscard]] std::shared_ptr<ServerMap> map0() const { return stack_.find(agent_.agent_maps.at(0).map); }

  AgentRecord agent_;
  MapStack stack_;
  IngestLimits limits_;
};

TEST_F(BatchIngestTest, ValidBatchStoresKeyframesPointsAndObservationsInOneNewMap) {
  const v1::MapBatch batch = makeKeyframeBatch(1, 0, 3);

  auto report = ingest(batch);

  ASSERT_TRUE(report.ok()) << report.error().toString();
  EXPECT_EQ(report->keyframes, 3);
  EXPECT_EQ(report->points, 3);
  EXPECT_EQ(report->observations, 5);  // each keyframe sees its own point, and the next keyframe's point
  EXPECT_EQ(report->maps_opened, 1);
  EXPECT_EQ(report->imu_links_missing, 0);
  ASSERT_EQ(stack_.maps().size(), 1U);
  auto content = map0()->read();
  EXPECT_EQ(content->keyframes().size(), 3U);
  EXPECT_EQ(content->points().size(), 3U);
  EXPECT_EQ(content->covisibility(kfId(0), kfId(1)), 1);
  EXPECT_EQ(content->covisibility(kfId(1), kfId(2)), 1);
  EXPECT_EQ(content->covisibility(kfId(0), kfId(2)), 0);
  EXPECT_TRUE(content->checkConsistency().ok());
  EXPECT_EQ(agent_.keyframes.size(), 3U);
  EXPECT_EQ(agent_.points.size(), 3U);
  EXPECT_EQ(agent_.keyframes.at(2).keypoints, static_cast<std::uint32_t>(test::kKeypointsPerKeyframe));
}

TEST_F(BatchIngestTest, KeyframeIsStoredWithTheStateAndKeypointsItWasSentWith) {
  const v1::MapBatch batch = makeKeyframeBatch(1, 0, 2);
  const v1::Keyframe& sent = batch.keyframes(1);

  ingestOk(batch);

  auto content = map0()->read();
  const ServerKeyframe* kf = content->keyframe(kfId(1));
  ASSERT_NE(kf, nullptr);
  EXPECT_EQ(kf->t_ns, keyframeTime(1));
  EXPECT_DOUBLE_EQ(kf->T_w_s.translation().x(), sent.state().t_w_s().px());
  EXPECT_NEAR(kf->T_w_s.so3().quaternion().z(), sent.state().t_w_s().qz(), 1e-7);
  EXPECT_FLOAT_EQ(static_cast<float>(kf->v_w.y()), sent.state().v_w(1));
  EXPECT_FLOAT_EQ(static_cast<float>(kf->bias.accel.z()), sent.state().bias_accel(2));
  ASSERT_EQ(kf->keypoints.size(), static_cast<std::size_t>(test::kKeypointsPerKeyframe));
  EXPECT_FLOAT_EQ(kf->keypoints[13].px.x(), sent.keypoints().xy(26));
  EXPECT_FLOAT_EQ(kf->keypoints[13].px.y(), sent.keypoints().xy(27));
  EXPECT_EQ(kf->keypoints[13].octave, static_cast<std::uint8_t>(sent.keypoints().octave()[13]));
  std::array<std::uint8_t, 32> sent_descriptor{};
  wire::unpackDescriptor(sent.keypoints().descriptors().data() + 4 * 13, sent_descriptor.data());
  EXPECT_EQ(kf->descriptors[13], sent_descriptor);
  const ServerMapPoint* point = content->point(ptId(1));
  ASSERT_NE(point, nullptr);
  EXPECT_EQ(point->reference, kfId(1));
  EXPECT_FLOAT_EQ(static_cast<float>(point->p_w.x()), batch.points(1).p_w(0));
}

TEST_F(BatchIngestTest, EveryKeypointIsStoredUndistortedToo) {
  dataset::CameraCalibration calibration;
  calibration.distortion_coefficients = {-0.2834, 0.0740, 0.0002, 0.00002};  // EuRoC cam0's radial-tangential
  auto cam0 = camera::CameraModel::create(calibration);
  ASSERT_TRUE(cam0.ok());
  agent_.sensors->cam0 = *cam0;
  ingestOk(makeKeyframeBatch(1, 0, 1));
  auto content = map0()->read();
  const ServerKeyframe* kf = content->keyframe(kfId(0));
  ASSERT_NE(kf, nullptr);
  ASSERT_EQ(kf->keypoints_undistorted.size(), kf->keypoints.size());
  double moved_px = 0.0;  // the undistorted pixels differ from the keypoints
  for (std::size_t k = 0; k < kf->keypoints.size(); ++k) {
    const Eigen::Vector2d expected = agent_.sensors->cam0.undistortPixel(kf->keypoints[k].px.cast<double>());
    EXPECT_LT((kf->keypoints_undistorted[k].cast<double>() - expected).norm(), 1e-3) << "keypoint " << k;
    moved_px = std::max(moved_px, (expected - kf->keypoints[k].px.cast<double>()).norm());
  }
  EXPECT_GT(moved_px, 0.5);
}

TEST_F(BatchIngestTest, PreintegrationBetweenConsecutiveKeyframesIsRebuiltFromTheRawSamples) {
  ingestOk(makeKeyframeBatch(1, 0, 2));

  ingestOk(makeKeyframeBatch(2, 2, 1));  // keyframe 2's predecessor came in the batch before

  auto content = map0()->read();
  EXPECT_FALSE(content->keyframe(kfId(0))->preintegration.has_value());
  for (std::uint32_t c : {1U, 2U}) {
    const ServerKeyframe* kf = content->keyframe(kfId(c));
    ASSERT_TRUE(kf->preintegration.has_value()) << c;
    ASSERT_TRUE(kf->imu_from.has_value());
    EXPECT_EQ(*kf->imu_from, kfId(c - 1));
    const double dt_s = static_cast<double>(keyframeTime(c) - keyframeTime(c - 1)) * 1e-9;
    EXPECT_NEAR(kf->preintegration->dt(), dt_s, 1e-12);
    // A constant rate, less the predecessor's gyro bias (the linearisation point), turns by (w - b) dt.
    const Eigen::Vector3d w = Eigen::Vector3f(0.01F, -0.02F, 0.05F).cast<double>();
    const Eigen::Vector3d b_g = Eigen::Vector3f(0.001F, 0.002F, 0.003F).cast<double>();
    EXPECT_TRUE(kf->preintegration->deltaR().log().isApprox((w - b_g) * dt_s, 1e-9))
        << kf->preintegration->deltaR().log().transpose();
  }
}

TEST_F(BatchIngestTest, KeyframeWithANewAgentMapOpensANewServerMapAndTheOldOneStays) {
  ingestOk(makeKeyframeBatch(1, 0, 2));
  const MapId first = agent_.agent_maps.at(0).map;
  v1::MapBatch batch;
  *batch.add_keyframes() = makeKeyframe(2, 1);  // tracking restarted: agent map 1
  *batch.add_points() = makePoint(2, 2);
  addObservations(batch, 2, {0}, {2});

  auto report = ingest(batch);

  ASSERT_TRUE(report.ok()) << report.error().toString();
  EXPECT_EQ(report->maps_opened, 1);
  ASSERT_EQ(stack_.maps().size(), 2U);
  ASSERT_EQ(agent_.agent_maps.size(), 2U);
  const MapId second = agent_.agent_maps.at(1).map;
  EXPECT_NE(first, second);
  EXPECT_EQ(stack_.find(first)->read()->keyframes().size(), 2U);
  EXPECT_EQ(stack_.find(first)->read()->points().size(), 2U);
  EXPECT_EQ(stack_.find(second)->read()->keyframes().size(), 1U);
  EXPECT_NE(stack_.find(second)->read()->keyframe(kfId(2)), nullptr);
  EXPECT_EQ(agent_.keyframes.at(2).map, second);
  EXPECT_EQ(agent_.points.at(2), second);
}

TEST_F(BatchIngestTest, ImuLinkToAKeyframeOfAnotherMapIsDroppedAndCounted) {
  ingestOk(makeKeyframeBatch(1, 0, 2));
  v1::MapBatch batch;
  *batch.add_keyframes() = makeKeyframe(2, 1, 1);  // new agent map, but IMU-linked to keyframe 1 of map 0

  auto report = ingest(batch);

  ASSERT_TRUE(report.ok()) << report.error().toString();
  EXPECT_EQ(report->imu_links_missing, 1);
  auto content = stack_.find(agent_.agent_maps.at(1).map)->read();
  EXPECT_FALSE(content->keyframe(kfId(2))->imu_from.has_value());
  EXPECT_FALSE(content->keyframe(kfId(2))->preintegration.has_value());
}

TEST_F(BatchIngestTest, ObservationOfAPointInAnotherMapIsRefused) {
  ingestOk(makeKeyframeBatch(1, 0, 2));
  v1::MapBatch batch;
  *batch.add_keyframes() = makeKeyframe(2, 1);
  addObservations(batch, 2, {0}, {1});  // point 1 lives in agent map 0's server map
  const std::string before = snapshot(agent_, stack_);

  auto report = ingest(batch);

  ASSERT_FALSE(report.ok());
  EXPECT_EQ(report.error().code(), ErrorCode::kInvalidArgument);
  EXPECT_THAT(report.error().message(), AllOf(HasSubstr("map point 3:1"), HasSubstr("another map")));
  EXPECT_EQ(snapshot(agent_, stack_), before);
}

TEST_F(BatchIngestTest, KeyframeAndPointSentInFullAgainAreDroppedAndCounted) {
  const v1::MapBatch batch = makeKeyframeBatch(1, 0, 2);
  ingestOk(batch);
  v1::MapBatch again = batch;
  again.set_sequence(2);
  again.clear_observations();
  again.mutable_keyframes(0)->mutable_state()->mutable_t_w_s()->set_px(50.0);  // a resend is not an update
  const std::string before = snapshot(agent_, stack_);

  auto report = ingest(again);

  ASSERT_TRUE(report.ok()) << report.error().toString();
  EXPECT_EQ(report->duplicate_objects, 4);
  EXPECT_EQ(report->keyframes, 0);
  EXPECT_EQ(report->points, 0);
  EXPECT_EQ(snapshot(agent_, stack_), before);
}

TEST_F(BatchIngestTest, KeyframeAndPointUpdatesReplaceTheStoredState) {
  ingestOk(makeKeyframeBatch(1, 0, 2));
  map0()->write()->keyframe(kfId(0))->refined = true;  // as a GBA leaves it
  v1::MapBatch batch;
  v1::KeyframeState state = makeState(0);
  state.mutable_t_w_s()->set_px(7.5);
  state.set_v_w(2, -0.5F);
  state.set_bias_gyro(0, 0.25F);
  *batch.add_keyframe_updates() = state;
  batch.mutable_point_updates()->add_point(1);
  for (float v : {4.0F, 5.0F, 6.0F}) batch.mutable_point_updates()->add_p_w(v);

  auto report = ingest(batch);

  ASSERT_TRUE(report.ok()) << report.error().toString();
  EXPECT_EQ(report->keyframe_updates, 1);
  EXPECT_EQ(report->point_updates, 1);
  auto content = map0()->read();
  const ServerKeyframe* kf = content->keyframe(kfId(0));
  EXPECT_DOUBLE_EQ(kf->T_w_s.translation().x(), 7.5);
  EXPECT_DOUBLE_EQ(kf->v_w.z(), -0.5);
  EXPECT_DOUBLE_EQ(kf->bias.gyro.x(), 0.25);
  EXPECT_TRUE(agent_.corrections.empty());  // the agent's own updates are not server corrections
  EXPECT_FALSE(kf->refined) << "the agent's estimate replaced the server's";
  EXPECT_TRUE(content->point(ptId(1))->p_w.isApprox(Eigen::Vector3d(4, 5, 6)));
}

TEST_F(BatchIngestTest, StatesAndPositionsAreStoredInTheServerMapFrame) {
  ingestOk(makeKeyframeBatch(1, 0, 1));
  // As if a merge had moved agent map 0 into a server map frame: T_m_w is 90 deg about z plus a shift.
  const geometry::SE3d T_m_w(geometry::SO3d::exp(Eigen::Vector3d(0, 0, M_PI / 2)), Eigen::Vector3d(10, 0, 0));
  agent_.agent_maps.at(0).T_m_w = T_m_w;
  v1::MapBatch batch = makeKeyframeBatch(2, 1, 1);
  *batch.add_keyframe_updates() = makeState(0);
  batch.mutable_point_updates()->add_point(0);
  for (float v : {1.0F, 2.0F, 3.0F}) batch.mutable_point_updates()->add_p_w(v);

  ingestOk(batch);

  auto content = map0()->read();
  const auto expect_in_map_frame = [&](std::uint32_t c) {
    const v1::KeyframeState s = makeState(c);
    const Eigen::Vector3d p_w(s.t_w_s().px(), s.t_w_s().py(), s.t_w_s().pz());
    const Eigen::Vector3d v_w = Eigen::Vector3f(s.v_w(0), s.v_w(1), s.v_w(2)).cast<double>();
    const ServerKeyframe* kf = content->keyframe(kfId(c));
    EXPECT_TRUE(kf->T_w_s.translation().isApprox(T_m_w * p_w, 1e-9)) << c << ": " << kf->T_w_s.translation();
    EXPECT_TRUE(kf->v_w.isApprox(T_m_w.so3() * v_w, 1e-9)) << c;
  };
  expect_in_map_frame(0);  // the update
  expect_in_map_frame(1);  // the new keyframe
  EXPECT_TRUE(content->point(ptId(0))->p_w.isApprox(T_m_w * Eigen::Vector3d(1, 2, 3), 1e-9));
  const v1::MapPoint sent = makePoint(1, 1);
  EXPECT_TRUE(content->point(ptId(1))->p_w.isApprox(
      T_m_w * Eigen::Vector3f(sent.p_w(0), sent.p_w(1), sent.p_w(2)).cast<double>(), 1e-6));
}

TEST_F(BatchIngestTest, MergeMovesTheObservationsAndForgetsTheDroppedPoint) {
  ingestOk(makeKeyframeBatch(1, 0, 3));
  v1::MapBatch batch;
  batch.mutable_merges()->add_drop(2);
  batch.mutable_merges()->add_keep(0);

  auto report = ingest(batch);

  ASSERT_TRUE(report.ok()) << report.error().toString();
  EXPECT_EQ(report->merges, 1);
  EXPECT_EQ(agent_.points.count(2), 0U);
  auto content = map0()->read();
  EXPECT_EQ(content->point(ptId(2)), nullptr);
  EXPECT_EQ(content->point(ptId(0))->observations.size(), 3U);  // keyframe 0, and 1 and 2 that saw point 2
  EXPECT_TRUE(content->checkConsistency().ok());
}

TEST_F(BatchIngestTest, RemovalsTakeThePointsAndKeyframesOutOfTheMapAndTheRecord) {
  ingestOk(makeKeyframeBatch(1, 0, 3));
  v1::MapBatch batch;
  batch.add_removed_points(1);
  batch.add_removed_keyframes(2);  // the only observer of point 2 besides keyframe 1

  auto report = ingest(batch);

  ASSERT_TRUE(report.ok()) << report.error().toString();
  EXPECT_EQ(report->removed_points, 1);
  EXPECT_EQ(report->removed_keyframes, 1);
  auto content = map0()->read();
  EXPECT_EQ(content->point(ptId(1)), nullptr);
  EXPECT_EQ(content->keyframe(kfId(2)), nullptr);
  ASSERT_NE(content->point(ptId(2)), nullptr);             // keyframe 1 still sees it...
  EXPECT_EQ(content->point(ptId(2))->reference, kfId(1));  // ...and becomes its reference
  EXPECT_EQ(agent_.keyframes.count(2), 0U);
  EXPECT_EQ(agent_.points.count(1), 0U);
  EXPECT_EQ(agent_.points.size(), content->points().size());
  EXPECT_TRUE(content->checkConsistency().ok());
}

TEST_F(BatchIngestTest, RemovingAKeyframeForgetsEveryPointThatWentWithIt) {
  // Point 0 is made by keyframe 0, which later sees a new point 2 at that keypoint instead: point 0 is left
  // with its reference and no observer. When keyframe 0 goes, point 0 goes with it, and the record must
  // forget it too.
  ingestOk(makeKeyframeBatch(1, 0, 2));
  v1::MapBatch relink;
  *relink.add_points() = makePoint(2, 1);
  addObservations(relink, 0, {0}, {2});
  ingestOk(relink);
  ASSERT_EQ(map0()->read()->point(ptId(0))->observations.size(), 0U);
  v1::MapBatch removal;
  removal.add_removed_keyframes(0);

  ingestOk(removal);

  EXPECT_EQ(map0()->read()->point(ptId(0)), nullptr);
  EXPECT_EQ(agent_.points.count(0), 0U);
  EXPECT_EQ(agent_.points.size(), map0()->read()->points().size());
  // And an observation of it is refused as unknown, not silently dropped.
  v1::MapBatch late;
  addObservations(late, 1, {5}, {0});
  auto report = ingest(late);
  ASSERT_FALSE(report.ok());
  EXPECT_THAT(report.error().message(), HasSubstr("map point 3:0, which the server never received"));
}

TEST_F(BatchIngestTest, BatchBeforeTheSensorsAreKnownIsRefusedAsFailedPrecondition) {
  agent_.sensors.reset();

  auto report = ingest(makeKeyframeBatch(1, 0, 1));

  ASSERT_FALSE(report.ok());
  EXPECT_EQ(report.error().code(), ErrorCode::kFailedPrecondition);
  EXPECT_THAT(report.error().message(), HasSubstr("before the Hello"));
  EXPECT_TRUE(stack_.maps().empty());
}

TEST_F(BatchIngestTest, KeyframeWithMoreKeypointsThanTheLimitIsRefused) {
  limits_.max_keypoints_per_keyframe = test::kKeypointsPerKeyframe - 1;

  auto report = ingest(makeKeyframeBatch(1, 0, 1));

  ASSERT_FALSE(report.ok());
  EXPECT_EQ(report.error().code(), ErrorCode::kInvalidArgument);
  EXPECT_THAT(report.error().message(),
              AllOf(HasSubstr("keyframe 3:0"), HasSubstr("50 keypoints, more than the limit 49")));
  EXPECT_TRUE(stack_.maps().empty());
}

TEST_F(BatchIngestTest, KeyframeWithMoreImuSamplesThanTheLimitIsRefused) {
  ingestOk(makeKeyframeBatch(1, 0, 1));
  limits_.max_imu_samples_per_keyframe = 20;  // the batch carries 21
  const std::string before = snapshot(agent_, stack_);

  auto report = ingest(makeKeyframeBatch(2, 1, 1));

  ASSERT_FALSE(report.ok());
  EXPECT_EQ(report.error().code(), ErrorCode::kInvalidArgument);
  EXPECT_THAT(report.error().message(), HasSubstr("21 IMU samples, more than the limit 20"));
  EXPECT_EQ(snapshot(agent_, stack_), before);
}

TEST_F(BatchIngestTest, AgentOpeningMoreMapsThanTheLimitIsRefusedAsResourceExhausted) {
  limits_.max_maps_per_agent = 2;
  ingestOk(makeKeyframeBatch(1, 0, 1));
  v1::MapBatch batch;
  *batch.add_keyframes() = makeKeyframe(1, 1);
  *batch.add_keyframes() = makeKeyframe(2, 2);
  const std::string before = snapshot(agent_, stack_);

  auto report = ingest(batch);

  ASSERT_FALSE(report.ok());
  EXPECT_EQ(report.error().code(), ErrorCode::kResourceExhausted);
  EXPECT_THAT(report.error().message(), HasSubstr("opens more than 2 maps"));
  EXPECT_EQ(snapshot(agent_, stack_), before);
}

// ---- Bad input: each rule, with the code, the words of the message, and nothing changed ----

struct BadBatchCase {
  std::string name;
  std::function<void(v1::MapBatch&)> break_it;
  std::vector<std::string> message_parts;
  ErrorCode code = ErrorCode::kInvalidArgument;
};

std::ostream& operator<<(std::ostream& out, const BadBatchCase& c) {
  return out << c.name;
}

// The server holds keyframes 0 and 1 and points 0 and 1 (batch 1). The batch each case breaks adds keyframe 2
// with its IMU from keyframe 1, point 2 and two observations, and updates keyframe 0 and point 0: all valid.
v1::MapBatch unbrokenBatch() {
  v1::MapBatch batch = makeKeyframeBatch(2, 2, 1);
  addObservations(batch, 2, {1}, {1});
  v1::KeyframeState update = makeState(0);
  update.mutable_t_w_s()->set_px(-3.0);
  *batch.add_keyframe_updates() = update;
  batch.mutable_point_updates()->add_point(0);
  for (float v : {-1.0F, -2.0F, -3.0F}) batch.mutable_point_updates()->add_p_w(v);
  return batch;
}

v1::Keyframe& newKeyframe(v1::MapBatch& b) {
  return *b.mutable_keyframes(0);
}
v1::Pose& newPose(v1::MapBatch& b) {
  return *newKeyframe(b).mutable_state()->mutable_t_w_s();
}

const std::vector<BadBatchCase>& badBatchCases() {
  static const std::vector<BadBatchCase> cases = {
      // Malformed parts: columns whose sizes disagree.
      {"KeypointDescriptorsShorterThanTheKeypoints",
       [](auto& b) { newKeyframe(b).mutable_keypoints()->mutable_descriptors()->Truncate(4 * 49); },
       {"keyframe 3:2", "keypoint columns disagree", "196 descriptor words"}},
      {"KeypointCoordinatesOfOddCount",
       [](auto& b) { newKeyframe(b).mutable_keypoints()->add_xy(1.0F); },
       {"keyframe 3:2", "keypoint columns disagree", "101 coordinates"}},
      {"KeypointAnglesMissing",
       [](auto& b) { newKeyframe(b).mutable_keypoints()->clear_angle(); },
       {"keyframe 3:2", "keypoint columns disagree", "0 angles"}},
      {"ImuGyroColumnLongerThanTheTimes",
       [](auto& b) { newKeyframe(b).mutable_imu()->add_gyro(0.0F); },
       {"keyframe 3:2", "IMU columns disagree", "21 times, 64 gyro"}},
      {"StereoMatchColumnsDisagree",
       [](auto& b) { newKeyframe(b).mutable_right()->add_keypoint(0); },
       {"keyframe 3:2", "stereo match columns disagree"}},
      {"ObservationKeypointsAndPointsDisagree",
       [](auto& b) { b.mutable_observations(0)->add_point(1); },
       {"observations of keyframe 3:2", "1 keypoints but 2 points"}},
      {"PointUpdateCoordinatesMissing",
       [](auto& b) { b.mutable_point_updates()->add_point(1); },
       {"point updates", "2 points but 3 coordinates"}},
      {"MergeDropAndKeepListsDisagree",
       [](auto& b) { b.mutable_merges()->add_drop(0); },
       {"merges", "drop and keep lists differ"}},
      {"VelocityWithTwoValues",
       [](auto& b) { newKeyframe(b).mutable_state()->mutable_v_w()->RemoveLast(); },
       {"keyframe 3:2 v_w", "2 values, expected 3"}},
      {"PointPositionWithFourValues",
       [](auto& b) { b.mutable_points(0)->add_p_w(1.0F); },
       {"map point 3:2 p_w", "4 values, expected 3"}},
      // Finite but absurd values: they would overflow to inf once composed into a shared map.
      {"PosePosition1e300", [](auto& b) { newPose(b).set_px(1e300); }, {"keyframe 3:2 T_w_s", "from the origin"}},
      {"Velocity1e30",
       [](auto& b) { newKeyframe(b).mutable_state()->set_v_w(0, 1e30F); },
       {"keyframe 3:2 v_w", "at most 1000"}},
      {"AccelBias1e30",
       [](auto& b) { newKeyframe(b).mutable_state()->set_bias_accel(2, -1e30F); },
       {"keyframe 3:2 bias_accel", "at most 100"}},
      {"PointPosition1e30",
       [](auto& b) { b.mutable_points(0)->set_p_w(1, 1e30F); },
       {"map point 3:2 p_w", "from the origin"}},
      {"PointUpdate1e30",
       [](auto& b) { b.mutable_point_updates()->set_p_w(0, 1e30F); },
       {"update of map point", "from the origin"}},
      // Non-finite values.
      {"PosePositionNaN", [](auto& b) { newPose(b).set_px(kNaN64); }, {"keyframe 3:2 T_w_s", "non-finite"}},
      {"PosePositionInfinite", [](auto& b) { newPose(b).set_pz(-kInf64); }, {"keyframe 3:2 T_w_s", "non-finite"}},
      {"PoseQuaternionNaN", [](auto& b) { newPose(b).set_qw(kNaN); }, {"keyframe 3:2 T_w_s", "non-finite"}},
      {"VelocityNaN",
       [](auto& b) { newKeyframe(b).mutable_state()->set_v_w(1, kNaN); },
       {"keyframe 3:2 v_w", "non-finite"}},
      {"VelocityInfinite",
       [](auto& b) { newKeyframe(b).mutable_state()->set_v_w(0, kInf); },
       {"keyframe 3:2 v_w", "non-finite"}},
      {"GyroBiasNaN",
       [](auto& b) { newKeyframe(b).mutable_state()->set_bias_gyro(2, kNaN); },
       {"keyframe 3:2 bias_gyro", "non-finite"}},
      {"AccelerometerBiasInfinite",
       [](auto& b) { newKeyframe(b).mutable_state()->set_bias_accel(0, kInf); },
       {"keyframe 3:2 bias_accel", "non-finite"}},
      {"PointPositionNaN", [](auto& b) { b.mutable_points(0)->set_p_w(1, kNaN); }, {"map point 3:2 p_w", "non-finite"}},
      {"PointPositionInfinite",
       [](auto& b) { b.mutable_points(0)->set_p_w(2, kInf); },
       {"map point 3:2 p_w", "non-finite"}},
      {"ImuGyroNaN",
       [](auto& b) { newKeyframe(b).mutable_imu()->set_gyro(7, kNaN); },
       {"keyframe 3:2", "non-finite IMU sample"}},
      {"ImuAccelerometerInfinite",
       [](auto& b) { newKeyframe(b).mutable_imu()->set_accel(30, -kInf); },
       {"keyframe 3:2", "non-finite IMU sample"}},
      {"KeyframeUpdateVelocityNaN",
       [](auto& b) { b.mutable_keyframe_updates(0)->set_v_w(0, kNaN); },
       {"update of keyframe 3:0 v_w", "non-finite"}},
      {"KeyframeUpdatePoseInfinite",
       [](auto& b) { b.mutable_keyframe_updates(0)->mutable_t_w_s()->set_py(kInf64); },
       {"update of keyframe 3:0 T_w_s", "non-finite"}},
      {"PointUpdateNaN",
       [](auto& b) { b.mutable_point_updates()->set_p_w(1, kNaN); },
       {"update of map point 3:0", "non-finite position"}},
      {"KeypointNaN",
       [](auto& b) { newKeyframe(b).mutable_keypoints()->set_xy(10, kNaN); },
       {"keyframe 3:2", "keypoint 5", "outside the 752x480 image"}},
      // Rotations that are not rotations.
      {"QuaternionLongerThanOne",
       [](auto& b) { newPose(b).set_qw(1.5F); },
       {"keyframe 3:2 T_w_s", "quaternion has norm 1.5", "not 1"}},
      {"QuaternionZero",
       [](auto& b) {
         newPose(b).set_qz(0.0F);
         newPose(b).set_qw(0.0F);
       },
       {"keyframe 3:2 T_w_s", "quaternion has norm 0.0", "not 1"}},
      {"KeyframeUpdateQuaternionNotUnit",
       [](auto& b) { b.mutable_keyframe_updates(0)->mutable_t_w_s()->set_qx(0.5F); },
       {"update of keyframe 3:0 T_w_s", "quaternion has norm", "not 1"}},
      // Keypoints outside the image.
      {"KeypointRightOfTheImage",
       [](auto& b) { newKeyframe(b).mutable_keypoints()->set_xy(14, 760.0F); },
       {"keyframe 3:2", "keypoint 7 at (760.0", "outside the 752x480 image"}},
      {"KeypointAboveTheImage",
       [](auto& b) { newKeyframe(b).mutable_keypoints()->set_xy(1, -5.0F); },
       {"keyframe 3:2", "keypoint 0 at (20.0", "-5.0", "outside the 752x480 image"}},
      {"KeypointBelowTheImage",
       [](auto& b) { newKeyframe(b).mutable_keypoints()->set_xy(99, 482.0F); },
       {"keyframe 3:2", "keypoint 49", "outside the 752x480 image"}},
      // Unknown ids.
      {"KeyframeUpdateOfAKeyframeNeverReceived",
       [](auto& b) { *b.add_keyframe_updates() = makeState(40); },
       {"update of keyframe 3:40", "keyframe 3:40, which the server never received"}},
      {"PointWithAnUnknownReferenceKeyframe",
       [](auto& b) { b.mutable_points(0)->set_reference_keyframe(40); },
       {"map point 3:2", "keyframe 3:40, which the server never received"}},
      {"ObservationOfAnUnknownPoint",
       [](auto& b) { b.mutable_observations(0)->set_point(0, 40); },
       {"observations of keyframe 3:2", "map point 3:40, which the server never received"}},
      {"ObservationByAnUnknownKeyframe",
       [](auto& b) { addObservations(b, 40, {0}, {0}); },
       {"observations of keyframe 3:40", "which the server never received"}},
      {"ObservationOfAKeypointTheKeyframeDoesNotHave",
       [](auto& b) { b.mutable_observations(0)->set_keypoint(0, 50); },
       {"observations of keyframe 3:2", "keypoint 50 of 50"}},
      {"PointUpdateOfAnUnknownPoint",
       [](auto& b) { b.mutable_point_updates()->set_point(0, 40); },
       {"point update", "map point 3:40, which the server never received"}},
      {"MergeOfAnUnknownPoint",
       [](auto& b) {
         b.mutable_merges()->add_drop(40);
         b.mutable_merges()->add_keep(0);
       },
       {"merge", "map point 3:40, which the server never received"}},
      {"RemovalOfAnUnknownPoint",
       [](auto& b) { b.add_removed_points(40); },
       {"removal", "map point 3:40, which the server never received"}},
      {"RemovalOfAnUnknownKeyframe",
       [](auto& b) { b.add_removed_keyframes(40); },
       {"removal", "keyframe 3:40, which the server never received"}},
      // Inconsistent within the batch.
      {"KeyframeSentInFullTwice",
       [](auto& b) { *b.add_keyframes() = b.keyframes(0); },
       {"keyframe 3:2", "sent in full twice in one batch"}},
      {"PointSentInFullTwice",
       [](auto& b) { *b.add_points() = b.points(0); },
       {"map point 3:2", "sent in full twice in one batch"}},
      {"KeyframeStateOfAnotherKeyframe",
       [](auto& b) { newKeyframe(b).mutable_state()->set_counter(9); },
       {"keyframe 3:2", "its state says keyframe 9"}},
      {"KeyframeWithoutState", [](auto& b) { newKeyframe(b).clear_state(); }, {"keyframe 3:2", "no state"}},
      {"KeyframeTimeNotPositive",
       [](auto& b) { newKeyframe(b).set_t_ns(0); },
       {"keyframe 3:2", "time 0 ns is not positive"}},
      {"ImuTimesNotIncreasing",
       [](auto& b) { newKeyframe(b).mutable_imu()->set_dt_ns(3, 0); },
       {"keyframe 3:2", "IMU sample 3 does not come after the one before it"}},
      {"ImuTimeBeyondTheLargestInt64",
       [](auto& b) {
         newKeyframe(b).set_t_ns(std::numeric_limits<std::int64_t>::max() - 1'000'000);
         newKeyframe(b).mutable_imu()->set_dt_ns(20, 1'000'000'000);  // a valid 1 s step, past the end of time
       },
       {"keyframe 3:2", "IMU sample 20 is later than an int64 time in ns can be"}},
      {"ImuLinkToItself",
       [](auto& b) { newKeyframe(b).set_imu_from(2); },
       {"keyframe 3:2", "IMU link starts at itself"}},
      {"StereoMatchesFromAMonocularAgent",
       [](auto& b) {
         v1::StereoMatches* r = newKeyframe(b).mutable_right();
         r->add_keypoint(0);
         r->add_xy(10.0F);
         r->add_xy(20.0F);
         r->mutable_octave()->push_back('\0');
       },
       {"keyframe 3:2", "stereo matches from an agent that said it is monocular"}},
      {"KeypointOctaveOutOfRange",
       [](auto& b) { (*newKeyframe(b).mutable_keypoints()->mutable_octave())[4] = 40; },
       {"keyframe 3:2", "keypoint 4 has octave 40"}},
      {"PointDescriptorOf31Bytes",
       [](auto& b) { b.mutable_points(0)->mutable_orb()->RemoveLast(); },
       {"map point 3:2", "descriptor of 3 words, expected 4 (32 bytes)"}},
      {"PointOctaveOutOfRange", [](auto& b) { b.mutable_points(0)->set_octave(40); }, {"map point 3:2", "octave 40"}},
      {"MergeOfAPointIntoItself",
       [](auto& b) {
         b.mutable_merges()->add_drop(1);
         b.mutable_merges()->add_keep(1);
       },
       {"merge of map point 3:1 into itself"}},
      {"PointUpdateOfAPointMergedAwayEarlierInTheBatch",
       [](auto& b) {
         b.mutable_merges()->add_drop(0);
         b.mutable_merges()->add_keep(1);
       },
       {"point update", "map point 3:0, which an earlier part of this batch removed"}},
      {"KeyframeRemovedTwice",
       [](auto& b) {
         b.add_removed_keyframes(0);
         b.add_removed_keyframes(0);
       },
       {"removal: keyframe 3:0", "was removed in this batch"}},
      {"LivePoseWithoutItsOrientation",
       [](auto& b) {
         for (float v : {1.0F, 2.0F, 3.0F}) b.mutable_live_pose()->add_p_w_s(v);
       },
       {"live pose", "0 orientation values"}},
      {"LivePoseNotFinite",
       [](auto& b) {
         for (float v : {1.0F, std::numeric_limits<float>::quiet_NaN(), 3.0F}) b.mutable_live_pose()->add_p_w_s(v);
         for (float v : {0.0F, 0.0F, 0.0F, 1.0F}) b.mutable_live_pose()->add_q_w_s(v);
       },
       {"live pose: a non-finite position"}},
      {"LivePoseNotARotation",
       [](auto& b) {
         for (float v : {1.0F, 2.0F, 3.0F}) b.mutable_live_pose()->add_p_w_s(v);
         for (float v : {0.0F, 0.0F, 0.0F, 2.0F}) b.mutable_live_pose()->add_q_w_s(v);
       },
       {"live pose: the orientation is not a unit quaternion"}},
  };
  return cases;
}

class BadBatchTest : public BatchIngestTest, public ::testing::WithParamInterface<BadBatchCase> {
 protected:
  void SetUp() override { ingestOk(makeKeyframeBatch(1, 0, 2)); }
};

TEST_F(BatchIngestTest, UnbrokenBatchOfTheBadInputCasesIsStored) {
  // The cases below break one thing each in this batch; unbroken, it is accepted in full.
  ingestOk(makeKeyframeBatch(1, 0, 2));

  auto report = ingest(unbrokenBatch());

  ASSERT_TRUE(report.ok()) << report.error().toString();
  EXPECT_EQ(report->keyframes, 1);
  EXPECT_EQ(report->points, 1);
  EXPECT_EQ(report->observations, 2);
  EXPECT_EQ(report->keyframe_updates, 1);
  EXPECT_EQ(report->point_updates, 1);
  EXPECT_EQ(report->imu_links_missing, 0);
}

TEST_F(BatchIngestTest, TheLivePoseIsKeptOnTheRecordAndLeftOutOfTheStoredBatch) {
  ingestOk(makeKeyframeBatch(1, 0, 2));
  v1::MapBatch batch = unbrokenBatch();
  v1::LivePose& pose = *batch.mutable_live_pose();
  pose.set_t_ns(123);
  for (float v : {1.0F, 2.0F, 3.0F}) pose.add_p_w_s(v);
  for (float v : {0.0F, 0.0F, 0.6F, 0.8F}) pose.add_q_w_s(v);
  pose.set_metric(true);
  // What the store keeps is the batch without its pose: a resend with a newer pose is the same stored batch.
  v1::MapBatch without = batch;
  without.clear_live_pose();
  EXPECT_EQ(storedBody(batch), without.SerializeAsString());
  EXPECT_EQ(storedBody(without), without.SerializeAsString());

  ingestOk(batch);
  ASSERT_TRUE(agent_.live_pose.has_value());
  EXPECT_EQ(agent_.live_pose->t_ns, 123);
  EXPECT_TRUE(agent_.live_pose->metric);
  EXPECT_NEAR((agent_.live_pose->T_w_s.translation() - Eigen::Vector3d(1, 2, 3)).norm(), 0.0, 1e-6);
  EXPECT_NEAR(agent_.live_pose->T_w_s.so3().quaternion().z(), 0.6, 1e-6);
}

TEST_P(BadBatchTest, IsRefusedNamingTheProblemAndChangesNothing) {
  v1::MapBatch batch = unbrokenBatch();
  GetParam().break_it(batch);
  const std::string before = snapshot(agent_, stack_);
  const std::size_t maps_before = stack_.maps().size();

  auto report = ingest(batch);

  ASSERT_FALSE(report.ok()) << "accepted";
  EXPECT_EQ(report.error().code(), GetParam().code) << report.error().toString();
  for (const std::string& part : GetParam().message_parts) EXPECT_THAT(report.error().message(), HasSubstr(part));
  EXPECT_FALSE(agent_.live_pose.has_value()) << "a refused batch's live pose is not kept";
  EXPECT_EQ(stack_.maps().size(), maps_before);
  EXPECT_EQ(snapshot(agent_, stack_), before);
}

INSTANTIATE_TEST_SUITE_P(Rules, BadBatchTest, ::testing::ValuesIn(badBatchCases()),
                         [](const ::testing::TestParamInfo<BadBatchCase>& param_info) {
                           return param_info.param.name;
                         });

}  // namespace
}  // namespace cvislam::server

// cvislam_replay's copies: the agent ids they fly under, and the world frame each copy's batches are moved into.
// A copy must be the same flight seen from another start: every pose, velocity and position moved by one rigid
// motion about gravity, so that what the server derives from the batch (a point seen from a keyframe, the
// direction of gravity in the body frame) is unchanged.
#include "server_cloud/replay/replay_copies.hpp"

#include <cmath>

#include <gtest/gtest.h>
#include <Eigen/Geometry>

#include "cvislam/v1/agent_link.pb.h"

namespace cvislam::server::replay {
namespace {

void setState(v1::KeyframeState& s, std::uint32_t counter, const Eigen::Vector3d& p, const Eigen::Quaterniond& q) {
  s.set_counter(counter);
  v1::Pose& pose = *s.mutable_t_w_s();
  pose.set_px(p.x());
  pose.set_py(p.y());
  pose.set_pz(p.z());
  pose.set_qx(static_cast<float>(q.x()));
  pose.set_qy(static_cast<float>(q.y()));
  pose.set_qz(static_cast<float>(q.z()));
  pose.set_qw(static_cast<float>(q.w()));
  for (float v : {0.5F, -0.2F, 0.1F}) s.add_v_w(v);
  for (float b : {0.01F, 0.02F, 0.03F}) s.add_bias_gyro(b);
}

Eigen::Isometry3d poseOf(const v1::KeyframeState& s) {
  const v1::Pose& p = s.t_w_s();
  Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
  T.linear() = Eigen::Quaterniond(p.qw(), p.qx(), p.qy(), p.qz()).normalized().toRotationMatrix();
  T.translation() = Eigen::Vector3d(p.px(), p.py(), p.pz());
  return T;
}

template <typename Floats>
Eigen::Vector3d vec(const Floats& f, int i = 0) {
  return {f.Get(i), f.Get(i + 1), f.Get(i + 2)};
}

v1::MapBatch sampleBatch() {
  v1::MapBatch batch;
  batch.set_sequence(3);
  const Eigen::Quaterniond q_w_s(Eigen::AngleAxisd(0.3, Eigen::Vector3d(0.2, -0.5, 1.0).normalized()));
  setState(*batch.add_keyframes()->mutable_state(), 7, Eigen::Vector3d(1.0, 2.0, 0.5), q_w_s);
  setState(*batch.add_keyframe_updates(), 6, Eigen::Vector3d(0.8, 1.9, 0.4), q_w_s);
  v1::MapPoint& point = *batch.add_points();
  point.set_counter(40);
  for (float c : {3.0F, 1.0F, 1.5F}) point.add_p_w(c);
  for (float c : {2.0F, -1.0F, 0.7F, 4.0F, 4.0F, 4.0F}) batch.mutable_point_updates()->add_p_w(c);
  batch.mutable_point_updates()->add_point(30);
  batch.mutable_point_updates()->add_point(31);
  v1::LivePose& live = *batch.mutable_live_pose();
  for (float c : {1.1F, 2.1F, 0.5F}) live.add_p_w_s(c);
  for (float c : {static_cast<float>(q_w_s.x()), static_cast<float>(q_w_s.y()), static_cast<float>(q_w_s.z()),
                  static_cast<float>(q_w_s.w())}) {
    live.add_q_w_s(c);
  }
  return batch;
}

TEST(ReplayCopiesTest, CopiesTakeIdsAStrideApartAndCopyZeroIsTheRecording) {
  CopyOptions options;
  options.copies = 3;
  options.id_stride = 2;  // recorded agents 0 and 1
  EXPECT_EQ(copyAgentId(0, 0, options), 0);
  EXPECT_EQ(copyAgentId(1, 0, options), 1);
  EXPECT_EQ(copyAgentId(0, 1, options), 2);
  EXPECT_EQ(copyAgentId(1, 1, options), 3);
  EXPECT_EQ(copyAgentId(1, 2, options), 5);
  v1::MapBatch batch = sampleBatch();
  const std::string before = batch.SerializeAsString();
  moveToCopyWorld(batch, 0, options);
  EXPECT_EQ(batch.SerializeAsString(), before);
}

// Copy 2 of the sample: every pose, velocity and position moved by the same rotation about z and shift, and the
// geometry within the batch (a point in a keyframe's frame, gravity in the body frame, biases) unchanged.
TEST(ReplayCopiesTest, ACopyMovesEveryPoseAndPositionByOneMotionAboutGravity) {
  CopyOptions options;
  options.id_stride = 2;
  const v1::MapBatch recorded = sampleBatch();
  v1::MapBatch copy = recorded;
  moveToCopyWorld(copy, 2, options);

  const Eigen::AngleAxisd yaw(2 * options.yaw_step_rad, Eigen::Vector3d::UnitZ());
  const Eigen::Vector3d shift = 2 * Eigen::Vector3d(options.step_m[0], options.step_m[1], options.step_m[2]);
  const auto moved = [&](const Eigen::Vector3d& p) -> Eigen::Vector3d { return yaw * p + shift; };
  constexpr double kTol = 1e-5;  // the wire's floats

  const Eigen::Isometry3d T_w_s = poseOf(recorded.keyframes(0).state());
  const Eigen::Isometry3d T_w2_s = poseOf(copy.keyframes(0).state());
  EXPECT_TRUE(T_w2_s.translation().isApprox(moved(T_w_s.translation()), kTol));
  EXPECT_TRUE(T_w2_s.linear().isApprox(yaw.toRotationMatrix() * T_w_s.linear(), kTol));
  EXPECT_TRUE(vec(copy.keyframes(0).state().v_w()).isApprox(yaw * vec(recorded.keyframes(0).state().v_w()), kTol));
  EXPECT_EQ(vec(copy.keyframes(0).state().bias_gyro()), vec(recorded.keyframes(0).state().bias_gyro()));
  EXPECT_TRUE(poseOf(copy.keyframe_updates(0))
                  .translation()
                  .isApprox(moved(poseOf(recorded.keyframe_updates(0)).translation()), kTol));

  const Eigen::Vector3d p_w = vec(recorded.points(0).p_w());
  const Eigen::Vector3d p_w2 = vec(copy.points(0).p_w());
  EXPECT_TRUE(p_w2.isApprox(moved(p_w), kTol));
  // The point seen from the keyframe, and gravity in the body frame, are what they were.
  EXPECT_TRUE((T_w2_s.inverse() * p_w2).isApprox(T_w_s.inverse() * p_w, kTol));
  EXPECT_TRUE((T_w2_s.linear().transpose() * Eigen::Vector3d::UnitZ())
                  .isApprox(T_w_s.linear().transpose() * Eigen::Vector3d::UnitZ(), kTol));
  for (int i : {0, 3}) {
    EXPECT_TRUE(vec(copy.point_updates().p_w(), i).isApprox(moved(vec(recorded.point_updates().p_w(), i)), kTol));
  }
  EXPECT_EQ(copy.point_updates().point_size(), 2);
  EXPECT_TRUE(vec(copy.live_pose().p_w_s()).isApprox(moved(vec(recorded.live_pose().p_w_s())), kTol));
  const auto& q = copy.live_pose().q_w_s();
  const Eigen::Quaterniond q_w2_s(q.Get(3), q.Get(0), q.Get(1), q.Get(2));
  EXPECT_TRUE(q_w2_s.toRotationMatrix().isApprox(T_w2_s.linear(), kTol));
  EXPECT_EQ(copy.sequence(), recorded.sequence());
}

}  // namespace
}  // namespace cvislam::server::replay

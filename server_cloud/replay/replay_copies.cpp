#include "server_cloud/replay/replay_copies.hpp"

#include <Eigen/Geometry>

#include "cvislam/v1/agent_link.pb.h"

namespace cvislam::server::replay {

namespace {

// Copy k's world from the recorded one: p_copy = R * p_recorded + t.
struct CopyWorld {
  Eigen::Quaterniond q;
  Eigen::Vector3d t;

  CopyWorld(int k, const CopyOptions& options)
      : q(Eigen::AngleAxisd(k * options.yaw_step_rad, Eigen::Vector3d::UnitZ())),
        t(k * Eigen::Vector3d(options.step_m[0], options.step_m[1], options.step_m[2])) {}

  template <typename Floats>
  void movePoints(Floats& p_w) const {  // 3 values per point
    for (int i = 0; i + 2 < p_w.size(); i += 3) {
      const Eigen::Vector3d p = q * Eigen::Vector3d(p_w.Get(i), p_w.Get(i + 1), p_w.Get(i + 2)) + t;
      for (int j = 0; j < 3; ++j) p_w.Set(i + j, static_cast<float>(p[j]));
    }
  }
  template <typename Floats>
  void turnVector(Floats& v_w) const {
    if (v_w.size() != 3) return;
    const Eigen::Vector3d v = q * Eigen::Vector3d(v_w.Get(0), v_w.Get(1), v_w.Get(2));
    for (int j = 0; j < 3; ++j) v_w.Set(j, static_cast<float>(v[j]));
  }
  void moveState(v1::KeyframeState& state) const {
    if (state.has_t_w_s()) {
      v1::Pose& pose = *state.mutable_t_w_s();
      const Eigen::Vector3d p = q * Eigen::Vector3d(pose.px(), pose.py(), pose.pz()) + t;
      const Eigen::Quaterniond r = (q * Eigen::Quaterniond(pose.qw(), pose.qx(), pose.qy(), pose.qz())).normalized();
      pose.set_px(p.x());
      pose.set_py(p.y());
      pose.set_pz(p.z());
      pose.set_qx(static_cast<float>(r.x()));
      pose.set_qy(static_cast<float>(r.y()));
      pose.set_qz(static_cast<float>(r.z()));
      pose.set_qw(static_cast<float>(r.w()));
    }
    turnVector(*state.mutable_v_w());
  }
  void moveLivePose(v1::LivePose& live) const {
    movePoints(*live.mutable_p_w_s());
    auto& q_w_s = *live.mutable_q_w_s();
    if (q_w_s.size() != 4) return;
    const Eigen::Quaterniond r =
        (q * Eigen::Quaterniond(q_w_s.Get(3), q_w_s.Get(0), q_w_s.Get(1), q_w_s.Get(2))).normalized();
    q_w_s.Set(0, static_cast<float>(r.x()));
    q_w_s.Set(1, static_cast<float>(r.y()));
    q_w_s.Set(2, static_cast<float>(r.z()));
    q_w_s.Set(3, static_cast<float>(r.w()));
  }
};

}  // namespace

AgentId copyAgentId(AgentId agent, int k, const CopyOptions& options) {
  return static_cast<AgentId>(agent + k * options.id_stride);
}

void moveToCopyWorld(v1::MapBatch& batch, int k, const CopyOptions& options) {
  if (k == 0) return;
  const CopyWorld world(k, options);
  for (v1::Keyframe& keyframe : *batch.mutable_keyframes()) {
    if (keyframe.has_state()) world.moveState(*keyframe.mutable_state());
  }
  for (v1::KeyframeState& update : *batch.mutable_keyframe_updates()) world.moveState(update);
  for (v1::MapPoint& point : *batch.mutable_points()) world.movePoints(*point.mutable_p_w());
  if (batch.has_point_updates()) world.movePoints(*batch.mutable_point_updates()->mutable_p_w());
  if (batch.has_live_pose()) world.moveLivePose(*batch.mutable_live_pose());
}

}  // namespace cvislam::server::replay

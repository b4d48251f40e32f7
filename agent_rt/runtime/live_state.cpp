#include "agent_rt/runtime/live_state.hpp"

#include <algorithm>

#include "common/imu/preintegration.hpp"

namespace cvislam::agent {

using geometry::SE3d;
using geometry::SO3d;

live::StateStatus statusOf(TrackingStatus status) {
  switch (status) {
    case TrackingStatus::kWaitingForMap:
      return live::StateStatus::kWaitingForMap;
    case TrackingStatus::kTracking:
      return live::StateStatus::kTracking;
    case TrackingStatus::kRelocalising:
      return live::StateStatus::kRelocalising;
  }
  return live::StateStatus::kWaitingForMap;
}

namespace {

void writePose(const SE3d& T_w_s, const Eigen::Vector3d& v_w, live::AgentStateMessage& m) {
  const Eigen::Quaterniond& q = T_w_s.quaternion();
  m.q_w_s[0] = q.x();
  m.q_w_s[1] = q.y();
  m.q_w_s[2] = q.z();
  m.q_w_s[3] = q.w();
  for (int k = 0; k < 3; ++k) {
    m.p_w_s[k] = T_w_s.translation()[k];
    m.v_w[k] = v_w[k];
  }
}

}  // namespace

live::AgentStateMessage frameState(const FrameResult& r, std::int64_t t_ns, std::int64_t captured_steady_ns,
                                   AgentId agent) {
  live::AgentStateMessage m;
  m.kind = live::StateKind::kFrame;
  m.t_ns = t_ns;
  m.captured_steady_ns = captured_steady_ns;
  m.status = statusOf(r.status);
  m.flags = (r.tracked ? live::kTracked : 0U) | (r.keyframe ? live::kKeyframe : 0U) |
            (r.imu_initialised ? live::kMetric : 0U);
  m.agent = agent;
  m.map_id = r.map_id;
  m.map_epoch = r.map_epoch;
  writePose(r.T_w_s, r.v_w, m);
  for (int k = 0; k < 3; ++k) {
    m.gyro_bias[k] = r.bias.gyro[k];
    m.accel_bias[k] = r.bias.accel[k];
  }
  return m;
}

ImuPropagator::ImuPropagator(std::size_t capacity) {
  samples_.reserve(std::max<std::size_t>(capacity, 4));
}

void ImuPropagator::onFrameState(const live::AgentStateMessage& state) {
  if ((state.flags & live::kMetric) == 0U) {
    state_.reset();  // a world frame without gravity or scale cannot be carried by the IMU
    return;
  }
  if (state_ && state.t_ns < frame_t_ns_ && state.map_id == state_->map_id) return;
  frame_t_ns_ = state.t_ns;
  state_ = state;
  state_->kind = live::StateKind::kPropagated;
  const Eigen::Quaterniond q(state.q_w_s[3], state.q_w_s[0], state.q_w_s[1], state.q_w_s[2]);
  T_w_s_ = SE3d(SO3d(q), Eigen::Vector3d(state.p_w_s[0], state.p_w_s[1], state.p_w_s[2]));
  v_w_ = Eigen::Vector3d(state.v_w[0], state.v_w[1], state.v_w[2]);
  bias_.gyro = Eigen::Vector3d(state.gyro_bias[0], state.gyro_bias[1], state.gyro_bias[2]);
  bias_.accel = Eigen::Vector3d(state.accel_bias[0], state.accel_bias[1], state.accel_bias[2]);
  // The samples already past the frame: integrated again from it.
  keepSamplesFrom(state.t_ns);
  for (std::size_t i = 0; i < samples_.size(); ++i) {
    if (samples_[i].t_ns <= state_->t_ns) continue;
    step(i > 0 ? samples_[i - 1] : samples_[i], samples_[i].t_ns);
  }
}

std::optional<live::AgentStateMessage> ImuPropagator::onImu(const dataset::ImuSample& sample,
                                                            std::int64_t captured_steady_ns) {
  if (!samples_.empty() && sample.t_ns <= samples_.back().t_ns) return std::nullopt;
  if (samples_.size() == samples_.capacity()) samples_.erase(samples_.begin(), samples_.begin() + samples_.size() / 2);
  const dataset::ImuSample* previous = samples_.empty() ? nullptr : &samples_.back();
  const dataset::ImuSample rates = previous != nullptr ? *previous : sample;
  samples_.push_back(sample);
  if (!state_ || sample.t_ns <= state_->t_ns) return std::nullopt;
  step(rates, sample.t_ns);
  state_->captured_steady_ns = captured_steady_ns;
  return state_;
}

// From the state's time to `to_ns` with constant rates: rotation by the bias-corrected angular rate, velocity and
// position by the bias-corrected specific force turned into the world frame plus gravity.
void ImuPropagator::step(const dataset::ImuSample& rates, std::int64_t to_ns) {
  const double dt = static_cast<double>(to_ns - state_->t_ns) * 1e-9;
  if (dt <= 0.0) return;
  const Eigen::Vector3d a_w = T_w_s_.so3() * (rates.accel_s - bias_.accel) + imu::kGravityW;
  const Eigen::Vector3d p = T_w_s_.translation() + v_w_ * dt + 0.5 * a_w * dt * dt;
  v_w_ += a_w * dt;
  T_w_s_ = SE3d(T_w_s_.so3() * SO3d::exp((rates.gyro_s - bias_.gyro) * dt), p);
  state_->t_ns = to_ns;
  writePose(T_w_s_, v_w_, *state_);
}

void ImuPropagator::keepSamplesFrom(std::int64_t t_ns) {
  auto first_after = std::upper_bound(samples_.begin(), samples_.end(), t_ns,
                                      [](std::int64_t t, const dataset::ImuSample& s) { return t < s.t_ns; });
  if (first_after - samples_.begin() > 1) samples_.erase(samples_.begin(), first_after - 1);
}

}  // namespace cvislam::agent

// The agent's live state: a tracked frame's result as a state message, and the IMU carrying the newest state
// forward between frames, checked against motions whose answer is known in closed form.
#include "agent_rt/runtime/live_state.hpp"

#include <cmath>

#include <gtest/gtest.h>

namespace cvislam::agent {
namespace {

constexpr std::int64_t kImuPeriodNs = 5'000'000;  // 200 Hz

live::AgentStateMessage metricStateAt(std::int64_t t_ns, const Eigen::Vector3d& p_w, const Eigen::Vector3d& v_w) {
  FrameResult r;
  r.status = TrackingStatus::kTracking;
  r.tracked = true;
  r.imu_initialised = true;
  r.T_w_s = geometry::SE3d(geometry::SO3d(), p_w);
  r.v_w = v_w;
  return frameState(r, t_ns, 0, 3);
}

dataset::ImuSample sampleAt(std::int64_t t_ns, const Eigen::Vector3d& gyro, const Eigen::Vector3d& accel) {
  dataset::ImuSample s;
  s.t_ns = t_ns;
  s.gyro_s = gyro;
  s.accel_s = accel;
  return s;
}

Eigen::Vector3d positionOf(const live::AgentStateMessage& m) {
  return {m.p_w_s[0], m.p_w_s[1], m.p_w_s[2]};
}

const Eigen::Vector3d kLevelAtRest(0.0, 0.0, 9.81);  // a level IMU's accelerometer: the reaction to gravity

TEST(FrameState, CarriesThePoseTheFlagsAndTheBiases) {
  FrameResult r;
  r.status = TrackingStatus::kRelocalising;
  r.keyframe = true;
  r.imu_initialised = true;
  r.map_id = 2;
  r.map_epoch = 1;
  r.T_w_s = geometry::SE3d(geometry::SO3d::exp(Eigen::Vector3d(0.0, 0.0, 0.3)), Eigen::Vector3d(1.0, 2.0, 3.0));
  r.v_w = {0.1, 0.2, 0.3};
  r.bias.gyro = {0.01, 0.02, 0.03};
  r.bias.accel = {0.1, -0.1, 0.2};
  const live::AgentStateMessage m = frameState(r, 123, 456, 7);
  EXPECT_EQ(m.kind, live::StateKind::kFrame);
  EXPECT_EQ(m.status, live::StateStatus::kRelocalising);
  EXPECT_EQ(m.flags, live::kKeyframe | live::kMetric);
  EXPECT_EQ(m.agent, 7U);
  EXPECT_EQ(m.map_id, 2U);
  EXPECT_EQ(m.t_ns, 123);
  EXPECT_EQ(m.captured_steady_ns, 456);
  EXPECT_NEAR(m.q_w_s[2], std::sin(0.15), 1e-12);
  EXPECT_NEAR(m.q_w_s[3], std::cos(0.15), 1e-12);
  EXPECT_EQ(m.p_w_s[1], 2.0);
  EXPECT_EQ(m.v_w[2], 0.3);
  EXPECT_EQ(m.gyro_bias[1], 0.02);
  EXPECT_EQ(m.accel_bias[2], 0.2);
}

TEST(ImuPropagator, ALevelImuAtRestStaysPut) {
  ImuPropagator propagator(64);
  propagator.onFrameState(metricStateAt(0, {1.0, 2.0, 3.0}, Eigen::Vector3d::Zero()));
  std::optional<live::AgentStateMessage> state;
  for (std::int64_t t = 0; t <= 1'000'000'000; t += kImuPeriodNs) {
    state = propagator.onImu(sampleAt(t, Eigen::Vector3d::Zero(), kLevelAtRest), t);
  }
  ASSERT_TRUE(state.has_value());
  EXPECT_EQ(state->kind, live::StateKind::kPropagated);
  EXPECT_EQ(state->t_ns, 1'000'000'000);
  EXPECT_LT((positionOf(*state) - Eigen::Vector3d(1.0, 2.0, 3.0)).norm(), 1e-9);
}

TEST(ImuPropagator, AConstantForwardAccelerationGivesHalfATSquared) {
  ImuPropagator propagator(256);
  propagator.onFrameState(metricStateAt(0, Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero()));
  std::optional<live::AgentStateMessage> state;
  for (std::int64_t t = 0; t <= 500'000'000; t += kImuPeriodNs) {
    state = propagator.onImu(sampleAt(t, Eigen::Vector3d::Zero(), kLevelAtRest + Eigen::Vector3d(1.0, 0.0, 0.0)), t);
  }
  ASSERT_TRUE(state.has_value());
  EXPECT_NEAR(state->p_w_s[0], 0.5 * 1.0 * 0.25, 1e-9);
  EXPECT_NEAR(state->v_w[0], 0.5, 1e-9);
  EXPECT_NEAR(state->p_w_s[2], 0.0, 1e-9);
}

TEST(ImuPropagator, AConstantYawRateTurnsByRateTimesTimeAndTheGyroBiasIsTakenOff) {
  for (const double bias : {0.0, 0.05}) {
    ImuPropagator propagator(256);
    live::AgentStateMessage start = metricStateAt(0, Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero());
    start.gyro_bias[2] = bias;
    propagator.onFrameState(start);
    std::optional<live::AgentStateMessage> state;
    for (std::int64_t t = 0; t <= 1'000'000'000; t += kImuPeriodNs) {
      state = propagator.onImu(sampleAt(t, Eigen::Vector3d(0.0, 0.0, 0.5 + bias), kLevelAtRest), t);
    }
    ASSERT_TRUE(state.has_value());
    EXPECT_NEAR(state->q_w_s[2], std::sin(0.25), 1e-9) << "bias " << bias;
    EXPECT_NEAR(state->q_w_s[3], std::cos(0.25), 1e-9) << "bias " << bias;
  }
}

TEST(ImuPropagator, ALateFrameStateTakesOverAndTheSamplesPastItAreIntegratedAgain) {
  ImuPropagator propagator(256);
  propagator.onFrameState(metricStateAt(0, Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero()));
  for (std::int64_t t = 0; t <= 200'000'000; t += kImuPeriodNs) {
    (void)propagator.onImu(sampleAt(t, Eigen::Vector3d::Zero(), kLevelAtRest), t);
  }
  // Tracking's state of the frame at 0.1 s arrives now, at 0.2 s: moving at 1 m/s along x from x = 5.
  propagator.onFrameState(metricStateAt(100'000'000, {5.0, 0.0, 0.0}, {1.0, 0.0, 0.0}));
  const auto state = propagator.onImu(sampleAt(205'000'000, Eigen::Vector3d::Zero(), kLevelAtRest), 1);
  ASSERT_TRUE(state.has_value());
  EXPECT_NEAR(state->p_w_s[0], 5.0 + 0.105, 1e-9);
  EXPECT_EQ(state->t_ns, 205'000'000);
  // An older frame state than the one held changes nothing.
  propagator.onFrameState(metricStateAt(50'000'000, {-9.0, 0.0, 0.0}, Eigen::Vector3d::Zero()));
  const auto next = propagator.onImu(sampleAt(210'000'000, Eigen::Vector3d::Zero(), kLevelAtRest), 2);
  ASSERT_TRUE(next.has_value());
  EXPECT_NEAR(next->p_w_s[0], 5.0 + 0.110, 1e-9);
}

TEST(ImuPropagator, NothingIsCarriedBeforeTheStateIsMetric) {
  ImuPropagator propagator(64);
  live::AgentStateMessage up_to_scale = metricStateAt(0, Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero());
  up_to_scale.flags &= ~live::kMetric;
  propagator.onFrameState(up_to_scale);
  EXPECT_FALSE(propagator.onImu(sampleAt(kImuPeriodNs, Eigen::Vector3d::Zero(), kLevelAtRest), 0).has_value());
  // Samples not later than the one before are ignored.
  propagator.onFrameState(metricStateAt(0, Eigen::Vector3d::Zero(), Eigen::Vector3d::Zero()));
  EXPECT_FALSE(propagator.onImu(sampleAt(kImuPeriodNs, Eigen::Vector3d::Zero(), kLevelAtRest), 0).has_value());
  EXPECT_TRUE(propagator.onImu(sampleAt(2 * kImuPeriodNs, Eigen::Vector3d::Zero(), kLevelAtRest), 0).has_value());
}

}  // namespace
}  // namespace cvislam::agent

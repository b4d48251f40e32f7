// The agent's live state: a tracked frame's result as a state message, and the IMU carrying the newest state
// forward between frames, checked against motions whose answer is known in closed form.
#include "agent_rt/runtime/live_state.hpp"

#include "agent_rt/runtime/pushed_propagation.hpp"
#include "agent_rt/runtime/spsc_queue.hpp"

#include <atomic>
#include <chrono>
#include <cmath>
#include <thread>

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

TEST(SpscQueue, KeepsOrderRefusesWhenFullAndCarriesAcrossThreads) {
  SpscQueue<int> queue(4);
  for (int i = 0; i < 4; ++i) EXPECT_TRUE(queue.push(i));
  EXPECT_FALSE(queue.push(4));
  int v = -1;
  for (int i = 0; i < 4; ++i) {
    ASSERT_TRUE(queue.pop(v));
    EXPECT_EQ(v, i);
  }
  EXPECT_FALSE(queue.pop(v));
  // One producer and one consumer thread: every value arrives once, in order.
  constexpr int kValues = 20000;
  std::thread producer([&] {
    for (int i = 0; i < kValues; ++i) {
      while (!queue.push(i)) std::this_thread::yield();
    }
  });
  int expected = 0;
  while (expected < kValues) {
    if (queue.pop(v)) {
      ASSERT_EQ(v, expected);
      ++expected;
    } else {
      std::this_thread::yield();
    }
  }
  producer.join();
}

// The embedding API's IMU-rate states: frame states from one thread, samples from another, states out on its own.
TEST(PushedPropagation, CarriesTheNewestFrameStateThroughPushedSamples) {
  struct Collect final : StateListener {
    void onState(const live::AgentStateMessage& state) override {
      last_p_x.store(state.p_w_s[0]);
      last_t_ns.store(state.t_ns);
      count.fetch_add(1);
    }
    std::atomic<int> count{0};
    std::atomic<double> last_p_x{0.0};
    std::atomic<std::int64_t> last_t_ns{0};
  } collect;
  PushedPropagation propagation(collect);
  propagation.onFrameState(metricStateAt(0, {2.0, 0.0, 0.0}, {1.0, 0.0, 0.0}));
  std::this_thread::sleep_for(std::chrono::milliseconds(20));  // the frame state first, as tracking would have it
  for (std::int64_t t = kImuPeriodNs; t <= 100'000'000; t += kImuPeriodNs) {
    propagation.pushImu(sampleAt(t, Eigen::Vector3d::Zero(), kLevelAtRest), t);
  }
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(5);
  while (collect.count.load() < 20 && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  EXPECT_EQ(collect.count.load(), 20);
  EXPECT_EQ(collect.last_t_ns.load(), 100'000'000);
  EXPECT_NEAR(collect.last_p_x.load(), 2.0 + 0.1, 1e-9);  // 1 m/s for 0.1 s
  EXPECT_EQ(propagation.dropped(), 0U);
}

}  // namespace
}  // namespace cvislam::agent

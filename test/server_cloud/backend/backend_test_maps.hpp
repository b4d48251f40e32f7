// What the back-end's tests share (backend_test.cpp, backend_concurrency_test.cpp): agents' maps built from a
// synthetic visual-inertial scenario with exact ground truth (test/support/vi_scenario), as the server would hold
// them, the worker fixture of one mission, and a gate that holds a GBA while a test makes changes arrive.
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <functional>
#include <memory>
#include <mutex>

#include <gtest/gtest.h>

#include "server_cloud/backend/backend_worker.hpp"
#include "test/support/vi_scenario.hpp"

namespace cvislam::server::backend::test_maps {

using geometry::SE3d;

// How an agent's map is built from the scenario.
struct AgentPlan {
  AgentId agent = 0;
  int first = 0;  // scenario keyframes [first, last]
  int last = 0;
  // The estimate of keyframe k in the map frame is E(k) * truth (map frame and drift).
  std::function<SE3d(int)> E = [](int) { return SE3d(); };
  // Keyframes of one generation share points; a new generation makes new points (as after drift).
  std::function<int(int)> generation = [](int) { return 0; };
};

camera::CameraModel pinholeCamera(const test::ViScenario& s);
AgentSensors sensorsOf(const test::ViScenario& s);

// Adds the plan's keyframes and points to `map`, and what the server would keep in `record`.
void buildAgentMap(MapContent& map, const test::ViScenario& s, const AgentPlan& plan, AgentRecord* record);

// Adds the plan's keyframes to `map` one at a time under its write lock, without points, as ingest stores
// keyframes that arrive while the back-end solves. True when every one was added.
bool addArrivingKeyframes(ServerMap& map, const test::ViScenario& s, const AgentPlan& plan);

// Two agents over the same place, their points fused as a merge would: agent 1 flies keyframes 0-7 and agent 2
// keyframes 8-15 of `s`, seeing the same points.
void buildTwoAgentsFusedMap(MapContent& map, const test::ViScenario& s);

// Moves every keyframe but agent 1's first (the gauge) by 0.01 rad and 5 cm, its velocity by 5 cm/s, and every
// point by 5 cm (standard deviations per axis; seeded).
void perturbAllButTheGauge(MapContent& map, std::uint64_t seed);

// The largest position error of the agent's keyframes against the truth, after mapping the map frame by T.
double maxPositionError(const MapContent& map, const test::ViScenario& s, AgentId agent, const SE3d& T_truth_map = {});

// `keyframes` keyframes `interval_s` apart, 300 points, IMU at 200 Hz, seed 11.
test::ViScenario scenario(int keyframes, double interval_s, double pixel_sigma);

// A verified match as place recognition would hand it on (the caller sets the transforms).
recognition::MatchRecord matchRecord(recognition::QueryKind kind, const KeyframeId& query, MapId query_map,
                                     const KeyframeId& candidate, MapId candidate_map);

// A loop of agent 1 from keyframe `query` to keyframe `candidate` of `map`, measured exactly (the query camera's
// true pose, as the old points see it).
recognition::MatchRecord exactLoop(MapId map, const test::ViScenario& s, std::uint32_t query, std::uint32_t candidate);

// Polls `done` (the worker's stats) until it holds; false after a minute.
bool eventually(const std::function<bool()>& done);

class BackendWorkerTest : public ::testing::Test {
 protected:
  void SetUp() override { mission_ = registry_.getOrCreate("m"); }

  // A map for `plan` with the agent's record, as ingest would have left them.
  std::shared_ptr<ServerMap> addAgent(const test::ViScenario& s, const AgentPlan& plan) {
    std::shared_ptr<ServerMap> map = mission_->stack().createMap();
    auto record = mission_->agent(plan.agent)->write();
    record->sensors = sensorsOf(s);
    record->agent_maps[0] = AgentRecord::AgentMap{map->id(), SE3d()};
    buildAgentMap(*map->write(), s, plan, &*record);
    return map;
  }

  // One map that two agents share, as after a merge: agent 1 flew keyframes 0-11 and agent 2 keyframes 8-19,
  // with points of its own (nothing links them to agent 1's yet).
  std::shared_ptr<ServerMap> twoAgentsInOneMap(const test::ViScenario& s) {
    const auto map = addAgent(s, AgentPlan{.agent = 1, .first = 0, .last = 11});
    auto record = mission_->agent(2)->write();
    record->sensors = sensorsOf(s);
    record->agent_maps[0] = AgentRecord::AgentMap{map->id(), SE3d()};
    buildAgentMap(*map->write(), s, AgentPlan{.agent = 2, .first = 8, .last = 19}, &*record);
    return map;
  }

  MissionRegistry registry_;
  std::shared_ptr<Mission> mission_;
};

// Holds the first GBA of one map after its snapshot until released, so that a test can make changes arrive
// while it runs, deterministically.
class GbaGate {
 public:
  explicit GbaGate(MapId map) : map_(map) {}
  std::function<void(MapId)> hook() {
    return [this](MapId map) {
      if (map != map_ || held_.exchange(true)) return;
      std::unique_lock lock(mutex_);
      waiting_ = true;
      wake_.notify_all();
      wake_.wait(lock, [this] { return released_; });
    };
  }
  void waitUntilHeld() {
    std::unique_lock lock(mutex_);
    EXPECT_TRUE(wake_.wait_for(lock, std::chrono::seconds(60), [this] { return waiting_; })) << "no GBA started";
  }
  void release() {
    const std::lock_guard lock(mutex_);
    released_ = true;
    wake_.notify_all();
  }

 private:
  MapId map_;
  std::atomic<bool> held_{false};
  std::mutex mutex_;
  std::condition_variable wake_;
  bool waiting_ = false;
  bool released_ = false;
};

}  // namespace cvislam::server::backend::test_maps

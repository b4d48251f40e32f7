// The server's recognition worker on a mission's map stack: keyframes announced as ingest announces them are
// put in the database, queried after the delay, and a place two agents' maps share is matched with the right
// transform; removals leave the database; a missing vocabulary names the file.
#include "server_cloud/recognition/recognition_worker.hpp"

#include <chrono>
#include <future>
#include <numbers>
#include <vector>

#include <gtest/gtest.h>

#include "common/dataset/euroc_calibration.hpp"
#include "common/geometry/alignment.hpp"
#include "test/server_cloud/recognition/synthetic_keyframes.hpp"
#include "test/sim/presets.hpp"

namespace cvislam::server::recognition {
namespace {

RecognitionWorkerOptions workerOptions() {
  RecognitionWorkerOptions o;
  o.vocabulary = CVISLAM_VOCABULARY_FILE;
  o.delay_keyframes = 2;
  return o;
}

// Two agents' maps in mission "m" of `registry`, six keyframes each of the same stretch (agent 1 0.2 s later, in
// its own frame E_b_w), and the events ingest would have queued for them.
void buildTwoAgentMission(MissionRegistry& registry, const geometry::SE3d& E_b_w, std::vector<KeyframeEvent>& events) {
  auto plan = sim::planPreset("loop", 1, 60.0);
  ASSERT_TRUE(plan.ok());
  sim::WorldOptions world_options;
  world_options.seed = 1;
  const sim::World world(plan->layout, world_options);
  auto maker = test::ViewMaker::create(dataset::eurocCam0());
  ASSERT_TRUE(maker.ok());
  const auto mission = registry.getOrCreate("m");
  for (AgentId agent = 0; agent < 2; ++agent) {
    AgentSensors sensors{SensorMode::kMono, true, maker->camera(), std::nullopt, maker->T_s_c(), {}, 200.0};
    mission->agent(agent)->write()->sensors = sensors;
    const auto map = mission->stack().createMap();
    auto content = map->write();
    test::SyntheticMap builder(*content, world, agent, {});
    for (int k = 0; k < 6; ++k) {
      const double t_s = 14.0 + 0.4 * k + 0.2 * agent;
      auto id = builder.add(maker->render(world, plan->agents[0].trajectory.state(t_s).T_w_b),
                            agent == 0 ? geometry::SE3d() : E_b_w);
      ASSERT_TRUE(id.ok()) << id.error().message();
      events.push_back(KeyframeEvent{KeyframeEvent::Kind::kAdded, "m", map->id(), *id});
    }
  }
}

const geometry::SE3d kE_b_w(geometry::rotationAboutZ(-1.0), Eigen::Vector3d(-4.0, 1.0, 0.2));

TEST(RecognitionWorker, MatchesTwoAgentsMapsThroughTheMissionStack) {
  MissionRegistry registry;
  std::vector<KeyframeEvent> events;
  ASSERT_NO_FATAL_FAILURE(buildTwoAgentMission(registry, kE_b_w, events));

  auto worker = RecognitionWorker::create(workerOptions(), registry);
  ASSERT_TRUE(worker.ok()) << worker.error().message();
  for (const KeyframeEvent& e : events) EXPECT_TRUE((*worker)->enqueue(e));
  (*worker)->drain();
  RecognitionCounters c = (*worker)->counters("m");
  EXPECT_EQ(c.keyframes, 12U);
  EXPECT_EQ(c.queries, 24U);  // every keyframe, loop and map match (the delay is flushed by drain)
  EXPECT_EQ(c.loops, 0U);     // 2.4 s of flight: nothing to close
  ASSERT_GE(c.map_matches, 3U);
  for (const MatchRecord& m : (*worker)->matches("m")) {
    ASSERT_EQ(m.kind, QueryKind::kMapMatch);
    // Map 0 is the world frame and map 1 is E_b_w: the true transform from the candidate's map into the query's.
    const geometry::SE3d truth = m.match.query_map == 0 ? kE_b_w.inverse() : kE_b_w;
    const geometry::SE3d error = truth.inverse() * m.match.T_qmap_cmap;
    EXPECT_LT(error.translation().norm(), 0.15);
    EXPECT_LT(error.so3().log().norm() * 180.0 / std::numbers::pi, 1.0);
  }

  // A removal takes the keyframe out of the database.
  EXPECT_TRUE((*worker)->enqueue(KeyframeEvent{KeyframeEvent::Kind::kRemoved, "m", 0, KeyframeId{0, 0}}));
  (*worker)->drain();
  c = (*worker)->counters("m");
  EXPECT_EQ(c.keyframes, 11U);
}

// While a candidate is verified (matching, RANSAC and the guided search) no map lock is held: a writer, as ingest
// is, takes every map's write lock at once, and the matches are those of a quiet run.
TEST(RecognitionWorker, IngestWritesEveryMapWhileACandidateIsVerified) {
  MissionRegistry registry;
  std::vector<KeyframeEvent> events;
  ASSERT_NO_FATAL_FAILURE(buildTwoAgentMission(registry, kE_b_w, events));
  const auto mission = registry.find("m");

  // The writers wait here, not in the hook: were a lock still held, the hook's wait times out and the writer
  // finishes once the worker lets go.
  std::vector<std::future<void>> writers;
  int verifications = 0;
  int written_during = 0;
  RecognitionWorkerOptions options = workerOptions();
  options.on_verification_start = [&](const std::string& name, const Candidate&) {
    EXPECT_EQ(name, "m");
    ++verifications;
    writers.push_back(std::async(std::launch::async, [&] {
      for (const auto& map : mission->stack().maps()) {
        auto content = map->write();
        for (const auto& [id, kf] : content->keyframes()) content->keyframe(id)->provisional = false;
      }
    }));
    if (writers.back().wait_for(std::chrono::seconds(5)) == std::future_status::ready) ++written_during;
  };
  auto worker = RecognitionWorker::create(options, registry);
  ASSERT_TRUE(worker.ok()) << worker.error().message();
  for (const KeyframeEvent& e : events) EXPECT_TRUE((*worker)->enqueue(e));
  (*worker)->drain();
  for (auto& w : writers) w.wait();
  const RecognitionCounters c = (*worker)->counters("m");
  ASSERT_GE(c.map_matches, 3U);
  EXPECT_EQ(static_cast<std::uint64_t>(verifications), c.candidates);
  EXPECT_EQ(written_during, verifications);
  ASSERT_EQ(c.lock_held_ms.size(), 12U);  // one per query keyframe
  for (const MatchRecord& m : (*worker)->matches("m")) {
    const geometry::SE3d truth = m.match.query_map == 0 ? kE_b_w.inverse() : kE_b_w;
    const geometry::SE3d error = truth.inverse() * m.match.T_qmap_cmap;
    EXPECT_LT(error.translation().norm(), 0.15);
  }
}

TEST(RecognitionWorker, AMissingVocabularyNamesTheFileAndTheSetting) {
  MissionRegistry registry;
  RecognitionWorkerOptions o = workerOptions();
  o.vocabulary = "/nonexistent/vocabulary.cvvoc";
  auto worker = RecognitionWorker::create(o, registry);
  ASSERT_FALSE(worker.ok());
  EXPECT_NE(worker.error().message().find("/nonexistent/vocabulary.cvvoc"), std::string::npos);
  EXPECT_NE(worker.error().message().find("recognition.vocabulary"), std::string::npos);
  o = workerOptions();
  o.recognition.min_matches = 2;
  worker = RecognitionWorker::create(o, registry);
  ASSERT_FALSE(worker.ok());
  EXPECT_NE(worker.error().message().find("min_matches"), std::string::npos);
}

}  // namespace
}  // namespace cvislam::server::recognition

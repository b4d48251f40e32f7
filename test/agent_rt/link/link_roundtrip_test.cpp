// The agent's real tracking and mapping on a simulated stereo sequence (rendered at test time, fixed seed), their
// map deltas fed to link stores, and every batch delivered to the server's real core. The same deltas go to a
// clean link and to a faulty one (batches lost with the stream, reconnections, late acknowledgements);
// the two servers must end up holding the same map, and it must be the agent's.
#include <map>
#include <optional>
#include <set>

#include <gtest/gtest.h>

#include "agent_rt/link/link_store.hpp"
#include "server_cloud/store/sqlite_store.hpp"
#include "test/agent_rt/link/link_test_support.hpp"
#include "test/server_cloud/store/faulty_stores.hpp"
#include "test/sim/mission_writer.hpp"
#include "test/sim/presets.hpp"
#include "test/support/inline_agent.hpp"
#include "test/support/rendered_mission.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::agent {
namespace {

// One link: a store, a server, and how batches travel between them.
struct LinkUnderTest {
  explicit LinkUnderTest(const std::string& mission)
      : store(test::kAgent, LinkStoreOptions{}), server(mission, /*stereo=*/true) {}

  void connect() {
    std::uint64_t resend_from = 0;
    const std::uint64_t stored = server.connect(store.acked(), &resend_from);
    store.onWelcome(stored, resend_from);
    next = stored + 1;
  }
  // Builds a batch; delivers it unless `lose`. Returns whether one was built.
  bool send(bool lose = false) {
    if (!store.buildBatch(next, 0, 512U << 10U, batch)) return false;
    ++next;
    ++built;
    if (!lose) {
      const Status s = server.deliver(batch);
      EXPECT_TRUE(s.ok()) << s.error().toString();
      refused += s.ok() ? 0 : 1;
    }
    return true;
  }
  // The same where the server may end the stream: its answer, or nullopt when nothing was due.
  std::optional<Status> trySend() {
    if (!store.buildBatch(next, 0, 512U << 10U, batch)) return std::nullopt;
    ++next;
    ++built;
    return server.deliver(batch);
  }
  void ack() { store.onAck(server.stored()); }
  void flush() {
    while (send()) {
    }
    ack();
  }

  LinkStore store;
  test::ServerSide server;
  v1::MapBatch batch;
  std::uint64_t next = 1;
  int built = 0;
  int refused = 0;
};

class LinkRoundTrip : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    dir_ = new cvislam::test::TempDir();
    auto rendered = cvislam::test::renderedMission({"loop", 11, 9.0, /*stereo=*/true}, dir_->path());
    ASSERT_TRUE(rendered.ok()) << rendered.error().toString();
    mission_ = *rendered;
  }
  static void TearDownTestSuite() { delete dir_; }

  // Runs the agent over the sequence; `each_frame` is called after every frame with the newest delta count.
  template <typename F>
  void runAgent(F&& each_frame, const std::function<void(const MapDeltaMessage&)>& on_delta) {
    auto seq = dataset::EurocSequence::open(mission_ / "agent0");
    ASSERT_TRUE(seq.ok()) << seq.error().toString();
    TrackerOptions tracker_options;
    tracker_options.agent = test::kAgent;
    MapperOptions mapper_options;
    mapper_options.agent = test::kAgent;
    auto agent = cvislam::test::InlineAgent::create(*seq, true, tracker_options, mapper_options);
    ASSERT_TRUE(agent.ok()) << agent.error().toString();
    (*agent)->onDelta(on_delta);
    for (std::size_t i = 0; i < (*agent)->frameCount(); ++i) {
      ASSERT_TRUE((*agent)->load(i).ok());
      (*agent)->track([] {}, [] {});
      each_frame(i);
    }
  }

  static cvislam::test::TempDir* dir_;
  static std::filesystem::path mission_;  // read-only: shared with the other tests of the CTest run
};
cvislam::test::TempDir* LinkRoundTrip::dir_ = nullptr;
std::filesystem::path LinkRoundTrip::mission_;

TEST_F(LinkRoundTrip, LostBatchesReconnectionsAndLateAcksChangeNothingTheServerEndsUpWith) {
  LinkUnderTest clean("clean");
  LinkUnderTest faulty("faulty");
  clean.connect();
  faulty.connect();
  std::map<std::uint32_t, KeyframeStateMsg> final_states;  // the agent's newest state of each keyframe
  int deltas = 0;
  int opportunity = 0;
  int lost = 0;
  int reconnections = 0;
  runAgent(
      [&](std::size_t frame) {
        if (frame % 4 != 0) return;  // a batch every 4 frames (5 per second)
        clean.send();
        clean.ack();
        // The faulty link: every third batch breaks the stream while it travels, every fifth opportunity is a
        // reconnection between batches, and acknowledgements come only every other time.
        ++opportunity;
        if (opportunity % 3 == 1) {
          if (faulty.send(/*lose=*/true)) {
            ++lost;
            faulty.connect();
            ++reconnections;
          }
        } else if (opportunity % 5 == 0) {
          faulty.connect();
          ++reconnections;
        } else {
          faulty.send();
          if (opportunity % 2 == 0) faulty.ack();
        }
      },
      [&](const MapDeltaMessage& d) {
        ++deltas;
        clean.store.onDelta(d);
        faulty.store.onDelta(d);
        if (d.ready == 0) return;
        for (std::uint16_t i = 0; i < d.keyframe_count; ++i) final_states[d.keyframes[i].id.counter] = d.keyframes[i];
      });
  clean.flush();
  faulty.connect();
  faulty.flush();
  std::printf("%d deltas; clean link %d batches; faulty link %d batches, %d lost, %d reconnections\n", deltas,
              clean.built, faulty.built, lost, reconnections);

  ASSERT_GT(deltas, 15);
  EXPECT_GT(lost, 0);
  EXPECT_EQ(clean.refused + faulty.refused, 0);
  EXPECT_TRUE(clean.store.allAcknowledged());
  EXPECT_TRUE(faulty.store.allAcknowledged());
  ASSERT_TRUE(clean.server.consistent().ok()) << clean.server.consistent().error().toString();
  ASSERT_TRUE(faulty.server.consistent().ok()) << faulty.server.consistent().error().toString();

  // The agent's map: every keyframe of its ready map, with its newest state.
  ASSERT_GT(clean.server.keyframes(), 15U);
  EXPECT_EQ(clean.server.keyframes(), final_states.size());
  for (const auto& [c, state] : final_states) {
    const server::ServerKeyframe* kf = clean.server.keyframe(c);
    ASSERT_NE(kf, nullptr) << "keyframe " << c << " never reached the server";
    EXPECT_LT((kf->T_w_s.translation() - fromMsg(state.T_w_s).translation()).norm(), 2e-4) << "keyframe " << c;
  }
  // The faulty link's server holds the same, exactly once.
  EXPECT_EQ(faulty.server.keyframes(), clean.server.keyframes());
  EXPECT_EQ(faulty.server.points(), clean.server.points());
  clean.server.forEachMap([&](const server::MapContent& m) {
    for (const auto& [id, kf] : m.keyframes()) {
      const server::ServerKeyframe* other = faulty.server.keyframe(id.counter);
      ASSERT_NE(other, nullptr) << id.toString();
      EXPECT_EQ(other->observationCount(), kf.observationCount()) << id.toString();
      EXPECT_LT((other->T_w_s.translation() - kf.T_w_s.translation()).norm(), 1e-9) << id.toString();
      EXPECT_EQ(other->preintegration.has_value(), kf.preintegration.has_value()) << id.toString();
    }
    for (const auto& [id, p] : m.points()) {
      const server::ServerMapPoint* other = faulty.server.point(id.counter);
      ASSERT_NE(other, nullptr) << id.toString();
      EXPECT_EQ(other->observations.size(), p.observations.size()) << id.toString();
    }
  });
}

TEST_F(LinkRoundTrip, AfterAServerRestartTheServerGetsTheAgentsCurrentMapAndNothingTwice) {
  LinkUnderTest link("restart");
  link.connect();
  std::size_t held_at_restart = 0;
  std::size_t restarted_at_frame = 0;
  runAgent(
      [&](std::size_t frame) {
        if (frame % 4 != 0) return;
        link.send();
        link.ack();
        if (frame == 120) {  // about 6 s in: the server restarts empty
          held_at_restart = link.store.backlog().keyframes_held;
          restarted_at_frame = frame;
          link.server.restart();
          link.connect();
        }
      },
      [&](const MapDeltaMessage& d) { link.store.onDelta(d); });
  link.flush();
  ASSERT_GT(restarted_at_frame, 0U);
  ASSERT_GT(held_at_restart, 5U);
  EXPECT_EQ(link.refused, 0);
  EXPECT_TRUE(link.server.consistent().ok());
  // At least the keyframes the agent still held at the restart came again, and nothing is there twice (a second
  // full copy of a keyframe would be refused by the server's map as a duplicate id).
  EXPECT_GE(link.server.keyframes(), held_at_restart);
  EXPECT_TRUE(link.store.allAcknowledged());
  std::printf("held at the restart: %zu keyframes; the restarted server ends with %zu keyframes, %zu points\n",
              held_at_restart, link.server.keyframes(), link.server.points());
}

// A batch whose append committed but whose answer was lost ends the stream; the agent reconnects and builds its
// next batch from its current map. Every keyframe the server acknowledged must still be held after a restart
// that replays the store, and the replay must go through.
TEST_F(LinkRoundTrip, ABatchCommittedUnseenAndTheBatchesAfterItAreHeldOnceAfterARestart) {
  cvislam::test::TempDir store_dir;
  const std::filesystem::path db = store_dir.path() / "maps.db";
  constexpr std::uint64_t kLostSequence = 6;
  bool first_open = true;
  server::test::InDoubtStore* in_doubt = nullptr;
  LinkUnderTest link("in-doubt");
  link.server.useStore([&]() -> Result<std::unique_ptr<server::MapStore>> {
    server::SqliteStoreOptions o;
    o.path = db;
    o.sync = server::SqliteStoreOptions::Sync::kNormal;
    auto sqlite = server::openSqliteStore(o);
    if (!sqlite || !first_open) return sqlite;
    first_open = false;  // only the first process's connection loses an answer
    auto wrapped = std::make_unique<server::test::InDoubtStore>(std::move(sqlite).value(), kLostSequence);
    in_doubt = wrapped.get();
    return std::unique_ptr<server::MapStore>(std::move(wrapped));
  });
  ASSERT_TRUE(link.server.recovery().ok());
  link.connect();
  bool stream_down = false;
  int keyframes_while_down = 0;
  int refused = 0;
  runAgent(
      [&](std::size_t frame) {
        if (frame % 4 != 0) return;
        // Down until mapping made a keyframe more, so that the rebuilt batch carries something new.
        if (stream_down) {
          if (keyframes_while_down == 0) return;
          link.connect();
          stream_down = false;
        }
        const std::optional<Status> s = link.trySend();
        if (!s) return;
        if (s->ok()) {
          link.ack();
          return;
        }
        ++refused;
        EXPECT_EQ(s->error().code(), ErrorCode::kUnavailable) << s->error().toString();
        stream_down = true;
        keyframes_while_down = 0;
      },
      [&](const MapDeltaMessage& d) {
        link.store.onDelta(d);
        if (stream_down && d.has_keyframe != 0) ++keyframes_while_down;
      });
  if (stream_down) link.connect();
  link.flush();
  ASSERT_NE(in_doubt, nullptr);
  ASSERT_TRUE(in_doubt->lostOne()) << "the run made fewer than " << kLostSequence << " batches";
  EXPECT_EQ(refused, 1);
  EXPECT_TRUE(link.store.allAcknowledged());
  ASSERT_TRUE(link.server.consistent().ok()) << link.server.consistent().error().toString();
  std::set<std::uint32_t> acknowledged;
  link.server.forEachMap([&](const server::MapContent& m) {
    for (const auto& [id, kf] : m.keyframes()) acknowledged.insert(id.counter);
  });
  const std::size_t points = link.server.points();
  ASSERT_GT(acknowledged.size(), 10U);

  link.server.restart();  // the same file, replayed by a new process
  ASSERT_TRUE(link.server.recovery().ok()) << link.server.recovery().error().toString();
  std::set<std::uint32_t> replayed;
  link.server.forEachMap([&](const server::MapContent& m) {
    for (const auto& [id, kf] : m.keyframes()) replayed.insert(id.counter);
  });
  EXPECT_EQ(replayed, acknowledged);
  EXPECT_EQ(link.server.points(), points);
  EXPECT_TRUE(link.server.consistent().ok());
  std::printf("%zu keyframes and %zu points acknowledged; after the restart %zu keyframes, %zu points\n",
              acknowledged.size(), points, replayed.size(), link.server.points());
}

}  // namespace
}  // namespace cvislam::agent

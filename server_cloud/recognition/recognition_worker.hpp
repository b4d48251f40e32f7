// The server's place-recognition worker (CVI-SLAM IV-A): one thread, fed by ingest through a bounded queue, that
// keeps a keyframe database per mission and runs loop detection and map matching for every new keyframe.
//
// Ingest only enqueues (keyframe added, keyframe removed) and never waits: when the queue is full the event is
// dropped and counted. A keyframe is queried `delay_keyframes` keyframes of its agent after it arrived, so that
// mapping has sent its points and its covisibility links (the query's neighbours are excluded from loops).
// A query reads the mission's maps under one map's read lock at a time, each only for what it reads there, so that
// ingest into a map never waits for a whole query: the query's map for the database's candidates and a copy of the
// query keyframe, each other map with candidates for their covisibility groups, and, per candidate, its map for a
// copy of what its verification reads (the candidate and its neighbourhood's points). The matching, RANSAC and
// the guided search run on the copies with no lock held.
//
// Verified matches are kept per mission, written at the end, and handed to the back-end (setMatchListener), which
// merges maps and closes loops; it tells the worker of merges (kMerged) and removals, so the database follows.
#pragma once

#include <algorithm>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "common/core/result.hpp"
#include "common/features/vocabulary.hpp"
#include "server_cloud/recognition/place_recognition.hpp"
#include "server_cloud/stack/map_stack.hpp"

namespace cvislam::server::recognition {

struct RecognitionWorkerOptions {
  bool enabled = true;
  std::filesystem::path vocabulary;  // the default is the file the project ships
  std::size_t queue_capacity = 100'000;
  int delay_keyframes = 5;
  RecognitionOptions recognition;
  // Test seam: called on the worker thread before each candidate's verification, once its copies are taken.
  std::function<void(const std::string& mission, const Candidate& candidate)> on_verification_start;

  [[nodiscard]] Status validate() const;
};

// What ingest tells the worker.
// What ingest and the back-end tell the worker.
struct KeyframeEvent {
  // kFlush (drain's): query every waiting keyframe now. kMerged: map `from_map` went into `map`.
  enum class Kind { kAdded, kRemoved, kFlush, kMerged };
  Kind kind = Kind::kAdded;
  std::string mission;
  MapId map = 0;
  KeyframeId keyframe;
  MapId from_map = 0;
};

struct MatchRecord {
  QueryKind kind = QueryKind::kLoop;
  VerifiedMatch match;
};

struct RecognitionCounters {
  std::uint64_t keyframes = 0;  // in the database
  std::uint64_t queries = 0;    // loop and map-match queries run
  std::uint64_t candidates = 0;
  std::uint64_t loops = 0;                          // accepted
  std::uint64_t map_matches = 0;                    // accepted
  std::map<std::string, std::uint64_t> rejections;  // by reason
  std::uint64_t dropped_events = 0;                 // the queue was full
  std::uint64_t skipped = 0;                        // keyframes gone before their turn
  double busy_s = 0.0;                              // time spent on queries
  LatencySamples query_ms;                          // per query keyframe (its loop and map-match queries)
  // Per query keyframe, the longest time any map's read lock was held for it: what ingest into that map may
  // have waited.
  LatencySamples lock_held_ms;
  // Per query keyframe, the worker thread's CPU time in all (its work) and while holding a map's lock (the work
  // under locks): the held times above also count the time the scheduler kept the thread off a core.
  LatencySamples query_cpu_ms;
  LatencySamples locked_cpu_ms;
};

class RecognitionWorker {
 public:
  // Loads the vocabulary (the error names the file) and starts the thread.
  static Result<std::unique_ptr<RecognitionWorker>> create(const RecognitionWorkerOptions& options,
                                                           MissionRegistry& missions);
  ~RecognitionWorker();  // stops the thread; events still queued are dropped
  // Stops the thread now (the object stays: events enqueued later are kept and never handled). Idempotent.
  void stop();
  RecognitionWorker(const RecognitionWorker&) = delete;
  RecognitionWorker& operator=(const RecognitionWorker&) = delete;

  // Never blocks on recognition: false when the queue was full (the event is dropped and counted).
  bool enqueue(KeyframeEvent event);
  // Hears of every accepted match, from the worker thread, with no lock held (the back-end queues it).
  using MatchListener = std::function<void(const std::string& mission, const MatchRecord& match)>;
  void setMatchListener(MatchListener listener);
  // Waits until every queued event has been handled (for tests and the shutdown output).
  void drain();

  [[nodiscard]] RecognitionCounters counters(const std::string& mission) const;
  // Keyframe events waiting for the worker (its queue's depth now).
  [[nodiscard]] std::size_t queueDepth() const;
  [[nodiscard]] std::vector<MatchRecord> matches(const std::string& mission) const;
  [[nodiscard]] std::vector<std::string> missions() const;
  [[nodiscard]] const features::Vocabulary& vocabulary() const { return vocabulary_; }

 private:
  struct MissionState;
  RecognitionWorker(const RecognitionWorkerOptions& options, MissionRegistry& missions,
                    features::Vocabulary vocabulary);
  void run();
  void handle(const KeyframeEvent& event);
  void query(MissionState& state, Mission& mission, const KeyframeId& keyframe);
  // The locks one query took: the longest held, and the CPU time spent holding them.
  struct QueryLocks {
    double held_ms = 0.0;
    double cpu_ms = 0.0;
    // Calls `read` with `map`'s content under its read lock, timed.
    template <typename Read>
    void read(const ServerMap& map, const Read& read);
  };
  // Copies the candidate's part of `input` under its map's read lock (counted in `locks`), then verifies with no
  // lock held.
  Verification verifyOnCopies(MissionState& state, Mission& mission, VerificationInput& input,
                              const Candidate& candidate, QueryLocks& locks);
  const AgentCamera* camera(MissionState& state, Mission& mission, AgentId agent);

  RecognitionWorkerOptions options_;
  MissionRegistry& missions_;
  features::Vocabulary vocabulary_;

  mutable std::mutex mutex_;  // guards the queue, `busy_`, `stop_` and the missions' results
  std::condition_variable wake_;
  std::condition_variable idle_;
  std::deque<KeyframeEvent> queue_;
  bool busy_ = false;
  bool stop_ = false;
  std::map<std::string, std::unique_ptr<MissionState>> states_;
  MatchListener on_match_;
  std::thread thread_;
};

}  // namespace cvislam::server::recognition

#include "server_cloud/recognition/recognition_worker.hpp"

#include <algorithm>
#include <chrono>
#include <optional>
#include <set>
#include <string>
#include <unordered_map>
#include <utility>

#include "common/core/steady_clock.hpp"
#include "common/trace/trace.hpp"

namespace cvislam::server::recognition {

struct RecognitionWorker::MissionState {
  explicit MissionState(std::size_t words) : database(words) {}
  // The worker thread's own.
  KeyframeDatabase database;
  std::map<AgentId, std::deque<std::pair<MapId, KeyframeId>>> pending;  // waiting for delay_keyframes more
  std::map<AgentId, std::unique_ptr<AgentCamera>> cameras;
  // Read by other threads: under the worker's mutex.
  RecognitionCounters counters;
  std::vector<MatchRecord> matches;
};

Status RecognitionWorkerOptions::validate() const {
  if (queue_capacity == 0) return Error(ErrorCode::kInvalidArgument, "recognition.queue_capacity must be positive");
  if (delay_keyframes < 0) return Error(ErrorCode::kInvalidArgument, "recognition.delay_keyframes must be >= 0");
  return recognition.validate();
}

Result<std::unique_ptr<RecognitionWorker>> RecognitionWorker::create(const RecognitionWorkerOptions& options,
                                                                     MissionRegistry& missions) {
  if (Status s = options.validate(); !s) return s.error();
  Result<features::Vocabulary> vocabulary = features::Vocabulary::load(options.vocabulary);
  if (!vocabulary) {
    return vocabulary.error().withContext(
        "recognition.vocabulary (set it to the vocabulary file, or recognition.enabled: false to run without)");
  }
  return std::unique_ptr<RecognitionWorker>(new RecognitionWorker(options, missions, std::move(vocabulary).value()));
}

RecognitionWorker::RecognitionWorker(const RecognitionWorkerOptions& options, MissionRegistry& missions,
                                     features::Vocabulary vocabulary)
    : options_(options), missions_(missions), vocabulary_(std::move(vocabulary)) {
  thread_ = std::thread([this] { run(); });
}

RecognitionWorker::~RecognitionWorker() {
  stop();
}

void RecognitionWorker::stop() {
  {
    const std::lock_guard lock(mutex_);
    stop_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) thread_.join();
}

bool RecognitionWorker::enqueue(KeyframeEvent event) {
  {
    const std::lock_guard lock(mutex_);
    if (queue_.size() >= options_.queue_capacity) {
      auto& state = states_[event.mission];
      if (!state) state = std::make_unique<MissionState>(vocabulary_.wordCount());
      ++state->counters.dropped_events;
      return false;
    }
    queue_.push_back(std::move(event));
  }
  wake_.notify_one();
  return true;
}

void RecognitionWorker::setMatchListener(MatchListener listener) {
  const std::lock_guard lock(mutex_);
  on_match_ = std::move(listener);
}

void RecognitionWorker::drain() {
  {
    // Behind everything queued: the last keyframes of every agent get their turn too.
    const std::lock_guard lock(mutex_);
    queue_.push_back(KeyframeEvent{KeyframeEvent::Kind::kFlush, {}, 0, {}});
  }
  wake_.notify_one();
  std::unique_lock lock(mutex_);
  idle_.wait(lock, [this] { return (queue_.empty() && !busy_) || stop_; });
}

RecognitionCounters RecognitionWorker::counters(const std::string& mission) const {
  const std::lock_guard lock(mutex_);
  const auto it = states_.find(mission);
  return it == states_.end() ? RecognitionCounters{} : it->second->counters;
}

std::size_t RecognitionWorker::queueDepth() const {
  const std::lock_guard lock(mutex_);
  return queue_.size();
}

std::vector<MatchRecord> RecognitionWorker::matches(const std::string& mission) const {
  const std::lock_guard lock(mutex_);
  const auto it = states_.find(mission);
  return it == states_.end() ? std::vector<MatchRecord>{} : it->second->matches;
}

std::vector<std::string> RecognitionWorker::missions() const {
  const std::lock_guard lock(mutex_);
  std::vector<std::string> names;
  for (const auto& [name, state] : states_) names.push_back(name);
  return names;
}

void RecognitionWorker::run() {
  trace::bindThread("recognition");
  std::unique_lock lock(mutex_);
  while (true) {
    wake_.wait(lock, [this] { return stop_ || !queue_.empty(); });
    if (stop_) break;
    KeyframeEvent event = std::move(queue_.front());
    queue_.pop_front();
    busy_ = true;
    lock.unlock();
    handle(event);
    lock.lock();
    busy_ = false;
    if (queue_.empty()) idle_.notify_all();
  }
  idle_.notify_all();
}

const AgentCamera* RecognitionWorker::camera(MissionState& state, Mission& mission, AgentId agent) {
  auto& slot = state.cameras[agent];
  if (!slot) {
    const SharedAgentRecord record = mission.findAgent(agent);
    if (!record) return nullptr;
    const auto r = record->read();
    if (!r->sensors) return nullptr;
    slot = std::make_unique<AgentCamera>(AgentCamera{r->sensors->cam0, r->sensors->T_s_c0});
  }
  return slot.get();
}

void RecognitionWorker::handle(const KeyframeEvent& event) {
  if (event.kind == KeyframeEvent::Kind::kFlush) {
    std::vector<std::pair<std::string, MissionState*>> states;
    {
      const std::lock_guard lock(mutex_);
      for (const auto& [name, state] : states_) states.emplace_back(name, state.get());
    }
    for (const auto& [name, state] : states) {
      const std::shared_ptr<Mission> mission = missions_.find(name);
      if (!mission) continue;
      for (auto& [agent, pending] : state->pending) {
        while (!pending.empty()) {
          const KeyframeId id = pending.front().second;
          pending.pop_front();
          query(*state, *mission, id);
        }
      }
    }
    return;
  }
  const std::shared_ptr<Mission> mission = missions_.find(event.mission);
  MissionState* state = nullptr;
  {
    const std::lock_guard lock(mutex_);
    auto& slot = states_[event.mission];
    if (!slot) slot = std::make_unique<MissionState>(vocabulary_.wordCount());
    state = slot.get();
  }
  if (!mission) return;
  if (event.kind == KeyframeEvent::Kind::kMerged) {
    state->database.moveMap(event.from_map, event.map);
    for (auto& [agent, pending] : state->pending) {
      for (auto& [map, id] : pending) {
        if (map == event.from_map) map = event.map;
      }
    }
    return;
  }
  if (event.kind == KeyframeEvent::Kind::kRemoved) {
    (void)state->database.remove(event.keyframe);  // kNotFound: it never got in
    auto& pending = state->pending[event.keyframe.agent];
    std::erase_if(pending, [&](const auto& p) { return p.second == event.keyframe; });
    const std::lock_guard lock(mutex_);
    state->counters.keyframes = state->database.size();
    return;
  }
  // Added: into the database now, queried delay_keyframes keyframes of its agent later. The map comes from the
  // agent's record: a merge since ingest may have moved the keyframe into another map.
  MapId map_id = event.map;
  if (const SharedAgentRecord record = mission->findAgent(event.keyframe.agent)) {
    const auto r = record->read();
    if (const auto held = r->keyframes.find(event.keyframe.counter); held != r->keyframes.end()) {
      map_id = held->second.map;
    }
  }
  const std::shared_ptr<ServerMap> map = mission->stack().find(map_id);
  if (!map) return;
  std::vector<features::Descriptor> descriptors;
  {
    const auto content = map->read();
    const ServerKeyframe* kf = content->keyframe(event.keyframe);
    if (kf == nullptr) return;
    descriptors = kf->descriptors;
  }
  features::BowVector bow;
  features::FeatureVector fv;
  vocabulary_.transform(descriptors, bow, &fv, options_.recognition.direct_level);
  if (!state->database.add(event.keyframe, map_id, std::move(bow), std::move(fv)).ok()) return;
  {
    const std::lock_guard lock(mutex_);
    state->counters.keyframes = state->database.size();
  }
  auto& pending = state->pending[event.keyframe.agent];
  pending.emplace_back(map_id, event.keyframe);
  while (pending.size() > static_cast<std::size_t>(options_.delay_keyframes)) {
    const KeyframeId id = pending.front().second;
    pending.pop_front();
    query(*state, *mission, id);
  }
}

namespace {

double msSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start).count();
}

Verification missing(std::string detail) {
  Verification v;
  v.rejection = Rejection::kMissing;
  v.detail = std::move(detail);
  return v;
}

}  // namespace

template <typename Read>
void RecognitionWorker::QueryLocks::read(const ServerMap& map, const Read& read) {
  const auto content = map.read();
  const auto locked_at = std::chrono::steady_clock::now();
  const double cpu_at = threadCpuMs();
  read(*content);
  held_ms = std::max(held_ms, msSince(locked_at));
  cpu_ms += threadCpuMs() - cpu_at;
}

void RecognitionWorker::query(MissionState& state, Mission& mission, const KeyframeId& keyframe) {
  const trace::Span span(
      "recognition_query",
      {{"mission", trace::missionKey(mission.name())}, {"agent", keyframe.agent}, {"keyframe", keyframe.counter}});
  const auto start = std::chrono::steady_clock::now();
  const DatabaseEntry* entry = state.database.find(keyframe);
  if (entry == nullptr) return;
  const MapId query_map = entry->map;
  // The cameras first: an agent record is locked before any map, never while holding one.
  for (const SharedAgentRecord& record : mission.agents()) {
    AgentId agent = 0;
    { agent = record->read()->id; }
    (void)camera(state, mission, agent);
  }
  const double cpu_start_ms = threadCpuMs();
  QueryLocks locks;
  // One map's read lock at a time (locks.read), each for what is read of that map: ingest into a map never waits
  // behind the locks of others, nor behind the searches.
  // The query's map: the database's candidates (the exclusions and the loop's time rule read it), the groups of
  // those in it, and the query keyframe's copy.
  std::vector<std::pair<QueryKind, ScoredCandidates>> scored;
  std::unordered_map<KeyframeId, std::vector<KeyframeId>> around;  // each candidate's group neighbours
  VerificationInput input;  // the query's part now, each candidate's before its turn
  RecognitionCounters delta;
  bool held = false;
  if (const std::shared_ptr<ServerMap> map = mission.stack().find(query_map)) {
    locks.read(*map, [&](const MapContent& content) {
      if (content.keyframe(keyframe) == nullptr) return;
      held = true;
      (void)copyQuery(content, keyframe, input);
      for (const QueryKind kind : {QueryKind::kLoop, QueryKind::kMapMatch}) {
        Result<ScoredCandidates> s = scoreCandidates(state.database, content, keyframe, kind, options_.recognition);
        ++delta.queries;
        if (s) scored.emplace_back(kind, std::move(s).value());
      }
      for (const auto& [kind, s] : scored) {
        for (const BowCandidate& c : s.bow) {
          if (c.map == query_map) around[c.keyframe] = groupNeighbours(content, c.keyframe, options_.recognition);
        }
      }
    });
  }
  if (!held) {
    const std::lock_guard lock(mutex_);
    ++state.counters.skipped;
    return;
  }
  // The other maps' candidates' groups, map by map.
  std::set<MapId> others;
  for (const auto& [kind, s] : scored) {
    for (const BowCandidate& c : s.bow) {
      if (c.map != query_map) others.insert(c.map);
    }
  }
  for (const MapId id : others) {
    const std::shared_ptr<ServerMap> map = mission.stack().find(id);
    if (!map) continue;  // merged meanwhile: its candidates stand alone
    locks.read(*map, [&](const MapContent& content) {
      for (const auto& [kind, s] : scored) {
        for (const BowCandidate& c : s.bow) {
          if (c.map == id && content.keyframe(c.keyframe) != nullptr) {
            around[c.keyframe] = groupNeighbours(content, c.keyframe, options_.recognition);
          }
        }
      }
    });
  }
  std::vector<std::pair<QueryKind, CandidateSearch>> searches;
  for (auto& [kind, s] : scored) {
    searches.emplace_back(kind, groupCandidates(std::move(s), neighbourLookup(around), options_.recognition));
  }
  // Each candidate verified on a copy (verifyOnCopies): RANSAC and the guided search hold no lock.
  std::vector<MatchRecord> accepted;
  for (const auto& [kind, search] : searches) {
    delta.candidates += search.candidates.size();
    std::optional<VerifiedMatch> best;
    for (const Candidate& c : search.candidates) {
      trace::Span verify_span("verify_candidate", {{"mission", trace::missionKey(mission.name())},
                                                   {"agent", c.keyframe.agent},
                                                   {"keyframe", c.keyframe.counter}});
      const Verification v = verifyOnCopies(state, mission, input, c, locks);
      verify_span.set("accepted", v.accepted() ? 1 : 0);
      if (!v.accepted()) {
        ++delta.rejections[std::string(toString(v.rejection))];
      } else if (!best || v.match->inliers > best->inliers) {
        best = v.match;
      }
    }
    if (best) {
      ++(kind == QueryKind::kLoop ? delta.loops : delta.map_matches);
      accepted.push_back(MatchRecord{kind, *best});
    }
  }
  const double query_ms = msSince(start);
  MatchListener listener;
  {
    const std::lock_guard lock(mutex_);
    RecognitionCounters& c = state.counters;
    c.queries += delta.queries;
    c.candidates += delta.candidates;
    c.loops += delta.loops;
    c.map_matches += delta.map_matches;
    for (const auto& [reason, n] : delta.rejections) c.rejections[reason] += n;
    c.busy_s += query_ms * 1e-3;
    c.query_ms.add(query_ms);
    c.lock_held_ms.add(locks.held_ms);
    c.query_cpu_ms.add(threadCpuMs() - cpu_start_ms);
    c.locked_cpu_ms.add(locks.cpu_ms);
    for (const MatchRecord& m : accepted) state.matches.push_back(m);
    listener = on_match_;
  }
  if (listener) {
    for (const MatchRecord& m : accepted) listener(mission.name(), m);
  }
}

Verification RecognitionWorker::verifyOnCopies(MissionState& state, Mission& mission, VerificationInput& input,
                                               const Candidate& candidate, QueryLocks& locks) {
  const std::shared_ptr<ServerMap> map = mission.stack().find(candidate.map);
  if (!map) return missing("map " + std::to_string(candidate.map) + " went (merged) before the verification");
  Status copied;
  locks.read(*map, [&](const MapContent& content) {
    copied = copyCandidate(content, candidate.keyframe, options_.recognition, input);
  });
  // A merge or removal since the candidates were found: the merge made the match moot.
  if (!copied) return missing(copied.error().message());
  if (options_.on_verification_start) options_.on_verification_start(mission.name(), candidate);
  const CameraLookup cameras = [&](AgentId agent) -> const AgentCamera* {
    const auto found = state.cameras.find(agent);
    return found == state.cameras.end() ? nullptr : found->second.get();
  };
  return verifyCopied(state.database, input, candidate.score, cameras, options_.recognition);
}

}  // namespace cvislam::server::recognition

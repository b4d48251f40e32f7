#include "server_cloud/backend/backend_worker.hpp"

#include <algorithm>
#include <chrono>
#include <sstream>
#include <unordered_map>

#include "common/trace/trace.hpp"
#include "server_cloud/backend/backend_worker_state.hpp"
#include "server_cloud/backend/map_corrections.hpp"
#include "server_cloud/backend/merge_correction.hpp"

namespace cvislam::server::backend {

namespace {

using geometry::SE3d;

// A match's projection search, copied under the locks, run without any; its links and merges applied under the
// map's write lock, checked against the map as it is then. Returns the milliseconds the lock was held.
double fuseWithoutLock(ServerMap& map, const ProjectionSearchInput& search, const FusionOptions& options,
                       FusionReport& report) {
  const std::vector<ProjectionMatch> matches = searchByProjection(search, options);
  if (matches.empty()) return 0.0;
  const auto start = Clock::now();
  auto content = map.write();
  applyProjectionMatches(*content, matches, report);
  return std::chrono::duration<double, std::milli>(Clock::now() - start).count();
}

}  // namespace

// Every agent's cam0, in the form point fusion looks cameras up in.
class BackendWorker::CameraTable {
 public:
  explicit CameraTable(const AgentSensorsMap& sensors) {
    for (const auto& [agent, s] : sensors) cameras_.emplace(agent, recognition::AgentCamera{s.cam0, s.T_s_c0});
  }
  [[nodiscard]] recognition::CameraLookup lookup() const {
    return [this](AgentId agent) -> const recognition::AgentCamera* {
      const auto it = cameras_.find(agent);
      return it == cameras_.end() ? nullptr : &it->second;
    };
  }

 private:
  std::map<AgentId, recognition::AgentCamera> cameras_;
};

Status BackendOptions::validate() const {
  if (loop_cooldown_keyframes < 0) return Error{ErrorCode::kInvalidArgument, "backend.loop_cooldown_keyframes < 0"};
  if (frame_follows_keyframes < 1) {
    return Error{ErrorCode::kInvalidArgument, "backend.frame_follows_keyframes must be >= 1 (1: the newest alone)"};
  }
  if (!(loop_cancels_gba_m >= 0.0) || !(loop_cancels_gba_deg >= 0.0)) {
    return Error{ErrorCode::kInvalidArgument, "backend.loop_cancels_gba_m and loop_cancels_gba_deg must be >= 0"};
  }
  if (gba_every_keyframes < 0) {
    return Error{ErrorCode::kInvalidArgument,
                 "backend.gba_every_keyframes must be >= 0 (0: only after merges and loops)"};
  }
  if (merge_correction_keyframes < 0) {
    return Error{ErrorCode::kInvalidArgument, "backend.merge_correction_keyframes must be >= 0 (0: none)"};
  }
  if (!(loop_window_move_m >= 0.0) || !(loop_window_move_deg >= 0.0)) {
    return Error{ErrorCode::kInvalidArgument, "backend.loop_window_move_m and loop_window_move_deg must be >= 0"};
  }
  if (!(gba_time_budget_s >= 0.0)) {
    return Error{ErrorCode::kInvalidArgument, "backend.gba_time_budget_s must be >= 0 (0: no budget)"};
  }
  if (gba_window_above_keyframes < 0) {
    return Error{ErrorCode::kInvalidArgument,
                 "backend.gba_window_above_keyframes must be >= 0 (0: every GBA frees the whole map)"};
  }
  if (Status s = merge_correction_ba.validate(); !s.ok()) return s;
  if (redundancy_every_keyframes < 1) {
    return Error{ErrorCode::kInvalidArgument, "backend.redundancy_every_keyframes must be >= 1"};
  }
  if (queue_capacity == 0) return Error{ErrorCode::kInvalidArgument, "backend.queue_capacity must be positive"};
  if (Status s = gba.validate(); !s.ok()) return s;
  if (Status s = pose_graph.validate(); !s.ok()) return s;
  if (Status s = fusion.validate(); !s.ok()) return s;
  return redundancy.validate();
}

std::string BackendOptions::describe() const {
  std::ostringstream out;
  out << "merge maps " << (merge_maps ? "on" : "off") << ", loop closure " << (close_loops ? "on" : "off")
      << ", GBA after each " << (gba_after_change ? "on" : "off") << " (" << gba.structure_iterations << " + "
      << gba.full_iterations << " iterations, " << toString(gba.solver) << " solver, " << gba.threads << " threads, ";
  if (gba_time_budget_s > 0.0) {
    out << "at most " << gba_time_budget_s << " s each before the final one";
  } else {
    out << "each to convergence";
  }
  out << "; a loop cuts it short above " << loop_cancels_gba_m << " m or " << loop_cancels_gba_deg << " deg)";
  if (merge_correction_keyframes > 0) {
    out << ", a merge corrected at once (BA of the query and its " << merge_correction_keyframes
        << " most covisible keyframes, its query map moved rigidly by the fitted change)";
  }
  out << ", an agent's frame follows its " << frame_follows_keyframes << " newest corrected keyframes";
  if (gba_every_keyframes > 0) out << " and per " << gba_every_keyframes << " new keyframes of a map";
  if (gba_window_above_keyframes > 0) {
    out << ", a merge's or loop's GBA frees only what it changed in maps above " << gba_window_above_keyframes
        << " keyframes (a loop's: the agent maps its pose graph moved by more than " << loop_window_move_m << " m or "
        << loop_window_move_deg << " deg)";
  }
  out << ", new keyframes fused " << (fuse_new_keyframes ? "on" : "off") << " (" << fusion.neighbours << " covisible + "
      << fusion.nearby_keyframes << " within " << fusion.nearby_radius_m << " m and " << fusion.nearby_max_angle_deg
      << " deg), redundancy removal " << (redundancy.enabled ? "on" : "off") << " (" << redundancy.redundant_fraction
      << " of points seen by >= " << redundancy.min_other_observers
      << " others, IMU gap <= " << redundancy.max_imu_gap_s << " s; a final pass at the end "
      << (final_redundancy_pass ? "on" : "off") << ")";
  return out.str();
}

BackendWorker::BackendWorker(const BackendOptions& options, MissionRegistry& missions,
                             recognition::RecognitionWorker* recognition)
    : options_(options), missions_(missions), recognition_(recognition) {
  control_ = std::thread([this] { runControl(); });
  gba_thread_ = std::thread([this] { runGba(); });
}

BackendWorker::~BackendWorker() {
  {
    const std::lock_guard lock(mutex_);
    stop_ = true;
  }
  gba_cancel_ = true;
  control_wake_.notify_all();
  gba_wake_.notify_all();
  control_.join();
  gba_thread_.join();
}

BackendWorker::MissionState& BackendWorker::state(const std::string& mission) {
  auto& slot = states_[mission];
  if (!slot) {
    slot = std::make_unique<MissionState>();
    slot->rng.seed(options_.redundancy.seed);
  }
  return *slot;
}

bool BackendWorker::push(Event event) {
  {
    const std::lock_guard lock(mutex_);
    if (queue_.size() >= options_.queue_capacity) {
      ++state(event.mission).stats.dropped_events;
      return false;
    }
    event.arrived = Clock::now();
    queue_.push_back(std::move(event));
  }
  control_wake_.notify_one();
  return true;
}

bool BackendWorker::onMatch(const std::string& mission, const recognition::MatchRecord& match) {
  Event e;
  e.kind = Event::Kind::kMatch;
  e.mission = mission;
  e.match = match;
  return push(std::move(e));
}

bool BackendWorker::onKeyframesAdded(const std::string& mission,
                                     const std::vector<std::pair<MapId, KeyframeId>>& keyframes) {
  Event e;
  e.kind = Event::Kind::kKeyframes;
  e.mission = mission;
  e.keyframes = keyframes;
  return push(std::move(e));
}

void BackendWorker::drain(bool final_gba) {
  const auto wait_idle = [this] {
    push(Event{Event::Kind::kFlush, {}, std::nullopt, {}, {}});
    std::unique_lock lock(mutex_);
    idle_.wait(lock,
               [this] { return stop_ || (queue_.empty() && !control_busy_ && gba_queue_.empty() && !gba_running_); });
  };
  wait_idle();
  if (!final_gba) return;
  if (options_.redundancy.enabled && options_.final_redundancy_pass) {
    for (const auto& mission : missions_.missions()) {
      push(Event{Event::Kind::kFinalRedundancyPass, mission->name(), std::nullopt, {}, {}});
    }
    wait_idle();
  }
  std::vector<std::pair<std::string, MapId>> todo;
  for (const auto& mission : missions_.missions()) {
    // Every map with at least two keyframes: ingest changes every map, so each needs its last GBA.
    for (const auto& map : mission->stack().maps()) {
      if (map->read()->keyframes().size() >= 2) todo.emplace_back(mission->name(), map->id());
    }
  }
  for (const auto& [mission, map] : todo) requestGba(mission, map, true, std::nullopt, Clock::now());
  wait_idle();
}

BackendStats BackendWorker::stats(const std::string& mission) const {
  const std::lock_guard lock(mutex_);
  const auto it = states_.find(mission);
  return it == states_.end() ? BackendStats{} : it->second->stats;
}

BackendWorker::GbaWork BackendWorker::gbaWork(const std::string& mission) const {
  const std::lock_guard lock(mutex_);
  GbaWork out;
  out.running = gba_running_ && gba_running_->mission == mission;
  for (const GbaRequest& r : gba_queue_) {
    if (r.mission == mission) out.queued.push_back(r.map);
  }
  return out;
}

std::vector<std::string> BackendWorker::missions() const {
  const std::lock_guard lock(mutex_);
  std::vector<std::string> out;
  for (const auto& [name, s] : states_) out.push_back(name);
  return out;
}

void BackendWorker::runControl() {
  trace::bindThread("backend");
  std::unique_lock lock(mutex_);
  while (true) {
    control_wake_.wait(lock, [this] { return stop_ || !queue_.empty(); });
    if (stop_) break;
    Event event = std::move(queue_.front());
    queue_.pop_front();
    control_busy_ = true;
    lock.unlock();
    if (event.kind == Event::Kind::kMatch) {
      handleMatch(event);
    } else if (event.kind == Event::Kind::kKeyframes) {
      handleKeyframes(event);
    } else if (event.kind == Event::Kind::kFinalRedundancyPass) {
      finalRedundancyPass(event.mission);
    }
    lock.lock();
    control_busy_ = false;
    if (queue_.empty()) idle_.notify_all();
  }
  idle_.notify_all();
}

void BackendWorker::handleKeyframes(const Event& event) {
  const std::shared_ptr<Mission> mission = missions_.find(event.mission);
  if (!mission) return;
  MissionState* s = nullptr;
  {
    const std::lock_guard guard(mutex_);
    s = &state(event.mission);
  }
  if (options_.fuse_new_keyframes) {
    const CameraTable cameras(sensorsOf(*mission));
    for (const auto& [map, keyframe] : event.keyframes) fuseNewKeyframe(*mission, *s, cameras, keyframe);
  }
  // The maps whose count of new keyframes reaches `every` (their counts start again).
  const auto due = [&](std::map<MapId, int>& since, int every) {
    std::vector<MapId> out;
    const std::lock_guard guard(mutex_);
    for (const auto& [map, keyframe] : event.keyframes) {
      if (++since[map] >= every) {
        since[map] = 0;
        out.push_back(map);
      }
    }
    return out;
  };
  if (options_.gba_every_keyframes > 0) {
    // At most one request waits per map (requestGba joins them), so a GBA slower than the keyframes comes
    // back to back rather than piling up.
    for (MapId map : due(s->keyframes_since_gba, options_.gba_every_keyframes)) {
      requestGba(event.mission, map, false, std::nullopt, Clock::now());
    }
  }
  if (!options_.redundancy.enabled) return;
  for (MapId map : due(s->keyframes_since_redundancy, options_.redundancy_every_keyframes)) {
    removeRedundant(*mission, *s, map);
  }
}

void BackendWorker::finalRedundancyPass(const std::string& name) {
  const std::shared_ptr<Mission> mission = missions_.find(name);
  if (!mission) return;
  MissionState* s = nullptr;
  std::uint64_t before = 0;
  {
    const std::lock_guard guard(mutex_);
    s = &state(name);
    before = s->stats.redundant_removed;
  }
  for (const auto& map : mission->stack().maps()) {
    const int keyframes = static_cast<int>(map->read()->keyframes().size());
    if (keyframes > 0) removeRedundant(*mission, *s, map->id(), keyframes);
  }
  const std::lock_guard guard(mutex_);
  s->stats.final_pass_removed += s->stats.redundant_removed - before;
}

void BackendWorker::fuseNewKeyframe(Mission& mission, MissionState& state, const CameraTable& cameras,
                                    const KeyframeId& keyframe) {
  // The map that holds the keyframe now (a merge may have moved it since ingest).
  std::shared_ptr<ServerMap> map;
  if (SharedAgentRecord record = mission.findAgent(keyframe.agent)) {
    const auto r = record->read();
    const auto held = r->keyframes.find(keyframe.counter);
    if (held != r->keyframes.end()) map = mission.stack().find(held->second.map);
  }
  if (!map) return;
  const trace::Span span(
      "fusion",
      {{"mission", trace::missionKey(mission.name())}, {"agent", keyframe.agent}, {"keyframe", keyframe.counter}});
  const auto start = Clock::now();
  // Copy what the search needs under the read lock, search without a lock, apply under the write lock: ingest
  // waits for the copy and the apply only.
  // Timed from each lock's acquisition: what ingest may wait behind, not what this waited for.
  NewKeyframeSearch search;
  double locked_ms = 0.0;
  {
    const auto content = map->read();
    const auto locked_at = Clock::now();
    if (content->keyframe(keyframe) == nullptr) return;  // removed meanwhile
    search = gatherNewKeyframeSearch(*content, keyframe, cameras.lookup(), options_.fusion);
    locked_ms += std::chrono::duration<double, std::milli>(Clock::now() - locked_at).count();
  }
  const std::vector<ProjectionMatch> matches = searchNewKeyframe(search, options_.fusion);
  FusionReport report;
  if (!matches.empty()) {
    auto content = map->write();
    const auto locked_at = Clock::now();
    applyProjectionMatches(*content, matches, report);
    locked_ms += std::chrono::duration<double, std::milli>(Clock::now() - locked_at).count();
  }
  const double ms = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
  const std::lock_guard lock(mutex_);
  ++state.stats.new_keyframes_fused;
  state.stats.new_keyframe_links += static_cast<std::uint64_t>(report.projection_linked);
  state.stats.new_keyframe_point_merges += static_cast<std::uint64_t>(report.projection_fused);
  state.stats.new_keyframe_fuse_ms_max = std::max(state.stats.new_keyframe_fuse_ms_max, ms);
  state.stats.new_keyframe_fuse_ms_total += ms;
  state.stats.new_keyframe_fuse_locked_ms_max = std::max(state.stats.new_keyframe_fuse_locked_ms_max, locked_ms);
}

void BackendWorker::handleMatch(const Event& event) {
  const std::shared_ptr<Mission> mission = missions_.find(event.mission);
  if (!mission || !event.match) return;
  MissionState* s = nullptr;
  {
    const std::lock_guard lock(mutex_);
    s = &state(event.mission);
  }
  const recognition::VerifiedMatch& match = event.match->match;
  const bool map_match = event.match->kind == recognition::QueryKind::kMapMatch;
  const trace::Span span(map_match ? "merge" : "loop", {{"mission", trace::missionKey(event.mission)},
                                                        {"agent", match.query.agent},
                                                        {"keyframe", match.query.counter},
                                                        {"map", match.candidate_map},
                                                        {"from_map", match.query_map}});
  if (map_match) {
    if (options_.merge_maps) merge(*mission, *s, match, event.arrived);
  } else if (options_.close_loops) {
    closeLoop(*mission, *s, match, event.arrived);
  }
}

void BackendWorker::merge(Mission& mission, MissionState& state, const recognition::VerifiedMatch& match,
                          Clock::time_point arrived) {
  const std::shared_ptr<ServerMap> from = mission.stack().find(match.query_map);
  const std::shared_ptr<ServerMap> into = mission.stack().find(match.candidate_map);
  const auto stale = [&] {
    const std::lock_guard lock(mutex_);
    ++state.stats.stale_matches;
  };
  if (!from || !into || from == into) return stale();
  // Until the merge's correction is applied, no GBA of `into` starts: the two results are changes of state and
  // compose when applied, so a GBA from a snapshot with the query map before the correction would apply the
  // correction a second time.
  struct HoldGba {
    BackendWorker& worker;
    HoldGba(BackendWorker& w, const std::string& mission, MapId map) : worker(w) {
      const std::lock_guard lock(worker.mutex_);
      worker.correcting_ = std::make_pair(mission, map);
    }
    ~HoldGba() {
      {
        const std::lock_guard lock(worker.mutex_);
        worker.correcting_.reset();
      }
      worker.gba_wake_.notify_one();
    }
    HoldGba(const HoldGba&) = delete;
    HoldGba& operator=(const HoldGba&) = delete;
  };
  const std::optional<HoldGba> hold = options_.merge_correction_keyframes > 0
                                          ? std::make_optional<HoldGba>(*this, mission.name(), into->id())
                                          : std::nullopt;
  // The query's map goes, so a GBA of it would be for nothing. Without a correction a GBA of the candidate's map
  // goes on: the merge adds keyframes and points and moves none of the map's own, so the GBA's result still
  // applies, and the merged keyframes keep their state until the GBA the merge requests. Cutting it short instead
  // throws its work away, and with merges coming faster than GBAs finish (many agents meeting one after another) a
  // growing map would get no GBA applied at all. A correction places the query's map against the candidate's
  // keyframes as they are now; a GBA that moved those afterwards, without the query's map in its snapshot, would
  // leave the two parts apart where they meet (agents holding anchors of both saw it: on simulated euroc-mh mono,
  // four paired runs with that GBA let finish were 1.14x worse onboard), so with a correction it is cut short and
  // the merge's GBA of the whole merged map follows.
  cancelGba(mission.name(), from->id());
  if (hold) cancelGba(mission.name(), into->id());
  const AgentSensorsMap sensors = sensorsOf(mission);
  const CameraTable cameras(sensors);

  MergeRecord record;
  std::unordered_set<KeyframeId> query_keyframes;  // the query map's, before it went
  std::optional<std::set<AgentMapKey>> changed;    // the smaller map's agent maps, for a GBA of them alone
  ProjectionSearchInput search;                    // the fusion's projection search, run after the locks
  {
    StackLocks locks(mission, {from, into});
    const auto start = Clock::now();
    MapContent& q = locks.map(from->id());
    MapContent& c = locks.map(into->id());
    const ServerKeyframe* query = q.keyframe(match.query);
    if (query == nullptr || c.keyframe(match.candidate) == nullptr) return stale();
    for (const auto& [id, kf] : q.keyframes()) query_keyframes.insert(id);
    if (options_.gba_window_above_keyframes > 0 &&
        q.keyframes().size() + c.keyframes().size() > static_cast<std::size_t>(options_.gba_window_above_keyframes)) {
      // The smaller of the two maps is what its GBA needs to move against the other: the merge placed one in the
      // other's frame from a single match, and each was refined on its own before.
      changed.emplace();
      for (const auto& [id, kf] : q.keyframes().size() <= c.keyframes().size() ? q.keyframes() : c.keyframes()) {
        changed->insert({id.agent, kf.agent_map});
      }
    }
    // The match's transform takes the candidate map into the query's; the query's map moves, in 4 DoF.
    const SE3d T_into_from = fourDofTransform(match.T_qmap_cmap.inverse(), query->T_w_s.translation());
    {
      // In the same hold of the maps' locks as the absorb: a GBA of the query's map (one this merge cut short goes
      // back in the queue) that finds the map empty hands its waiters on through merged_into, so it must never
      // see the map emptied without the entry.
      const std::lock_guard lock(mutex_);
      auto& loops = state.loops[into->id()];
      auto& moved = state.loops[from->id()];
      loops.insert(loops.end(), moved.begin(), moved.end());
      state.loops.erase(from->id());
      state.merged_into[from->id()] = into->id();
    }
    c.absorb(q, T_into_from);
    for (auto& [agent, r] : locks.records()) {
      bool member = false;
      for (auto& [index, agent_map] : r->agent_maps) {
        if (agent_map.map == into->id()) member = true;
        if (agent_map.map != from->id()) continue;
        member = true;
        agent_map.map = into->id();
        agent_map.T_m_w = T_into_from * agent_map.T_m_w;
      }
      // The agents that should receive this merge's corrections, for following them in a trace.
      if (member) {
        trace::instant("merged_map_agent",
                       {{"mission", trace::missionKey(mission.name())}, {"map", into->id()}, {"agent", r->id}});
      }
      for (auto& [counter, held] : r->keyframes) {
        if (held.map == from->id()) held.map = into->id();
      }
      for (auto& [counter, map] : r->points) {
        if (map == from->id()) map = into->id();
      }
    }
    search = fuseMatchPairs(c, match, cameras.lookup(), options_.fusion, record.fusion);
    record.from = from->id();
    record.into = into->id();
    record.query = match.query;
    record.candidate = match.candidate;
    record.T_into_from = T_into_from;
    record.apply_ms = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
  }
  if (options_.on_merge_joined) options_.on_merge_joined(into->id());
  record.apply_ms += fuseWithoutLock(*into, search, options_.fusion, record.fusion);
  mission.stack().remove(from->id());
  {
    MissionEvent merged;
    merged.kind = MissionEvent::Kind::kMapsMerged;
    merged.map = into->id();
    merged.from_map = from->id();
    merged.cause = "map fusion";
    mission.events().append(std::move(merged));
  }
  if (recognition_ != nullptr) {
    recognition_->enqueue(recognition::KeyframeEvent{
        recognition::KeyframeEvent::Kind::kMerged, mission.name(), into->id(), {}, from->id()});
  }
  record.match_to_merged_s = secondsSince(arrived);
  if (options_.merge_correction_keyframes > 0 && correctMerge(mission, into, match, query_keyframes, record)) {
    record.match_to_corrected_s = secondsSince(arrived);
  }
  std::size_t index = 0;
  {
    const std::lock_guard lock(mutex_);
    state.stats.merges.push_back(record);
    index = state.stats.merges.size() - 1;
  }
  if (options_.gba_after_change) {
    requestGba(mission.name(), into->id(), false, std::make_pair(true, index), arrived, changed ? &*changed : nullptr);
  }
}

bool BackendWorker::correctMerge(Mission& mission, const std::shared_ptr<ServerMap>& into,
                                 const recognition::VerifiedMatch& match,
                                 const std::unordered_set<KeyframeId>& query_keyframes, MergeRecord& record) {
  const trace::Span span("merge_correction", {{"mission", trace::missionKey(mission.name())}, {"map", into->id()}});
  const AgentSensorsMap sensors = sensorsOf(mission);
  // What the solve needs, copied under the read lock; the solve without a lock.
  Result<MergeCorrectionInput> input =
      copyMergeCorrection(*into->read(), match, query_keyframes, options_.merge_correction_keyframes, sensors);
  if (!input) return false;
  if (options_.on_merge_correction_solve_start) options_.on_merge_correction_solve_start(into->id());
  const auto start = Clock::now();
  Result<MergeCorrection> correction = solveMergeCorrection(*input, options_.merge_correction_ba);
  if (!correction) return false;
  record.correction_solve_ms = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
  record.correction_ba = correction->ba;
  record.correction_change = correction->change;
  record.correction_keyframes = static_cast<int>(correction->keyframes.size());
  record.correction_m = correction->query_moved_m;
  record.correction_deg = correction->query_moved_deg;
  StackLocks locks(mission, {into});
  // The query's map moves rigidly: its keyframes keep their standing (refined or not), and its agents' frames
  // follow the same change.
  (void)applyToMission(mission, locks, into->id(), correction->keyframes, {},
                       ApplyOptions{.marks_refined = false,
                                    .frame_window = options_.frame_follows_keyframes,
                                    .held = nullptr,
                                    .keeps_standing = true},
                       "merge correction");
  return true;
}

void BackendWorker::closeLoop(Mission& mission, MissionState& state, const recognition::VerifiedMatch& match,
                              Clock::time_point arrived) {
  const std::shared_ptr<ServerMap> map = mission.stack().find(match.query_map);
  if (!map || match.query_map != match.candidate_map) {
    const std::lock_guard lock(mutex_);
    ++state.stats.stale_matches;
    return;
  }
  {
    const std::lock_guard lock(mutex_);
    const auto last = state.last_loop_query.find(match.query.agent);
    if (last != state.last_loop_query.end() &&
        match.query.counter < last->second + static_cast<std::uint32_t>(options_.loop_cooldown_keyframes)) {
      ++state.stats.loops_in_cooldown;
      return;
    }
  }
  const AgentSensorsMap sensors = sensorsOf(mission);
  const auto sensor = sensors.find(match.query.agent);
  if (sensor == sensors.end()) return;

  // The loop edge and the graph, from the map as it is (read lock); the solve without any lock.
  LoopRecord record;
  record.map = map->id();
  record.query = match.query;
  record.candidate = match.candidate;
  PoseGraph graph;
  {
    const auto content = map->read();
    const ServerKeyframe* query = content->keyframe(match.query);
    const ServerKeyframe* candidate = content->keyframe(match.candidate);
    if (query == nullptr || candidate == nullptr) {
      const std::lock_guard lock(mutex_);
      ++state.stats.stale_matches;
      return;
    }
    const SE3d T_m_qs = match.T_cmap_cq * sensor->second.T_s_c0.inverse();
    const LoopEdge edge{match.candidate, match.query, candidate->T_w_s.inverse() * T_m_qs};
    record.query_t_ns = query->t_ns;
    record.candidate_t_ns = candidate->t_ns;
    record.T_cs_qs_measured = edge.T_a_b;
    record.T_cs_qs_map = candidate->T_w_s.inverse() * query->T_w_s;
    std::vector<LoopEdge> loops;
    {
      const std::lock_guard lock(mutex_);
      state.loops[map->id()].push_back(edge);
      loops = state.loops[map->id()];
      state.last_loop_query[match.query.agent] = match.query.counter;
    }
    graph = buildPoseGraph(*content, loops, options_.pose_graph);
  }
  const auto solve_start = Clock::now();
  trace::Span graph_span("loop_pose_graph", {{"mission", trace::missionKey(mission.name())}, {"map", map->id()}});
  Result<std::vector<KeyframeCorrection>> corrections = solvePoseGraph(graph, options_.pose_graph);
  graph_span.set("keyframes", static_cast<std::int64_t>(corrections ? corrections->size() : 0));
  record.solve_ms = std::chrono::duration<double, std::milli>(Clock::now() - solve_start).count();
  if (!corrections) return;
  record.graph = graph.summary;
  const Move moved = moveOf(*corrections, match.query);
  record.correction_m = moved.m;
  record.correction_deg = moved.deg;
  // A running GBA of this map goes on unless the loop is a big correction: both results are changes of state
  // and compose when applied, and the GBA requested below takes the loop in.
  if (record.correction_m > options_.loop_cancels_gba_m || record.correction_deg > options_.loop_cancels_gba_deg) {
    record.cancelled_gba = cancelGba(mission.name(), map->id());
  }
  const CameraTable cameras(sensors);
  ProjectionSearchInput search;
  std::optional<std::set<AgentMapKey>> changed;  // for a GBA of what the pose graph moved
  {
    StackLocks locks(mission, {map});
    MapContent& content = locks.map(map->id());
    if (options_.gba_window_above_keyframes > 0 &&
        content.keyframes().size() > static_cast<std::size_t>(options_.gba_window_above_keyframes)) {
      LoopWindow window =
          loopWindowAgentMaps(content, *corrections, {match.query, match.candidate}, options_.loop_window_move_m,
                              options_.loop_window_move_deg, kWindowMaxFreeFraction);
      record.window_agent_maps = static_cast<int>(window.free.size());
      record.map_agent_maps = window.map_agent_maps;
      changed = std::move(window.free);
    }
    (void)applyToMission(mission, locks, map->id(), *corrections, {},
                         ApplyOptions{/*marks_refined=*/false, options_.frame_follows_keyframes}, "loop closure");
    search = fuseMatchPairs(content, match, cameras.lookup(), options_.fusion, record.fusion);
  }
  (void)fuseWithoutLock(*map, search, options_.fusion, record.fusion);
  record.match_to_corrected_s = secondsSince(arrived);
  std::size_t index = 0;
  {
    const std::lock_guard lock(mutex_);
    state.stats.loops.push_back(record);
    index = state.stats.loops.size() - 1;
  }
  if (options_.gba_after_change) {
    requestGba(mission.name(), map->id(), false, std::make_pair(false, index), arrived, changed ? &*changed : nullptr);
  }
}

void BackendWorker::removeRedundant(Mission& mission, MissionState& state, MapId map_id, int checks) {
  const std::shared_ptr<ServerMap> map = mission.stack().find(map_id);
  if (!map) return;
  const AgentSensorsMap sensors = sensorsOf(mission);
  RedundancyOptions options = options_.redundancy;
  if (checks > 0) options.checks_per_round = checks;
  RedundancyReport report;
  {
    StackLocks locks(mission, {map});
    report = removeRedundantKeyframes(locks.map(map_id), sensors, options, state.rng);
    for (const KeyframeId& id : report.removed_keyframes) {
      const auto it = locks.records().find(id.agent);
      if (it == locks.records().end()) continue;
      it->second->server_removed_keyframes.insert(id.counter);
      it->second->removals_to_send.insert(id.counter);
      it->second->corrections.erase(id.counter);
    }
    for (const KeyframeId& id : report.removed_keyframes) {
      MissionEvent removed;
      removed.kind = MissionEvent::Kind::kKeyframeRemoved;
      removed.agent = id.agent;
      removed.keyframe = id;
      removed.map = map_id;
      removed.cause = "redundant";
      mission.events().append(std::move(removed));
    }
  }
  if (recognition_ != nullptr) {
    for (const KeyframeId& id : report.removed_keyframes) {
      recognition_->enqueue(
          recognition::KeyframeEvent{recognition::KeyframeEvent::Kind::kRemoved, mission.name(), map_id, id, 0});
    }
  }
  const std::lock_guard lock(mutex_);
  state.stats.redundancy_checked += static_cast<std::uint64_t>(report.checked);
  state.stats.redundant_removed += report.removed_keyframes.size();
  state.stats.redundant_kept_for_imu_gap += static_cast<std::uint64_t>(report.kept_for_imu_gap);
  state.stats.points_removed += report.removed_points.size();
}

}  // namespace cvislam::server::backend

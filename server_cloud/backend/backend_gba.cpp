// The back-end worker's GBA thread: the queue of GBA requests (requests for one map join, their waiters and
// windows with them), cutting a running GBA short, and one GBA from snapshot to applied result. The control
// thread (backend_worker.cpp) requests them.
#include <algorithm>
#include <iterator>

#include "common/trace/trace.hpp"
#include "server_cloud/backend/backend_worker.hpp"
#include "server_cloud/backend/backend_worker_state.hpp"
#include "server_cloud/backend/map_corrections.hpp"

namespace cvislam::server::backend {

void BackendWorker::requestGba(const std::string& mission, MapId map, bool final,
                               std::optional<std::pair<bool, std::size_t>> waiter, Clock::time_point since,
                               const std::set<AgentMapKey>* changed) {
  {
    const std::lock_guard lock(mutex_);
    auto it = std::find_if(gba_queue_.begin(), gba_queue_.end(),
                           [&](const GbaRequest& r) { return r.mission == mission && r.map == map; });
    if (it == gba_queue_.end()) {
      gba_queue_.push_back(GbaRequest{mission, map, final, {}, since, {}});
      it = std::prev(gba_queue_.end());
      if (changed != nullptr) it->changed = *changed;
    } else if (changed == nullptr) {
      it->changed.reset();
    } else if (it->changed) {
      it->changed->insert(changed->begin(), changed->end());
    }
    it->since = std::min(it->since, since);
    it->final = it->final || final;
    if (waiter) it->waiting.push_back({waiter->first, waiter->second, since});
  }
  gba_wake_.notify_one();
}

bool BackendWorker::cancelGba(const std::string& mission, MapId map) {
  const std::lock_guard lock(mutex_);
  if (gba_running_ && gba_running_->mission == mission && gba_running_->map == map && !gba_cancel_) {
    gba_cancel_ = true;
    ++state(mission).stats.gba_cancelled;
    // Its waiters move to the GBA that the change will request.
    GbaRequest again = *gba_running_;
    again.final = false;
    gba_queue_.push_front(std::move(again));
    return true;
  }
  return false;
}

void BackendWorker::refreshLoopEdges(const std::string& mission, MapId map, const MapContent& content) {
  // A loop edge carries the one relative pose place recognition measured when the loop closed. Once a GBA has
  // taken the loop in (its two sides' points fused, every keyframe refined against them), the map's own relative
  // pose across the loop is the better estimate; later loops' pose graphs then hold that, as ORB-SLAM's essential
  // graph does, instead of pulling the refined map back toward the old measurement at ten times the weight.
  const std::lock_guard lock(mutex_);
  const auto it = state(mission).loops.find(map);
  if (it == state(mission).loops.end()) return;
  for (LoopEdge& edge : it->second) {
    const ServerKeyframe* a = content.keyframe(edge.a);
    const ServerKeyframe* b = content.keyframe(edge.b);
    if (a != nullptr && b != nullptr) edge.T_a_b = a->T_w_s.inverse() * b->T_w_s;
  }
}

void BackendWorker::runGba() {
  trace::bindThread("global BA");
  std::unique_lock lock(mutex_);
  // The oldest request whose map no merge is correcting.
  const auto runnable = [this] {
    return std::find_if(gba_queue_.begin(), gba_queue_.end(), [this](const GbaRequest& r) {
      return !correcting_ || r.mission != correcting_->first || r.map != correcting_->second;
    });
  };
  while (true) {
    gba_wake_.wait(lock, [&] { return stop_ || runnable() != gba_queue_.end(); });
    if (stop_) break;
    const auto next = runnable();
    gba_running_ = std::move(*next);
    gba_queue_.erase(next);
    gba_cancel_ = false;
    const GbaRequest request = *gba_running_;
    lock.unlock();
    gba(request);
    lock.lock();
    gba_running_.reset();
    if (queue_.empty() && !control_busy_ && gba_queue_.empty()) idle_.notify_all();
  }
  idle_.notify_all();
}

void BackendWorker::gba(const GbaRequest& request) {
  const std::shared_ptr<Mission> mission = missions_.find(request.mission);
  if (!mission) return;
  // A map merged into another before its GBA could run: its waiters (and the final flag) wait for that map's GBA.
  const auto forward = [&] {
    MapId target = request.map;
    {
      const std::lock_guard lock(mutex_);
      const MissionState& s = state(request.mission);
      for (auto it = s.merged_into.find(target); it != s.merged_into.end(); it = s.merged_into.find(target)) {
        target = it->second;
      }
    }
    if (target == request.map) return;
    const std::set<AgentMapKey>* changed = request.changed ? &*request.changed : nullptr;
    if (request.waiting.empty() && request.final)
      requestGba(request.mission, target, true, std::nullopt, request.since, changed);
    for (const GbaRequest::Waiter& waiter : request.waiting) {
      requestGba(request.mission, target, request.final, std::make_pair(waiter.is_merge, waiter.index), waiter.since,
                 changed);
    }
  };
  const std::shared_ptr<ServerMap> map = mission->stack().find(request.map);
  if (!map) return forward();
  trace::Span span(
      "global_ba",
      {{"mission", trace::missionKey(request.mission)}, {"map", request.map}, {"final", request.final ? 1 : 0}});
  // From the snapshot to the applied result, ingest times its batches as "during GBA".
  struct RunningGba {
    Mission& mission;
    explicit RunningGba(Mission& m) : mission(m) { mission.gbaStarted(); }
    ~RunningGba() { mission.gbaEnded(); }
    RunningGba(const RunningGba&) = delete;
    RunningGba& operator=(const RunningGba&) = delete;
  } running(*mission);
  const AgentSensorsMap sensors = sensorsOf(*mission);
  GbaRecord record;
  record.map = request.map;
  record.final = request.final;
  Result<GbaSnapshot> snapshot = Error{ErrorCode::kInternal, "no snapshot"};
  bool emptied = false;  // by a merge while this waited for the lock
  {
    const auto start = Clock::now();
    const auto content = map->read();
    emptied = content->keyframes().empty();
    std::optional<GbaWindow> window;
    if (request.changed && !request.final) {
      window = agentMapsWindow(*content, *request.changed, kWindowMaxFreeFraction);
    }
    // A window frees whole agent maps, so the apply leaves the others as they are (no keyframe of theirs has a
    // correction to carry) and carries the keyframes that the free ones' agents add meanwhile.
    if (content->keyframes().size() >= 2) snapshot = makeGbaSnapshot(*content, sensors, window ? &*window : nullptr);
    record.windowed = window.has_value();
    record.snapshot_ms = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
  }
  if (emptied) return forward();
  if (!snapshot) return;
  record.held_keyframes = static_cast<int>(std::count_if(snapshot->keyframes.begin(), snapshot->keyframes.end(),
                                                         [](const GbaKeyframe& k) { return k.held; }));
  span.set("keyframes", static_cast<std::int64_t>(snapshot->keyframes.size()));
  span.set("held", record.held_keyframes);
  if (options_.on_gba_solve_start) options_.on_gba_solve_start(request.map);
  GlobalBaOptions gba_options = options_.gba;
  if (!request.final) gba_options.time_budget_s = options_.gba_time_budget_s;
  Result<GlobalBaSummary> summary = runGlobalBa(*snapshot, gba_options, &gba_cancel_);
  if (!summary) return;
  record.summary = *summary;
  if (gba_cancel_) record.summary.cancelled = true;  // cut short after its last iteration: not applied
  if (!record.summary.cancelled) {
    StackLocks locks(*mission, {map});
    if (gba_cancel_) {
      record.summary.cancelled = true;
    } else {
      const auto start = Clock::now();
      const AppliedCorrections applied =
          applyToMission(*mission, locks, request.map, keyframeCorrections(*snapshot), pointCorrections(*snapshot),
                         ApplyOptions{/*marks_refined=*/true, options_.frame_follows_keyframes}, "global BA");
      record.keyframes_propagated = applied.keyframes_propagated;
      record.apply_ms = std::chrono::duration<double, std::milli>(Clock::now() - start).count();
      refreshLoopEdges(request.mission, request.map, locks.map(request.map));
    }
  }
  const std::lock_guard lock(mutex_);
  MissionState& s = state(request.mission);
  s.stats.gba.push_back(record);
  if (record.summary.cancelled) return;
  for (const GbaRequest::Waiter& w : request.waiting) {
    const double since = secondsSince(w.since);
    if (w.is_merge && w.index < s.stats.merges.size()) s.stats.merges[w.index].match_to_optimised_s = since;
    if (!w.is_merge && w.index < s.stats.loops.size()) s.stats.loops[w.index].match_to_optimised_s = since;
  }
}

}  // namespace cvislam::server::backend

// The server's back-end (CVI-SLAM IV-E, IV-F): map fusion, loop closure, global BA and redundancy removal, on two
// threads of their own while agents keep streaming.
//
//   control thread  verified matches from place recognition (a map match merges the query's map into the
//                   candidate's, and with merge_correction_keyframes corrects it at once; a loop runs the pose
//                   graph), the fusion of every new keyframe with the points
//                   of its covisible and nearby keyframes (map_fusion.hpp), and redundancy removal every
//                   `redundancy_every_keyframes` new keyframes of a map. Each holds the locks of the maps it
//                   changes for the milliseconds it takes.
//   GBA thread      global BA of a map after every merge or loop, every `gba_every_keyframes` new keyframes
//                   of a map when set, and of every map at drain(true), the end of a mission; on a snapshot:
//                   ingest carries on meanwhile, and the result is applied with the corrections of what
//                   arrived (applyCorrections). After a merge into a large map, only the smaller map's part is
//                   freed (gba_window_above_keyframes). A merge cancels a running GBA of the map that goes
//                   (and, with a merge correction, of the map it goes into, which then starts again on the
//                   merged map); a loop cancels its map's only when its pose graph moves the query keyframe by
//                   more than `loop_cancels_gba_m` / `loop_cancels_gba_deg`. A smaller
//                   loop lets the running GBA finish: its result is a change of state, composed with the
//                   loop's (applyCorrections), and the GBA the loop asks for follows it.
//
// After every change the agent records are brought up to date: which server map holds each agent map, and its
// T_m_w (the agent's world frame in the map's frame), so that what agents send next lands where the map expects
// it; changed keyframes are queued for the downlink. Locks are taken in the stack's order: the agent records of
// the maps' agents (by id), then the maps (by id).
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <filesystem>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <random>
#include <set>
#include <string>
#include <thread>
#include <unordered_set>
#include <vector>

#include "common/core/result.hpp"
#include "server_cloud/backend/global_ba.hpp"
#include "server_cloud/backend/map_fusion.hpp"
#include "server_cloud/backend/pose_graph.hpp"
#include "server_cloud/backend/redundancy.hpp"
#include "server_cloud/recognition/recognition_worker.hpp"
#include "server_cloud/stack/map_stack.hpp"

namespace cvislam::server::backend {

struct BackendOptions {
  bool enabled = true;
  bool merge_maps = true;
  bool close_loops = true;
  bool gba_after_change = true;  // after every merge and loop
  // Also a GBA of a map after this many new keyframes since its last request (0: only after merges and loops).
  // Between merges and loops the map otherwise holds the agents' own onboard estimates, and what the downlink
  // sends is another agent's drift held fixed; a GBA that has fused them is what makes anchors worth more.
  int gba_every_keyframes = 0;
  // Fuse every new keyframe with its covisible and nearby keyframes' points (what the search needs is copied
  // under the map's read lock, the search runs without a lock, the result is applied under the write lock).
  bool fuse_new_keyframes = true;
  // A loop whose query keyframe is within this many keyframes of its agent's previous loop is left out (the
  // pose graph and GBA of the previous one already hold it).
  int loop_cooldown_keyframes = 20;
  // After a GBA or a loop's pose graph, an agent map's T_m_w changes as its this many newest corrected keyframes
  // did (mean rotation, least-squares translation); 1 follows the newest keyframe alone, whose own correction
  // (it is the least constrained) then turns every anchor the agent is sent next.
  int frame_follows_keyframes = 10;
  // A loop cuts a running GBA of its map short only when its pose graph moves the query keyframe by more than
  // this (either bound); smaller loops wait for the next GBA, so long solves are not thrown away again and again.
  double loop_cancels_gba_m = 0.05;
  double loop_cancels_gba_deg = 0.5;
  // Right after a merge, before its GBA (which takes seconds on a large map): a BA of the query keyframe and its
  // this many most covisible keyframes of the query's map against the candidate's map, and the one 4-DoF change
  // that fits their moves applied to the whole query map (merge_correction.hpp). The match's transform alone is
  // off by a few cm (the recognition's estimate from one keyframe); this takes that out in a fraction of a second
  // and keeps each map as consistent as it was. 0: the transform alone until the GBA.
  int merge_correction_keyframes = 10;
  // The GBA after a merge into a map of more than this many keyframes frees only the part the merge changed: the
  // keyframes of the agent maps of the smaller of the two maps joined (those their agents add meanwhile
  // included); the others that see their points are held. With many agents over one place every keyframe sees
  // most others' points, so a GBA's linear system is dense and its cost grows with the cube of the free
  // keyframes; what the merge did not move needs no new solve. Requests joined with a whole-map one (the
  // periodic one, the final one) free the whole map. 0: every GBA frees the whole map. 150 is what was
  // measured on the simulated hall8 mission.
  int gba_window_above_keyframes = 150;
  // The same for the GBA after a loop in such a map: it frees the loop's two sides' agent maps and those that the
  // loop's pose graph moved a keyframe of by more than either bound, the most moved first, up to 60 % of the map
  // (loopWindowAgentMaps); the rest keeps its state. A loop of a few cm in a merged map otherwise asks for a GBA of
  // every keyframe of every agent.
  double loop_window_move_m = 0.01;
  double loop_window_move_deg = 0.1;
  // A GBA other than the final one stops at the last iteration expected to end within this many seconds of its
  // start (each of its two steps takes one whatever the time) and is applied; the map's next GBA (the next merge's
  // or loop's, the periodic one, the final one) goes on from there. Past its first full iteration or two a GBA
  // lowers the cost by a few per cent at most (backend.json's accepted_steps), and a loop's or merge's GBA that
  // waits behind another waits about this long at most. Not a continuation: on a dense map that keeps growing
  // under load, continuations never converge, and the GBA thread would take a core from ingest for good.
  // 0: every GBA runs to convergence.
  double gba_time_budget_s = 3.0;
  GlobalBaOptions merge_correction_ba{.structure_iterations = 0, .full_iterations = 6, .function_tolerance = 1e-4};
  int redundancy_every_keyframes = 10;  // per map
  // At the end of a mission (drain(true)), before the last GBA: every eligible keyframe of every map is checked
  // once more. During the mission a keyframe is checked at random and often before later flights covered it.
  bool final_redundancy_pass = true;
  std::size_t queue_capacity = 100'000;
  GlobalBaOptions gba;
  PoseGraphOptions pose_graph;
  FusionOptions fusion;
  RedundancyOptions redundancy;
  // Test seams: called with the map's id once what a solve needs is copied, before it: a GBA's (on the GBA
  // thread) and a merge's correction (on the control thread).
  std::function<void(MapId)> on_gba_solve_start;
  std::function<void(MapId)> on_merge_correction_solve_start;
  // Called once a merge has joined the two maps and let go of their locks, before its fusion searches (the map
  // joined into).
  std::function<void(MapId)> on_merge_joined;

  [[nodiscard]] Status validate() const;
  [[nodiscard]] std::string describe() const;
};

struct MergeRecord {
  MapId from = 0;
  MapId into = 0;
  KeyframeId query;
  KeyframeId candidate;
  geometry::SE3d T_into_from;  // 4-DoF
  FusionReport fusion;
  double apply_ms = 0.0;           // under the locks
  double match_to_merged_s = 0.0;  // from the match's arrival to the joined map
  // The correction right after the merge (merge_correction_keyframes): the BA of the query's window, the rigid
  // change it gave the query's map and how many keyframes that moved, how far it moved the query keyframe, and
  // when the map held it.
  GlobalBaSummary correction_ba;
  geometry::SE3d correction_change;
  int correction_keyframes = 0;
  double correction_m = 0.0;
  double correction_deg = 0.0;
  double correction_solve_ms = 0.0;    // both solves, no lock held
  double match_to_corrected_s = -1.0;  // -1: no correction applied
  double match_to_optimised_s = -1.0;  // to the GBA after it applied (-1: none did)
};

struct LoopRecord {
  MapId map = 0;
  KeyframeId query;
  KeyframeId candidate;
  double correction_m = 0.0;  // how far the pose graph moved the query keyframe
  double correction_deg = 0.0;
  // The loop's measurement against the map it corrects, for scoring both against the truth: the two keyframes'
  // times, the query sensor's pose in the candidate's as place recognition measured it, and as the map held it
  // before the pose graph.
  std::int64_t query_t_ns = 0;
  std::int64_t candidate_t_ns = 0;
  geometry::SE3d T_cs_qs_measured;
  geometry::SE3d T_cs_qs_map;
  // In a map above gba_window_above_keyframes: how many of its agent maps the GBA after the loop frees (those the
  // pose graph moved, and the loop's two sides) out of how many it holds; 0 and 0 in a smaller map.
  int window_agent_maps = 0;
  int map_agent_maps = 0;
  PoseGraphSummary graph;
  FusionReport fusion;
  double solve_ms = 0.0;
  double match_to_corrected_s = -1.0;  // the pose graph's correction applied to the map
  bool cancelled_gba = false;          // it cut a running GBA of its map short (a big correction)
  double match_to_optimised_s = -1.0;
};

struct GbaRecord {
  MapId map = 0;
  GlobalBaSummary summary;  // its keyframes include the held ones
  bool windowed = false;    // a merge's, of the part it changed (gba_window_above_keyframes)
  int held_keyframes = 0;
  double snapshot_ms = 0.0;
  double apply_ms = 0.0;
  int keyframes_propagated = 0;  // arrived while it ran
  bool final = false;            // the drain's
};

struct BackendStats {
  std::vector<MergeRecord> merges;
  std::vector<LoopRecord> loops;
  std::vector<GbaRecord> gba;
  std::uint64_t gba_cancelled = 0;
  std::uint64_t stale_matches = 0;  // maps merged or keyframes gone before their turn
  std::uint64_t loops_in_cooldown = 0;
  std::uint64_t new_keyframes_fused = 0;  // new keyframes searched against their partners
  std::uint64_t new_keyframe_links = 0;   // keypoints that now observe a point they did not
  std::uint64_t new_keyframe_point_merges = 0;
  double new_keyframe_fuse_ms_max = 0.0;  // search and apply of one keyframe
  double new_keyframe_fuse_ms_total = 0.0;
  // Of which under the map's locks (the copy and the apply), from their acquisition: waits for them excluded.
  double new_keyframe_fuse_locked_ms_max = 0.0;
  std::uint64_t redundancy_checked = 0;
  std::uint64_t final_pass_removed = 0;          // of redundant_removed, by the final pass
  std::uint64_t redundant_kept_for_imu_gap = 0;  // redundant, but removing it would leave too long an IMU link
  std::uint64_t redundant_removed = 0;
  std::uint64_t points_removed = 0;
  std::uint64_t dropped_events = 0;
};

class BackendWorker {
 public:
  // `recognition`, when given, hears of merges and removals (its database follows the maps).
  BackendWorker(const BackendOptions& options, MissionRegistry& missions, recognition::RecognitionWorker* recognition);
  ~BackendWorker();
  BackendWorker(const BackendWorker&) = delete;
  BackendWorker& operator=(const BackendWorker&) = delete;

  // Never block: false when the queue is full (the event is dropped and counted).
  bool onMatch(const std::string& mission, const recognition::MatchRecord& match);
  // The keyframes ingest added, with the maps it put them in.
  bool onKeyframesAdded(const std::string& mission, const std::vector<std::pair<MapId, KeyframeId>>& keyframes);

  // Waits until every queued event is handled and no GBA runs; with `final_gba` (the end of a mission), then
  // makes the final redundancy pass (when enabled) and runs GBA on every map of every mission with at least two
  // keyframes.
  void drain(bool final_gba);

  [[nodiscard]] BackendStats stats(const std::string& mission) const;
  // What the GBA thread has to do for a mission: whether one of its GBAs runs, and the maps whose GBA waits.
  struct GbaWork {
    bool running = false;
    std::vector<MapId> queued;
  };
  [[nodiscard]] GbaWork gbaWork(const std::string& mission) const;
  [[nodiscard]] std::vector<std::string> missions() const;

 private:
  struct Event {
    enum class Kind { kMatch, kKeyframes, kFinalRedundancyPass, kFlush } kind = Kind::kMatch;
    std::string mission;
    std::optional<recognition::MatchRecord> match;
    std::vector<std::pair<MapId, KeyframeId>> keyframes;
    std::chrono::steady_clock::time_point arrived;
  };
  struct MissionState;
  class CameraTable;
  struct GbaRequest {
    std::string mission;
    MapId map = 0;
    bool final = false;
    // Merges and loops waiting for this GBA to report their time to optimised, each timed from its own match.
    struct Waiter {
      bool is_merge = false;
      std::size_t index = 0;
      std::chrono::steady_clock::time_point since;
    };
    std::vector<Waiter> waiting;
    std::chrono::steady_clock::time_point since;
    // The agent maps a merge moved (gba_window_above_keyframes); none: the whole map.
    std::optional<std::set<AgentMapKey>> changed;
  };

  bool push(Event event);
  void runControl();
  void runGba();
  void handleMatch(const Event& event);
  void merge(Mission& mission, MissionState& state, const recognition::VerifiedMatch& match,
             std::chrono::steady_clock::time_point arrived);
  // The merge's correction (merge_correction_keyframes) of `into`, which now holds the query's map; false when
  // it could not be made (the record says nothing of it then).
  bool correctMerge(Mission& mission, const std::shared_ptr<ServerMap>& into, const recognition::VerifiedMatch& match,
                    const std::unordered_set<KeyframeId>& query_keyframes, MergeRecord& record);
  void closeLoop(Mission& mission, MissionState& state, const recognition::VerifiedMatch& match,
                 std::chrono::steady_clock::time_point arrived);
  void handleKeyframes(const Event& event);
  void finalRedundancyPass(const std::string& mission);
  void fuseNewKeyframe(Mission& mission, MissionState& state, const CameraTable& cameras, const KeyframeId& keyframe);
  // Checks `checks` random keyframes of the map (options_.redundancy.checks_per_round when 0).
  void removeRedundant(Mission& mission, MissionState& state, MapId map, int checks = 0);
  // `changed`: the agent maps a merge moved, for a GBA of their keyframes alone; nullptr (and any request it
  // joins that has none): the whole map.
  void requestGba(const std::string& mission, MapId map, bool final, std::optional<std::pair<bool, std::size_t>> waiter,
                  std::chrono::steady_clock::time_point since, const std::set<AgentMapKey>* changed = nullptr);
  // True when a GBA of `map` was running and is now told to stop.
  bool cancelGba(const std::string& mission, MapId map);
  void gba(const GbaRequest& request);
  // After a GBA of `map` was applied: each of its loop edges takes the relative pose the GBA left across the loop in
  // place of the one measured when the loop closed. Takes the worker's mutex: call it with the map locked, not
  // the other way round (closeLoop's order).
  void refreshLoopEdges(const std::string& mission, MapId map, const MapContent& content);
  MissionState& state(const std::string& mission);

  BackendOptions options_;
  MissionRegistry& missions_;
  recognition::RecognitionWorker* recognition_;

  mutable std::mutex mutex_;  // guards everything below except the threads
  std::condition_variable control_wake_;
  std::condition_variable gba_wake_;
  std::condition_variable idle_;
  std::deque<Event> queue_;
  bool control_busy_ = false;
  std::deque<GbaRequest> gba_queue_;
  std::optional<GbaRequest> gba_running_;
  std::optional<std::pair<std::string, MapId>> correcting_;  // a merge's correction is solving: its map's GBA waits
  std::atomic<bool> gba_cancel_{false};
  bool stop_ = false;
  std::map<std::string, std::unique_ptr<MissionState>> states_;
  std::thread control_;
  std::thread gba_thread_;
};

}  // namespace cvislam::server::backend

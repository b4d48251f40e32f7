// One replica's part in a scale-out deployment: the missions it serves, through their leases
// (mission_leases.hpp).
//
//   - A Hello for a mission nobody serves makes this replica take its lease and load what the shared store holds
//     of it; the load runs on the coordinator's loading thread, and the Hello is answered UNAVAILABLE ("loading")
//     unless the load ends within a few tens of milliseconds: the agent connects again. A Hello for a mission
//     another replica serves is redirected there (the adapter names the owner's address in the stream's trailing
//     metadata).
//   - A renewal thread renews this replica's leases every ttl/3 on a connection of its own, so that neither a long
//     load nor a burst of lookups delays it, and writes its heartbeat first, so that the other replicas count it.
//   - The same thread queues takeovers of missions whose lease lapsed (their owner died or stalled) for the loading
//     thread. Lapsed missions are shared out over the live replicas, each in turn to the one that serves fewest
//     (takeoverShare()); every replica computes the same share from the database and takes only its own, so that
//     the missions of a dead replica spread instead of all going to the first replica that looks. A mission that
//     stays lapsed for two TTLs (its replica has no room, or died too) is taken by whoever looks next. A Hello
//     for a lapsed mission follows the same share: it is taken where it arrives only when the share says so, and
//     is otherwise told to connect again (by then the share's replica holds it, and redirects follow).
//   - After a load the lease is read again: a mission whose lease lapsed or moved while it loaded is dropped, not
//     served.
//   - A mission whose lease this replica loses is dropped at once (its streams end, its in-memory state goes); it
//     may be taken again later, loaded afresh from the store (its new owner may die too).
//   - A mission that fails to load (a damaged record) is retried with a growing back-off, and the replica says so,
//     instead of every replica replaying it every ttl/3.
//   - Who owns a mission and which replicas are alive are cached for ttl/3, so that map-service reads and listings
//     do not each query the database.
//   - At a clean shutdown release() lets every mission go at once, so that the others take them over at their
//     next look rather than after the lease's TTL.
#pragma once

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "server_cloud/cluster/mission_leases.hpp"
#include "server_cloud/ingest/mission_ownership.hpp"

namespace cvislam::server::cluster {

struct ReplicaCounters {
  std::uint64_t claimed = 0;     // missions taken at an agent's Hello
  std::uint64_t taken_over = 0;  // missions taken after their lease lapsed, by the thread
  std::uint64_t lost = 0;        // leases this replica lost
  std::uint64_t redirected = 0;  // Hellos answered with another replica's address
  std::uint64_t renew_failures = 0;
  std::uint64_t load_failures = 0;
  std::uint64_t lapsed_while_loading = 0;  // loads whose lease was gone when they ended
};

struct ReplicaOptions {
  // How long a Hello waits for the load it started before it is answered "loading".
  std::chrono::milliseconds claim_wait{50};
  // A mission that failed to load is tried again after this, doubling per failure up to the maximum.
  double retry_min_s = 5.0;
  double retry_max_s = 300.0;
};

class ReplicaCoordinator final : public MissionOwnership {
 public:
  // Loads a mission that this replica has just taken from the shared store; an error gives the lease back.
  using Loader = std::function<Status(const std::string& mission)>;
  // The mission is no longer this replica's (its lease was lost, or lapsed while it loaded): end its streams and
  // drop what memory holds of it.
  using Dropper = std::function<void(const std::string& mission)>;
  // Whether this replica may take one more mission (its limit of missions).
  using HasRoom = std::function<bool()>;

  // `leases` serves claims, lookups and takeovers; `renewals`, a connection of its own, only renews.
  ReplicaCoordinator(std::unique_ptr<MissionLeases> leases, std::unique_ptr<MissionLeases> renewals, Loader loader,
                     Dropper dropper, HasRoom has_room, ReplicaOptions options = {});
  ~ReplicaCoordinator() override;  // stops the threads; does not release (a crash must not either)
  ReplicaCoordinator(const ReplicaCoordinator&) = delete;
  ReplicaCoordinator& operator=(const ReplicaCoordinator&) = delete;

  // Starts renewing (and finding lapsed missions) every ttl/3, and the loading thread.
  void start();
  // Stops the threads and gives every mission back (a clean shutdown).
  Status release();

  Result<MissionOwner> claim(const std::string& mission) override;
  // A claim that first runs `prepare` while this replica holds the mission's lease, before the load is queued (map
  // reuse writes the mission's records into the shared store there, where no other replica can load half of
  // them). When another replica holds the lease, nothing runs and that replica is named; when `prepare` fails, the
  // lease is given back and its error returned. Does not wait for the load (waitForLoads() does).
  Result<MissionOwner> claimPrepared(const std::string& mission, const std::function<Status()>& prepare);
  Result<MissionOwner> owner(const std::string& mission) override;
  Result<std::vector<MissionOwner>> others() override;

  // One pass of the renewal thread's work (tests call it instead of waiting): renews, drops what was lost, and
  // queues takeovers of lapsed missions.
  void tick();
  // Waits until no load is queued or running (tests).
  void waitForLoads();

  [[nodiscard]] std::vector<std::string> served() const;
  [[nodiscard]] ReplicaCounters counters() const;
  [[nodiscard]] const LeaseOptions& options() const { return leases_->options(); }

 private:
  struct Retry {
    int failures = 0;
    std::chrono::steady_clock::time_point not_before;
    std::string error;
  };
  struct Load {
    std::string mission;
    Lease lease;  // as acquired
    bool by_takeover = false;
  };
  using Clock = std::chrono::steady_clock;

  // Lapsed missions this replica could take now (not served, loading or backing off here), and those of them
  // lapsed for overdueAfter(), which it takes whatever the share says.
  struct Candidates {
    std::vector<std::string> all;
    std::vector<std::string> overdue;
  };
  void renewLeases();
  // A Hello for a mission whose lease lapsed: true when the takeover share gives the mission to another live
  // replica (and it is not overdue), so that agents reconnecting all to the next replica in their lists do not pull
  // a dead replica's missions there; the renewal thread of the replica the share names takes it.
  bool takeoverGoesElsewhere(const std::string& mission);
  // How long a lapsed mission waits for the replica the share gives it before any replica takes it: two TTLs, so
  // that a replica whose renewal thread runs late (a CPU budget spent, a slow database) still takes its share.
  [[nodiscard]] Clock::duration overdueAfter() const { return cache_ttl_ * 6; }
  // Remembers since when each mission has been seen lapsed, and says which this replica could take.
  Candidates noteLapsed(const std::vector<std::string>& lapsed);
  void queueTakeovers();
  void runLoads();
  void load(const Load& job);
  // Under state_mutex_: a reason the mission may not be taken now, or nothing.
  [[nodiscard]] static Error loadingHere(const std::string& mission);
  void stopThreads();  // the renewals first, then the loads
  std::optional<std::string> blockedLocked(const std::string& mission, Clock::time_point now) const;
  // Acquires the lease and, when it is this replica's, queues its load. Returns the owner (here: queued).
  Result<MissionOwner> acquireAndQueue(const std::string& mission, bool by_takeover,
                                       const std::function<Status()>& prepare = {});

  std::unique_ptr<MissionLeases> leases_;
  std::unique_ptr<MissionLeases> renewals_;
  Loader loader_;
  Dropper dropper_;
  HasRoom has_room_;
  ReplicaOptions replica_options_;
  Clock::duration cache_ttl_;

  std::mutex db_mutex_;                    // leases_: one connection, one statement at a time
  std::mutex renew_mutex_;                 // renewals_: the renewal thread's, and tick()'s when a test calls it
  mutable std::mutex state_mutex_;         // everything below
  std::condition_variable state_changed_;  // a load ended, or one was queued
  std::set<std::string> served_;
  std::set<std::string> loading_;  // queued or running
  std::deque<Load> queue_;
  bool load_running_ = false;
  std::map<std::string, Retry> retries_;
  std::map<std::string, std::pair<Clock::time_point, MissionOwner>> owner_cache_;
  std::map<std::string, Clock::time_point> lapsed_seen_;  // lapsed missions, since when this replica has seen them
  std::optional<std::pair<Clock::time_point, std::vector<MissionOwner>>> others_cache_;
  ReplicaCounters counters_;
  bool stopping_ = false;

  std::mutex wake_mutex_;
  std::condition_variable wake_;
  bool renew_stopping_ = false;
  std::thread renew_thread_;
  std::thread load_thread_;
};

// The lapsed missions (by name) that `me` takes over: each mission in name order goes to the replica of `live` that
// then serves fewest, ties going to the first by holder name. `me` counts even when it is missing from `live` (its
// heartbeat could not be read back).
std::vector<std::string> takeoverShare(std::vector<std::string> lapsed, std::vector<ReplicaLoad> live,
                                       const std::string& me);

// A lease holder name for this process: "<replica>/<random 64-bit hex>".
std::string makeHolderName(const std::string& replica);

}  // namespace cvislam::server::cluster

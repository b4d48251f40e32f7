// One replica's part in a scale-out deployment: the missions it serves, through their leases
// (mission_leases.hpp).
//
//   - A Hello for a mission nobody serves makes this replica take its lease, load what the shared store holds of
//     it (the loader: ServerCore replays the mission's records), and serve it. A Hello for a mission another
//     replica serves is redirected there (the adapter names the owner's address in the stream's trailing metadata).
//   - Every ttl/3 a thread renews this replica's leases, and takes over every mission whose lease lapsed (its
//     owner died or stalled): the takeover needs no agent to come first. A mission whose lease this replica lost
//     is never served by it again in this process (its in-memory state is behind the store's): its agents and
//     readers are sent to the new owner.
//   - At a clean shutdown release() lets every mission go at once, so that the others take them over at their
//     next look rather than after the lease's TTL.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
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
};

class ReplicaCoordinator final : public MissionOwnership {
 public:
  // Loads a mission that this replica has just taken from the shared store; an error gives the lease back.
  using Loader = std::function<Status(const std::string& mission)>;

  ReplicaCoordinator(std::unique_ptr<MissionLeases> leases, Loader loader);
  ~ReplicaCoordinator() override;  // stops the thread; does not release (a crash must not either)
  ReplicaCoordinator(const ReplicaCoordinator&) = delete;
  ReplicaCoordinator& operator=(const ReplicaCoordinator&) = delete;

  // Starts renewing and taking over, every ttl/3.
  void start();
  // Stops the thread and gives every mission back (a clean shutdown).
  Status release();

  Result<MissionOwner> claim(const std::string& mission) override;
  Result<MissionOwner> owner(const std::string& mission) override;
  Result<std::vector<MissionOwner>> others() override;

  // One pass of the thread's work (tests call it to avoid waiting): renews, then takes lapsed missions over.
  void tick();

  [[nodiscard]] std::vector<std::string> served() const;
  [[nodiscard]] ReplicaCounters counters() const;
  [[nodiscard]] const LeaseOptions& options() const { return leases_->options(); }

 private:
  Result<MissionOwner> take(const std::string& mission, bool was_lost, bool by_takeover);
  bool renewLeases();  // false when the database did not answer

  std::unique_ptr<MissionLeases> leases_;
  Loader loader_;
  std::mutex db_mutex_;             // leases_: one connection, one statement at a time
  mutable std::mutex state_mutex_;  // the sets and counters
  std::set<std::string> served_;
  std::set<std::string> loading_;
  std::set<std::string> lost_;
  ReplicaCounters counters_;

  std::mutex wake_mutex_;
  std::condition_variable wake_;
  bool stopping_ = false;
  std::thread thread_;
};

// A lease holder name for this process: "<replica>/<random 64-bit hex>".
std::string makeHolderName(const std::string& replica);

}  // namespace cvislam::server::cluster

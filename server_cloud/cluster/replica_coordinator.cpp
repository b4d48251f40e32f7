#include "server_cloud/cluster/replica_coordinator.hpp"

#include <chrono>
#include <cstdio>
#include <random>

namespace cvislam::server::cluster {

namespace {
MissionOwner here() {
  return MissionOwner{};
}
MissionOwner elsewhere(const Lease& lease) {
  return MissionOwner{false, lease.holder, lease.address};
}
}  // namespace

std::string makeHolderName(const std::string& replica) {
  std::random_device entropy;  // not a simulation: a name that must differ between processes
  const std::uint64_t nonce = (static_cast<std::uint64_t>(entropy()) << 32U) ^ entropy();
  char hex[17];
  std::snprintf(hex, sizeof hex, "%016llx", static_cast<unsigned long long>(nonce));
  return replica + "/" + hex;
}

ReplicaCoordinator::ReplicaCoordinator(std::unique_ptr<MissionLeases> leases, Loader loader)
    : leases_(std::move(leases)), loader_(std::move(loader)) {}

ReplicaCoordinator::~ReplicaCoordinator() {
  {
    std::lock_guard lock(wake_mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) thread_.join();
}

void ReplicaCoordinator::start() {
  const auto period = std::chrono::duration<double>(leases_->options().ttl_s / 3.0);
  thread_ = std::thread([this, period] {
    std::unique_lock lock(wake_mutex_);
    while (!stopping_) {
      lock.unlock();
      tick();
      lock.lock();
      wake_.wait_for(lock, period, [this] { return stopping_; });
    }
  });
}

Status ReplicaCoordinator::release() {
  {
    std::lock_guard lock(wake_mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) thread_.join();
  std::vector<std::string> missions = served();
  Status result = Status::Ok();
  std::lock_guard db(db_mutex_);
  for (const std::string& mission : missions) {
    if (Status s = leases_->release(mission); !s.ok() && result.ok()) result = s;
  }
  std::lock_guard state(state_mutex_);
  served_.clear();
  return result;
}

Result<MissionOwner> ReplicaCoordinator::claim(const std::string& mission) {
  bool was_lost = false;
  {
    std::lock_guard lock(state_mutex_);
    if (served_.count(mission) != 0U) return here();
    if (loading_.count(mission) != 0U) {
      return Error{ErrorCode::kUnavailable,
                   "mission '" + mission + "' is being loaded from the store by this replica: connect again shortly"};
    }
    was_lost = lost_.count(mission) != 0U;
    if (!was_lost) loading_.insert(mission);  // from here on, this caller alone takes it
  }
  return take(mission, was_lost, /*by_takeover=*/false);
}

// The caller put `mission` into loading_ (unless it was lost: then only its owner is looked up).
Result<MissionOwner> ReplicaCoordinator::take(const std::string& mission, bool was_lost, bool by_takeover) {
  Result<Lease> lease = [&]() -> Result<Lease> {
    std::lock_guard db(db_mutex_);
    if (was_lost) {
      auto found = leases_->find(mission);
      if (!found) return found.error();
      if (!*found) return Error{ErrorCode::kNotFound, "mission '" + mission + "' has no lease"};
      return **found;
    }
    return leases_->acquire(mission);
  }();
  const auto done_loading = [&] {
    std::lock_guard lock(state_mutex_);
    loading_.erase(mission);
  };
  if (!lease) {
    done_loading();
    return lease.error();
  }
  if (lease->holder != leases_->options().holder) {
    done_loading();
    std::lock_guard lock(state_mutex_);
    ++counters_.redirected;
    if (was_lost && lease->remaining_s <= 0.0) {
      return Error{ErrorCode::kUnavailable, "mission '" + mission +
                                                "' is between replicas (its lease lapsed; another replica takes it "
                                                "over within a few seconds): connect again"};
    }
    return elsewhere(*lease);
  }
  // Ours: load what the store holds of it before anyone is served.
  const auto started = std::chrono::steady_clock::now();
  if (Status loaded = loader_(mission); !loaded.ok()) {
    {
      std::lock_guard db(db_mutex_);
      (void)leases_->release(mission);
    }
    done_loading();
    return loaded.error().withContext("loading mission '" + mission + "' from the store (its lease was given back)");
  }
  const double load_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - started).count();
  {
    std::lock_guard lock(state_mutex_);
    loading_.erase(mission);
    served_.insert(mission);
    ++(by_takeover ? counters_.taken_over : counters_.claimed);
  }
  std::fprintf(stderr, "[server] %s mission '%s' (lease epoch %lld), loaded from the store in %.3f s\n",
               by_takeover ? "took over" : "serves", mission.c_str(), static_cast<long long>(lease->epoch), load_s);
  return here();
}

Result<MissionOwner> ReplicaCoordinator::owner(const std::string& mission) {
  {
    std::lock_guard lock(state_mutex_);
    if (served_.count(mission) != 0U) return here();
  }
  std::lock_guard db(db_mutex_);
  auto found = leases_->find(mission);
  if (!found) return found.error();
  if (!*found) return Error{ErrorCode::kNotFound, "no replica serves mission '" + mission + "'"};
  if ((*found)->holder == leases_->options().holder) return here();
  if ((*found)->remaining_s <= 0.0) {
    return Error{ErrorCode::kUnavailable,
                 "mission '" + mission + "' is between replicas (its owner's lease lapsed): ask again shortly"};
  }
  return elsewhere(**found);
}

Result<std::vector<MissionOwner>> ReplicaCoordinator::others() {
  std::lock_guard db(db_mutex_);
  auto holders = leases_->otherHolders();
  if (!holders) return holders.error();
  std::vector<MissionOwner> out;
  out.reserve(holders->size());
  for (const Lease& lease : *holders) out.push_back(elsewhere(lease));
  return out;
}

bool ReplicaCoordinator::renewLeases() {
  Result<std::vector<std::string>> renewed = [&] {
    std::lock_guard db(db_mutex_);
    return leases_->renew();
  }();
  if (!renewed) {
    std::lock_guard lock(state_mutex_);
    if (counters_.renew_failures++ % 10 == 0) {
      std::fprintf(stderr, "[server] cannot renew the mission leases: %s\n", renewed.error().message().c_str());
    }
    return false;
  }
  {
    const std::set<std::string> still(renewed->begin(), renewed->end());
    std::lock_guard lock(state_mutex_);
    for (auto it = served_.begin(); it != served_.end();) {
      if (still.count(*it) != 0U) {
        ++it;
        continue;
      }
      std::fprintf(stderr,
                   "[server] lost the lease of mission '%s' (another replica took it over); its agents go there\n",
                   it->c_str());
      lost_.insert(*it);
      ++counters_.lost;
      it = served_.erase(it);
    }
  }
  return true;
}

void ReplicaCoordinator::tick() {
  if (!renewLeases()) return;
  Result<std::vector<std::string>> lapsed = [&] {
    std::lock_guard db(db_mutex_);
    return leases_->lapsed();
  }();
  if (!lapsed) return;
  for (const std::string& mission : *lapsed) {
    {
      std::lock_guard lock(wake_mutex_);
      if (stopping_) return;
    }
    // A load may take a while: keep the leases held so far alive first.
    if (!renewLeases()) return;
    {
      std::lock_guard lock(state_mutex_);
      if (served_.count(mission) != 0U || loading_.count(mission) != 0U || lost_.count(mission) != 0U) continue;
      loading_.insert(mission);
    }
    auto taken = take(mission, /*was_lost=*/false, /*by_takeover=*/true);
    if (!taken) {
      std::fprintf(stderr, "[server] could not take mission '%s' over: %s\n", mission.c_str(),
                   taken.error().message().c_str());
    }
  }
}

std::vector<std::string> ReplicaCoordinator::served() const {
  std::lock_guard lock(state_mutex_);
  return {served_.begin(), served_.end()};
}

ReplicaCounters ReplicaCoordinator::counters() const {
  std::lock_guard lock(state_mutex_);
  return counters_;
}

}  // namespace cvislam::server::cluster

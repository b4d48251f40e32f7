#include "server_cloud/cluster/replica_coordinator.hpp"

#include "common/core/text.hpp"
#include "server_cloud/store/operator_log.hpp"

#include <algorithm>
#include <cmath>
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
std::string seconds(double s) {
  return text::formatDouble(std::ceil(s)) + " s";
}
}  // namespace

std::vector<std::string> takeoverShare(std::vector<std::string> lapsed, std::vector<ReplicaLoad> live,
                                       const std::string& me) {
  if (std::none_of(live.begin(), live.end(), [&](const ReplicaLoad& r) { return r.holder == me; })) {
    live.push_back(ReplicaLoad{me, "", 0});
  }
  std::sort(lapsed.begin(), lapsed.end());
  std::vector<std::string> mine;
  for (const std::string& mission : lapsed) {
    auto least = std::min_element(live.begin(), live.end(), [](const ReplicaLoad& a, const ReplicaLoad& b) {
      return a.missions != b.missions ? a.missions < b.missions : a.holder < b.holder;
    });
    ++least->missions;
    if (least->holder == me) mine.push_back(mission);
  }
  return mine;
}

std::string makeHolderName(const std::string& replica) {
  std::random_device entropy;  // not a simulation: a name that must differ between processes
  const std::uint64_t nonce = (static_cast<std::uint64_t>(entropy()) << 32U) ^ entropy();
  char hex[17];
  std::snprintf(hex, sizeof hex, "%016llx", static_cast<unsigned long long>(nonce));
  return replica + "/" + hex;
}

ReplicaCoordinator::ReplicaCoordinator(std::unique_ptr<MissionLeases> leases, std::unique_ptr<MissionLeases> renewals,
                                       Loader loader, Dropper dropper, HasRoom has_room, ReplicaOptions options)
    : leases_(std::move(leases)),
      renewals_(std::move(renewals)),
      loader_(std::move(loader)),
      dropper_(std::move(dropper)),
      has_room_(std::move(has_room)),
      replica_options_(options),
      cache_ttl_(
          std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(leases_->options().ttl_s / 3.0))) {}

ReplicaCoordinator::~ReplicaCoordinator() {
  stopThreads();
}

void ReplicaCoordinator::stopThreads() {
  {
    std::lock_guard lock(wake_mutex_);
    renew_stopping_ = true;
  }
  wake_.notify_all();
  if (renew_thread_.joinable()) renew_thread_.join();
  {
    std::lock_guard lock(state_mutex_);
    stopping_ = true;
  }
  state_changed_.notify_all();
  if (load_thread_.joinable()) load_thread_.join();
}

void ReplicaCoordinator::start() {
  const auto period = std::chrono::duration<double>(leases_->options().ttl_s / 3.0);
  load_thread_ = std::thread([this] { runLoads(); });
  renew_thread_ = std::thread([this, period] {
    std::unique_lock lock(wake_mutex_);
    while (!renew_stopping_) {
      lock.unlock();
      tick();
      lock.lock();
      wake_.wait_for(lock, period, [this] { return renew_stopping_; });
    }
  });
}

Status ReplicaCoordinator::release() {
  stopThreads();
  std::vector<std::string> missions = served();
  Status result = Status::Ok();
  std::lock_guard db(db_mutex_);
  // The heartbeat goes first: the others then share the released missions among themselves only.
  if (Status s = leases_->leave(); !s.ok()) result = s;
  for (const std::string& mission : missions) {
    if (Status s = leases_->release(mission); !s.ok() && result.ok()) result = s;
  }
  std::lock_guard state(state_mutex_);
  served_.clear();
  return result;
}

std::optional<std::string> ReplicaCoordinator::blockedLocked(const std::string& mission, Clock::time_point now) const {
  const auto it = retries_.find(mission);
  if (it == retries_.end() || now >= it->second.not_before) return std::nullopt;
  const double wait_s = std::chrono::duration<double>(it->second.not_before - now).count();
  return "its stored records failed to load " + std::to_string(it->second.failures) + " time(s) (" + it->second.error +
         "); the next try is in " + seconds(wait_s);
}

Result<MissionOwner> ReplicaCoordinator::claim(const std::string& mission) {
  const auto loaded = [&](std::unique_lock<std::mutex>& lock) -> std::optional<Result<MissionOwner>> {
    state_changed_.wait_for(lock, replica_options_.claim_wait, [&] { return loading_.count(mission) == 0U; });
    if (served_.count(mission) != 0U) return Result<MissionOwner>(here());
    if (loading_.count(mission) != 0U) return Result<MissionOwner>(loadingHere(mission));
    return std::nullopt;
  };
  {
    std::unique_lock lock(state_mutex_);
    if (served_.count(mission) != 0U) return here();
    if (loading_.count(mission) != 0U) {
      if (auto answer = loaded(lock)) return *answer;
    }
    if (auto blocked = blockedLocked(mission, Clock::now())) {
      return Error{ErrorCode::kUnavailable, "mission '" + mission + "' cannot be served now: " + *blocked};
    }
  }
  if (takeoverGoesElsewhere(mission)) {
    return Error{ErrorCode::kUnavailable, "mission '" + mission +
                                              "' is between replicas (its owner's lease lapsed, and another live "
                                              "replica takes it over within a second): connect again"};
  }
  auto owner = acquireAndQueue(mission, /*by_takeover=*/false);
  if (!owner || !owner->here) return owner;
  std::unique_lock lock(state_mutex_);
  if (auto answer = loaded(lock)) return *answer;
  if (auto blocked = blockedLocked(mission, Clock::now())) {
    return Error{ErrorCode::kUnavailable, "mission '" + mission + "' cannot be served now: " + *blocked};
  }
  return Error{ErrorCode::kUnavailable, "mission '" + mission + "' is not served here now: connect again"};
}

Result<MissionOwner> ReplicaCoordinator::claimPrepared(const std::string& mission,
                                                       const std::function<Status()>& prepare) {
  return acquireAndQueue(mission, /*by_takeover=*/false, prepare);
}

Result<MissionOwner> ReplicaCoordinator::acquireAndQueue(const std::string& mission, bool by_takeover,
                                                         const std::function<Status()>& prepare) {
  {
    std::lock_guard lock(state_mutex_);
    if (served_.count(mission) != 0U || loading_.count(mission) != 0U) return here();
    loading_.insert(mission);  // from here on, this caller alone takes it
  }
  Result<Lease> lease = [&] {
    std::lock_guard db(db_mutex_);
    return leases_->acquire(mission);
  }();
  if (lease && lease->holder == leases_->options().holder && prepare) {
    if (Status prepared = prepare(); !prepared.ok()) {
      {
        std::lock_guard db(db_mutex_);
        (void)leases_->release(mission);
      }
      std::lock_guard lock(state_mutex_);
      loading_.erase(mission);
      state_changed_.notify_all();
      return prepared.error();
    }
  }
  std::lock_guard lock(state_mutex_);
  if (!lease || lease->holder != leases_->options().holder) {
    loading_.erase(mission);
    state_changed_.notify_all();
    if (!lease) {
      return Error{ErrorCode::kUnavailable,
                   "the lease of mission '" + mission + "' could not be taken (" + logForOperator(lease.error()) + ")"};
    }
    ++counters_.redirected;
    if (lease->remaining_s <= 0.0) {
      return Error{ErrorCode::kUnavailable, "mission '" + mission +
                                                "' is between replicas (its lease lapsed; a replica takes it over "
                                                "within a few seconds): connect again"};
    }
    owner_cache_[mission] = {Clock::now(), elsewhere(*lease)};
    return elsewhere(*lease);
  }
  queue_.push_back(Load{mission, *lease, by_takeover});
  state_changed_.notify_all();
  return here();
}

void ReplicaCoordinator::runLoads() {
  std::unique_lock lock(state_mutex_);
  while (true) {
    state_changed_.wait(lock, [this] { return stopping_ || !queue_.empty(); });
    if (stopping_) return;
    const Load job = queue_.front();
    queue_.pop_front();
    load_running_ = true;
    lock.unlock();
    load(job);
    lock.lock();
    load_running_ = false;
    loading_.erase(job.mission);
    state_changed_.notify_all();
  }
}

void ReplicaCoordinator::load(const Load& job) {
  const std::string& mission = job.mission;
  const auto started = Clock::now();
  if (Status loaded = loader_(mission); !loaded.ok()) {
    dropper_(mission);  // whatever the load applied before it failed
    {
      std::lock_guard db(db_mutex_);
      (void)leases_->release(mission);
    }
    std::lock_guard lock(state_mutex_);
    Retry& retry = retries_[mission];
    ++retry.failures;
    ++counters_.load_failures;
    retry.error = logForOperator(loaded.error());
    const double wait_s = std::min(replica_options_.retry_max_s,
                                   replica_options_.retry_min_s * std::pow(2.0, std::min(retry.failures - 1, 20)));
    retry.not_before =
        Clock::now() + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(wait_s));
    std::fprintf(stderr,
                 "[server] mission '%s' failed to load from the store (%d time(s)): %s; its lease was given back, "
                 "and this replica tries it again in %s\n",
                 mission.c_str(), retry.failures, retry.error.c_str(), seconds(wait_s).c_str());
    return;
  }
  const double load_s = std::chrono::duration<double>(Clock::now() - started).count();
  // The lease may have lapsed during a long load, and another replica taken the mission: then what was loaded is
  // behind what that replica appends, and must not be served.
  Result<std::optional<Lease>> now = [&] {
    std::lock_guard db(db_mutex_);
    return leases_->find(mission);
  }();
  const bool still_ours = now && *now && (*now)->holder == leases_->options().holder &&
                          (*now)->epoch == job.lease.epoch && (*now)->remaining_s > 0.0;
  if (!still_ours) {
    dropper_(mission);
    std::lock_guard lock(state_mutex_);
    ++counters_.lapsed_while_loading;
    std::fprintf(stderr, "[server] mission '%s' loaded in %.3f s, but its lease %s meanwhile: not served here\n",
                 mission.c_str(), load_s, now ? "lapsed or moved" : "could not be read");
    return;
  }
  std::lock_guard lock(state_mutex_);
  served_.insert(mission);
  retries_.erase(mission);
  owner_cache_.erase(mission);
  ++(job.by_takeover ? counters_.taken_over : counters_.claimed);
  std::fprintf(stderr, "[server] %s mission '%s' (lease epoch %lld), loaded from the store in %.3f s\n",
               job.by_takeover ? "took over" : "serves", mission.c_str(), static_cast<long long>(job.lease.epoch),
               load_s);
}

void ReplicaCoordinator::waitForLoads() {
  std::unique_lock lock(state_mutex_);
  state_changed_.wait(lock, [this] { return stopping_ || (queue_.empty() && !load_running_); });
}

Result<MissionOwner> ReplicaCoordinator::owner(const std::string& mission) {
  const auto now = Clock::now();
  {
    std::lock_guard lock(state_mutex_);
    if (served_.count(mission) != 0U) return here();
    // Held here but still replaying: a read now would see part of the mission.
    if (loading_.count(mission) != 0U) return loadingHere(mission);
    if (auto it = owner_cache_.find(mission); it != owner_cache_.end() && now - it->second.first < cache_ttl_) {
      return it->second.second;
    }
  }
  Result<std::optional<Lease>> found = [&] {
    std::lock_guard db(db_mutex_);
    return leases_->find(mission);
  }();
  if (!found) return found.error();
  if (!*found) return Error{ErrorCode::kNotFound, "no replica serves mission '" + mission + "'"};
  if ((*found)->holder == leases_->options().holder) {
    std::lock_guard lock(state_mutex_);
    if (served_.count(mission) != 0U) return here();
    if (loading_.count(mission) != 0U) return loadingHere(mission);
    // The lease is this replica's but the mission is not served: its load failed and the lease is being let go.
    return Error{ErrorCode::kUnavailable,
                 "mission '" + mission + "' is not served by this replica now, though it holds its lease: ask again"};
  }
  if ((*found)->remaining_s <= 0.0) {
    return Error{ErrorCode::kUnavailable,
                 "mission '" + mission + "' is between replicas (its owner's lease lapsed): ask again shortly"};
  }
  std::lock_guard lock(state_mutex_);
  owner_cache_[mission] = {now, elsewhere(**found)};
  return elsewhere(**found);
}

Error ReplicaCoordinator::loadingHere(const std::string& mission) {
  return Error{ErrorCode::kUnavailable,
               "mission '" + mission + "' is being loaded from the store by this replica: try again shortly"};
}

Result<std::vector<MissionOwner>> ReplicaCoordinator::others() {
  const auto now = Clock::now();
  {
    std::lock_guard lock(state_mutex_);
    if (others_cache_ && now - others_cache_->first < cache_ttl_) return others_cache_->second;
  }
  Result<std::vector<Lease>> holders = [&] {
    std::lock_guard db(db_mutex_);
    return leases_->otherHolders();
  }();
  if (!holders) return holders.error();
  std::vector<MissionOwner> out;
  out.reserve(holders->size());
  for (const Lease& lease : *holders) out.push_back(elsewhere(lease));
  std::lock_guard lock(state_mutex_);
  others_cache_ = std::make_pair(now, out);
  return out;
}

void ReplicaCoordinator::renewLeases() {
  // Only what was served before the renewal can have been lost: a mission whose load ends while the renewal runs
  // was acquired after (or during) it, so its lease is not among those renewed and yet is this replica's.
  std::set<std::string> served_before;
  {
    std::lock_guard lock(state_mutex_);
    served_before = served_;
  }
  Result<std::vector<std::string>> renewed = [&]() -> Result<std::vector<std::string>> {
    std::lock_guard renewing(renew_mutex_);
    if (Status beat = renewals_->heartbeat(); !beat.ok()) return beat.error();
    return renewals_->renew();
  }();
  if (!renewed) {
    std::lock_guard lock(state_mutex_);
    if (counters_.renew_failures++ % 10 == 0) {
      std::fprintf(stderr, "[server] cannot renew the mission leases: %s\n", renewed.error().message().c_str());
    }
    return;
  }
  std::vector<std::string> lost;
  {
    const std::set<std::string> still(renewed->begin(), renewed->end());
    std::lock_guard lock(state_mutex_);
    for (auto it = served_.begin(); it != served_.end();) {
      if (still.count(*it) != 0U || served_before.count(*it) == 0U) {
        ++it;
        continue;
      }
      lost.push_back(*it);
      ++counters_.lost;
      owner_cache_.erase(*it);
      it = served_.erase(it);
    }
  }
  for (const std::string& mission : lost) {
    std::fprintf(stderr,
                 "[server] lost the lease of mission '%s' (another replica took it over): its streams end and its "
                 "agents go there\n",
                 mission.c_str());
    dropper_(mission);
  }
}

bool ReplicaCoordinator::takeoverGoesElsewhere(const std::string& mission) {
  std::vector<std::string> lapsed;
  std::vector<ReplicaLoad> live;
  {
    std::lock_guard db(db_mutex_);
    Result<std::optional<Lease>> lease = leases_->find(mission);
    // A new mission, a live lease (acquire() names its holder) or an unreadable one: the claim goes on as before.
    if (!lease || !*lease || (*lease)->remaining_s > 0.0) return false;
    auto all_lapsed = leases_->lapsed();
    auto all_live = leases_->liveReplicas();
    if (!all_lapsed || !all_live) return false;
    lapsed = std::move(*all_lapsed);
    live = std::move(*all_live);
  }
  {
    std::lock_guard lock(state_mutex_);
    const auto seen = lapsed_seen_.find(mission);
    if (seen != lapsed_seen_.end() && Clock::now() - seen->second >= overdueAfter()) return false;
  }
  const std::vector<std::string> mine = takeoverShare(lapsed, live, leases_->options().holder);
  return std::find(mine.begin(), mine.end(), mission) == mine.end();
}

ReplicaCoordinator::Candidates ReplicaCoordinator::noteLapsed(const std::vector<std::string>& lapsed) {
  const auto now = Clock::now();
  Candidates out;
  std::lock_guard lock(state_mutex_);
  std::map<std::string, Clock::time_point> seen;
  for (const std::string& mission : lapsed) {
    auto it = lapsed_seen_.find(mission);
    const Clock::time_point since = it == lapsed_seen_.end() ? now : it->second;
    seen.emplace(mission, since);
    if (stopping_ || served_.count(mission) != 0U || loading_.count(mission) != 0U) continue;
    if (blockedLocked(mission, now)) continue;
    out.all.push_back(mission);
    if (now - since >= overdueAfter()) out.overdue.push_back(mission);
  }
  lapsed_seen_ = std::move(seen);
  return out;
}

void ReplicaCoordinator::queueTakeovers() {
  Result<std::vector<std::string>> lapsed = [&] {
    std::lock_guard db(db_mutex_);
    return leases_->lapsed();
  }();
  if (!lapsed) return;
  const Candidates candidates = noteLapsed(*lapsed);
  if (candidates.all.empty()) return;
  Result<std::vector<ReplicaLoad>> live = [&] {
    std::lock_guard db(db_mutex_);
    return leases_->liveReplicas();
  }();
  // Without the list of replicas, this one takes what it sees, as one replica alone would.
  std::vector<std::string> mine = live ? takeoverShare(*lapsed, *live, leases_->options().holder) : candidates.all;
  std::set<std::string> take(candidates.overdue.begin(), candidates.overdue.end());
  for (const std::string& mission : mine) {
    if (std::find(candidates.all.begin(), candidates.all.end(), mission) != candidates.all.end()) {
      take.insert(mission);
    }
  }
  for (const std::string& mission : take) {
    if (has_room_ && !has_room_()) return;
    auto taken = acquireAndQueue(mission, /*by_takeover=*/true);
    if (!taken) {
      std::fprintf(stderr, "[server] could not take mission '%s' over: %s\n", mission.c_str(),
                   taken.error().message().c_str());
    }
  }
}

void ReplicaCoordinator::tick() {
  renewLeases();
  queueTakeovers();
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

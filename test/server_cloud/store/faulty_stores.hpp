// Seams for map stores that fail the way disks and database connections fail, over a real store underneath.
#pragma once

#include <atomic>
#include <cstdint>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "server_cloud/store/map_store.hpp"

namespace cvislam::server::test {

// A store that passes everything to `inner` and lets a test decide, per append, what the caller hears.
class ForwardingStore : public MapStore {
 public:
  explicit ForwardingStore(std::unique_ptr<MapStore> inner) : inner_(std::move(inner)) {}
  Status append(const StoreRecord& r) override { return inner_->append(r); }
  Status replay(const std::string& m, const std::function<Status(const StoreRecord&)>& v) const override {
    return inner_->replay(m, v);
  }
  [[nodiscard]] Result<std::optional<StoreRecord>> findBatch(const std::string& m, AgentId a,
                                                             std::uint64_t s) const override {
    return inner_->findBatch(m, a, s);
  }
  [[nodiscard]] Result<std::vector<std::string>> missions() const override { return inner_->missions(); }
  [[nodiscard]] StoreCounters counters() const override { return inner_->counters(); }
  [[nodiscard]] std::string describe() const override { return inner_->describe(); }

 protected:
  MapStore& inner() { return *inner_; }

 private:
  std::unique_ptr<MapStore> inner_;
};

// A database connection that breaks after a commit: batch `lost_sequence` (of any agent, once) is stored by the
// real store underneath, but its append answers kUnavailable, as a lost reply would.
class InDoubtStore final : public ForwardingStore {
 public:
  InDoubtStore(std::unique_ptr<MapStore> inner, std::uint64_t lost_sequence)
      : ForwardingStore(std::move(inner)), lost_sequence_(lost_sequence) {}
  Status append(const StoreRecord& r) override {
    Status s = inner().append(r);
    if (s.ok() && r.kind == StoreRecord::Kind::kBatch && r.sequence == lost_sequence_ && !lost_one_) {
      lost_one_ = true;
      return Error{ErrorCode::kUnavailable, "server closed the connection unexpectedly"};
    }
    return s;
  }
  [[nodiscard]] bool lostOne() const { return lost_one_; }
  [[nodiscard]] std::string describe() const override { return "in doubt over " + ForwardingStore::describe(); }

 private:
  std::uint64_t lost_sequence_;
  bool lost_one_ = false;
};

}  // namespace cvislam::server::test

#include "server_cloud/access/stream_limits.hpp"

#include <string>

namespace cvislam::server {

Status StreamLimitOptions::validate() const {
  if (per_address < 1 || total < 1) {
    return Error{ErrorCode::kInvalidArgument, std::string(per_address_key) + " and " + total_key + " must be >= 1"};
  }
  return Status::Ok();
}

Result<StreamLimits::Slot> StreamLimits::open(const std::string& address) {
  std::lock_guard lock(mutex_);
  if (total_ >= options_.total) {
    ++refused_;
    return Error{ErrorCode::kResourceExhausted, "the server has " + std::to_string(total_) +
                                                    " streams of this kind open, its limit (" + options_.total_key +
                                                    "): retry later"};
  }
  std::size_t& mine = by_address_[address];
  if (mine >= options_.per_address) {
    ++refused_;
    return Error{ErrorCode::kResourceExhausted, "client " + address + " has " + std::to_string(mine) +
                                                    " streams of this kind open, the limit per address (" +
                                                    options_.per_address_key + ")"};
  }
  ++mine;
  ++total_;
  return Slot(this, address);
}

void StreamLimits::close(const std::string& address) {
  std::lock_guard lock(mutex_);
  auto it = by_address_.find(address);
  if (it == by_address_.end()) return;
  if (--it->second == 0) by_address_.erase(it);
  --total_;
}

std::size_t StreamLimits::openStreams() const {
  std::lock_guard lock(mutex_);
  return total_;
}

std::size_t StreamLimits::openStreams(const std::string& address) const {
  std::lock_guard lock(mutex_);
  auto it = by_address_.find(address);
  return it == by_address_.end() ? 0 : it->second;
}

std::uint64_t StreamLimits::refused() const {
  std::lock_guard lock(mutex_);
  return refused_;
}

}  // namespace cvislam::server

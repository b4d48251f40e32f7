// Requests per client: a token bucket per client key (the peer's address and the token it presented), refilled
// at `rate_per_s` up to `burst`. Calls that find their bucket empty are refused with RESOURCE_EXHAUSTED, saying
// the limit and when to retry; nothing else is slowed down. Thread-safe; the clock is passed in (tests step it).
#pragma once

#include <chrono>
#include <cstddef>
#include <mutex>
#include <string>
#include <unordered_map>

#include "common/core/result.hpp"

namespace cvislam::server {

struct RateLimitOptions {
  double rate_per_s = 50.0;         // sustained requests per second per client; 0 turns the limit off
  double burst = 100.0;             // requests a client may make at once after being quiet
  std::size_t max_clients = 10000;  // buckets kept; beyond it the fullest (quietest) ones are forgotten

  [[nodiscard]] Status validate() const;
};

class RateLimiter {
 public:
  using Clock = std::chrono::steady_clock;

  explicit RateLimiter(const RateLimitOptions& options) : options_(options) {}

  // Takes one request from `client`'s bucket at `now`: OK, or RESOURCE_EXHAUSTED naming `what` (the call) and
  // the limit.
  Status admit(const std::string& client, const std::string& what, Clock::time_point now = Clock::now());

  [[nodiscard]] std::uint64_t refused() const;
  [[nodiscard]] std::size_t clients() const;

 private:
  struct Bucket {
    double tokens = 0.0;
    Clock::time_point updated;
  };
  void forgetQuietClients(Clock::time_point now);

  RateLimitOptions options_;
  mutable std::mutex mutex_;
  std::unordered_map<std::string, Bucket> buckets_;
  std::uint64_t refused_ = 0;
};

}  // namespace cvislam::server

#include "server_cloud/access/rate_limiter.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>
#include <utility>
#include <vector>

namespace cvislam::server {

Status RateLimitOptions::validate() const {
  if (!std::isfinite(rate_per_s) || rate_per_s < 0.0) {
    return Error{ErrorCode::kInvalidArgument, "limits.requests_per_s must be >= 0 (0: no limit)"};
  }
  if (rate_per_s > 0.0 && (!std::isfinite(burst) || burst < 1.0)) {
    return Error{ErrorCode::kInvalidArgument, "limits.request_burst must be >= 1"};
  }
  if (max_clients < 1) return Error{ErrorCode::kInvalidArgument, "the rate limiter must keep at least 1 client"};
  return Status::Ok();
}

Status RateLimiter::admit(const std::string& client, const std::string& what, Clock::time_point now) {
  if (options_.rate_per_s <= 0.0) return Status::Ok();
  std::lock_guard lock(mutex_);
  auto it = buckets_.find(client);
  if (it == buckets_.end()) {
    if (buckets_.size() >= options_.max_clients) forgetQuietClients(now);
    it = buckets_.emplace(client, Bucket{options_.burst, now}).first;
  }
  Bucket& b = it->second;
  const double elapsed_s = std::max(0.0, std::chrono::duration<double>(now - b.updated).count());
  b.tokens = std::min(options_.burst, b.tokens + elapsed_s * options_.rate_per_s);
  b.updated = now;
  if (b.tokens >= 1.0) {
    b.tokens -= 1.0;
    return Status::Ok();
  }
  ++refused_;
  const double retry_ms = std::ceil((1.0 - b.tokens) / options_.rate_per_s * 1000.0);
  char limit[160];
  std::snprintf(limit, sizeof(limit), "more than %.4g requests per second (burst %.4g); retry in %.0f ms",
                options_.rate_per_s, options_.burst, retry_ms);
  return Error{ErrorCode::kResourceExhausted,
               what + " refused: client " + client + " made " + limit + " (limits.requests_per_s)"};
}

void RateLimiter::forgetQuietClients(Clock::time_point now) {
  // Buckets that refilled completely carry no state: drop those; if none did, drop the fullest half.
  std::vector<std::pair<double, std::string>> fill;
  fill.reserve(buckets_.size());
  for (const auto& [client, b] : buckets_) {
    const double elapsed_s = std::chrono::duration<double>(now - b.updated).count();
    fill.emplace_back(std::min(options_.burst, b.tokens + elapsed_s * options_.rate_per_s), client);
  }
  std::sort(fill.begin(), fill.end(), [](const auto& a, const auto& b) { return a.first > b.first; });
  const std::size_t drop = std::max<std::size_t>(1, fill.size() / 2);
  for (std::size_t i = 0; i < fill.size(); ++i) {
    if (i >= drop && fill[i].first < options_.burst) break;
    buckets_.erase(fill[i].second);
  }
}

std::uint64_t RateLimiter::refused() const {
  std::lock_guard lock(mutex_);
  return refused_;
}

std::size_t RateLimiter::clients() const {
  std::lock_guard lock(mutex_);
  return buckets_.size();
}

}  // namespace cvislam::server

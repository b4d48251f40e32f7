// Open agent streams, per client address and in all. A stream costs the server a reactor, buffers and a periodic
// tick from the moment it opens, before its Hello says who it is; without a bound, one address that opens
// streams and never speaks could take the server's memory. Plain C++, thread-safe.
#pragma once

#include <cstddef>
#include <cstdint>
#include <mutex>
#include <string>
#include <unordered_map>

#include "common/core/result.hpp"

namespace cvislam::server {

struct StreamLimitOptions {
  std::size_t per_address = 256;  // agents behind one address (a NAT, a test bench) share it
  std::size_t total = 4096;
  // What the limits are called in the config, for the errors.
  const char* per_address_key = "limits.max_streams_per_address";
  const char* total_key = "limits.max_streams";

  [[nodiscard]] Status validate() const;
};

class StreamLimits {
 public:
  explicit StreamLimits(const StreamLimitOptions& options) : options_(options) {}
  StreamLimits(const StreamLimits&) = delete;
  StreamLimits& operator=(const StreamLimits&) = delete;

  // One open stream; it counts until the slot is destroyed (or released).
  class Slot {
   public:
    Slot() = default;
    Slot(Slot&& other) noexcept : limits_(other.limits_), address_(std::move(other.address_)) {
      other.limits_ = nullptr;
    }
    Slot& operator=(Slot&& other) noexcept {
      if (this != &other) {
        release();
        limits_ = other.limits_;
        address_ = std::move(other.address_);
        other.limits_ = nullptr;
      }
      return *this;
    }
    Slot(const Slot&) = delete;
    Slot& operator=(const Slot&) = delete;
    ~Slot() { release(); }
    void release() {
      if (limits_ != nullptr) limits_->close(address_);
      limits_ = nullptr;
    }

   private:
    friend class StreamLimits;
    Slot(StreamLimits* limits, std::string address) : limits_(limits), address_(std::move(address)) {}
    StreamLimits* limits_ = nullptr;
    std::string address_;
  };

  // A slot for a stream from `address`, or RESOURCE_EXHAUSTED naming the limit that is reached.
  Result<Slot> open(const std::string& address);
  [[nodiscard]] std::size_t openStreams() const;
  [[nodiscard]] std::size_t openStreams(const std::string& address) const;
  [[nodiscard]] std::uint64_t refused() const;

 private:
  void close(const std::string& address);

  StreamLimitOptions options_;
  mutable std::mutex mutex_;
  std::unordered_map<std::string, std::size_t> by_address_;
  std::size_t total_ = 0;
  std::uint64_t refused_ = 0;
};

}  // namespace cvislam::server

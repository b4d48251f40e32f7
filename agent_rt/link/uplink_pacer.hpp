// How much the link may have on its way to the server: a window of unacknowledged bytes sized from the rate at
// which the server's acknowledgements show bytes arriving.
//
// Why: gRPC hands a message to the socket as soon as flow control lets it, and a slow radio link then holds seconds
// of data in the sender's buffers. Everything else on the connection waits behind it, the keepalive pings and their
// answers included, so a 0.5 MB first map at 0.5 Mbit/s (8 s on the wire) made both ends declare the connection dead
// and start over, again and again. With at most about `window_s` of data in flight the connection stays answerable,
// a large backlog goes as a train of smaller batches, and what waits stays in the link's store, where newer states
// of the same objects replace older ones instead of queueing behind them.
//
// The rate is estimated like a delivery-rate sampler: when a batch is acknowledged, the bytes acknowledged since it
// was sent over the time since it was sent (so acknowledgements that arrive bunched together do not look like a fast
// link), keeping the largest sample of the last `rate_memory_s` (a sender with little to send measures less than
// the link can carry; the maximum forgets that soon enough). Before the first sample the window is
// `initial_window_bytes`. Fixed-size: no allocation after construction.
#pragma once

#include <array>
#include <chrono>
#include <cstddef>
#include <cstdint>

#include "common/core/result.hpp"

namespace cvislam::agent {

// The smallest batch the link builds (LinkOptions::max_batch_bytes' floor), and so the smallest budget a batch gets.
inline constexpr std::size_t kMinBatchBytes = 16U << 10U;

struct UplinkPacerOptions {
  double window_s = 2.0;  // unacknowledged data in flight, in seconds at the estimated rate
  // Small to begin with: 64 KiB is one second at 0.5 Mbit/s; the first acknowledgements open it to what the link
  // carries (a fast link's doubles with every acknowledgement round, as TCP's slow start does).
  std::size_t min_window_bytes = 32U << 10U;
  std::size_t max_window_bytes = 8U << 20U;
  std::size_t initial_window_bytes = 64U << 10U;
  double rate_memory_s = 10.0;

  [[nodiscard]] Status validate() const;
};

class UplinkPacer {
 public:
  using Clock = std::chrono::steady_clock;
  static constexpr std::size_t kMaxInFlight = 64;  // batches; the link's rate limit keeps far fewer in flight

  explicit UplinkPacer(const UplinkPacerOptions& options) : options_(options) {}

  // A batch of `bytes` went out as `sequence`.
  void onSent(std::uint64_t sequence, std::size_t bytes, Clock::time_point now);
  // The server acknowledged every batch up to `sequence`.
  void onAck(std::uint64_t sequence, Clock::time_point now);
  // A new stream: what was in flight is sent again from the store, so nothing counts as in flight; and the link
  // may not be the one measured (the stream may have broken because it became slower), so the window starts over.
  void onReconnect();

  // Whether another batch may go now, and how big it may be (at most `max_batch_bytes`).
  [[nodiscard]] bool maySend() const;
  [[nodiscard]] std::size_t batchBudget(std::size_t max_batch_bytes) const;

  [[nodiscard]] std::size_t inFlightBytes() const { return in_flight_bytes_; }
  [[nodiscard]] std::size_t windowBytes() const;
  [[nodiscard]] double rateBytesPerS() const;  // 0 before the first sample

 private:
  struct Sent {
    std::uint64_t sequence = 0;
    std::size_t bytes = 0;
    Clock::time_point sent_at;
    std::uint64_t delivered_at_send = 0;  // delivered_ when it went
  };
  struct Sample {
    Clock::time_point t;
    double bytes_per_s = 0.0;
  };

  UplinkPacerOptions options_;
  std::array<Sent, kMaxInFlight> in_flight_{};
  std::size_t in_flight_count_ = 0;
  std::size_t in_flight_bytes_ = 0;
  std::array<Sample, 32> samples_{};
  std::size_t sample_count_ = 0;
  std::size_t sample_next_ = 0;
  std::uint64_t delivered_ = 0;  // bytes acknowledged so far
  bool have_ack_ = false;
};

}  // namespace cvislam::agent

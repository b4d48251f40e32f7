// The bookkeeping of a callback reactor that writes one message at a time and must call Finish() exactly once,
// never while a write is in flight: the agent link's streams and the map service's watches share it. Not
// thread-safe by itself: the reactor calls it under its own lock. Only service/ includes it (gRPC headers).
#pragma once

#include <optional>
#include <utility>

#include <grpcpp/support/status.h>

namespace cvislam::server {

class WriteGate {
 public:
  // A write may start now: none is in flight and the stream is not finishing.
  [[nodiscard]] bool writable() const { return !writing_ && !finishing(); }
  // Finish() was called, or waits for the write in flight.
  [[nodiscard]] bool finishing() const { return finished_ || pending_.has_value(); }

  void writeStarted() { writing_ = true; }
  // The write in flight completed. A finish that waited for it comes back: call Finish() with it now, whether the
  // write went through or not (another finish() would be ignored while it waits, and the stream never end).
  [[nodiscard]] std::optional<grpc::Status> writeDone() {
    writing_ = false;
    if (!pending_) return std::nullopt;
    finished_ = true;
    std::optional<grpc::Status> status = std::move(pending_);
    pending_.reset();
    return status;
  }
  // Asks to end the stream with `status`: it comes back when Finish() is to be called now; nothing when a write
  // is in flight (writeDone() gives it back then) or the stream is finishing already (the first status wins).
  [[nodiscard]] std::optional<grpc::Status> finish(const grpc::Status& status) {
    if (finishing()) return std::nullopt;
    if (writing_) {
      pending_ = status;
      return std::nullopt;
    }
    finished_ = true;
    return status;
  }

 private:
  bool writing_ = false;
  bool finished_ = false;
  std::optional<grpc::Status> pending_;
};

}  // namespace cvislam::server

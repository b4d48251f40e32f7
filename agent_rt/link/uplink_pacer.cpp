#include "agent_rt/link/uplink_pacer.hpp"

#include <algorithm>
#include <cmath>

namespace cvislam::agent {

Status UplinkPacerOptions::validate() const {
  const auto bad = [](const std::string& what) { return Error{ErrorCode::kInvalidArgument, "link: " + what}; };
  if (!std::isfinite(window_s) || !(window_s > 0.0)) return bad("uplink_window_s must be > 0");
  if (min_window_bytes < kMinBatchBytes || max_window_bytes < min_window_bytes ||
      initial_window_bytes < min_window_bytes || initial_window_bytes > max_window_bytes) {
    return bad("the uplink window must satisfy 16 KiB <= min <= initial <= max");
  }
  if (!std::isfinite(rate_memory_s) || !(rate_memory_s > 0.0)) return bad("the rate memory must be > 0 s");
  return Status::Ok();
}

void UplinkPacer::onSent(std::uint64_t sequence, std::size_t bytes, Clock::time_point now) {
  if (in_flight_count_ == kMaxInFlight) return;  // maySend() said no; counted nowhere rather than overflow
  in_flight_[in_flight_count_++] = Sent{sequence, bytes, now, delivered_};
  in_flight_bytes_ += bytes;
}

void UplinkPacer::onAck(std::uint64_t sequence, Clock::time_point now) {
  std::size_t delivered = 0;
  std::size_t kept = 0;
  bool any = false;
  Sent newest{};  // the newest batch this acknowledgement covers
  for (std::size_t i = 0; i < in_flight_count_; ++i) {
    if (in_flight_[i].sequence <= sequence) {
      delivered += in_flight_[i].bytes;
      if (!any || in_flight_[i].sequence > newest.sequence) newest = in_flight_[i];
      any = true;
    } else {
      in_flight_[kept++] = in_flight_[i];
    }
  }
  in_flight_count_ = kept;
  in_flight_bytes_ -= std::min(in_flight_bytes_, delivered);
  if (!any) return;
  delivered_ += delivered;
  const double elapsed_s = std::max(0.01, std::chrono::duration<double>(now - newest.sent_at).count());
  samples_[sample_next_] = Sample{now, static_cast<double>(delivered_ - newest.delivered_at_send) / elapsed_s};
  sample_next_ = (sample_next_ + 1) % samples_.size();
  sample_count_ = std::min(sample_count_ + 1, samples_.size());
  have_ack_ = true;
}

void UplinkPacer::onReconnect() {
  in_flight_count_ = 0;
  in_flight_bytes_ = 0;
  sample_count_ = 0;
  sample_next_ = 0;
  have_ack_ = false;
}

double UplinkPacer::rateBytesPerS() const {
  if (sample_count_ == 0) return 0.0;
  const std::size_t newest = (sample_next_ + samples_.size() - 1) % samples_.size();
  const Clock::time_point since = samples_[newest].t - std::chrono::duration_cast<Clock::duration>(
                                                           std::chrono::duration<double>(options_.rate_memory_s));
  double best = 0.0;
  for (std::size_t i = 0; i < sample_count_; ++i) {
    if (samples_[i].t >= since) best = std::max(best, samples_[i].bytes_per_s);
  }
  return best;
}

std::size_t UplinkPacer::windowBytes() const {
  if (!have_ack_) return options_.initial_window_bytes;
  const double wanted = rateBytesPerS() * options_.window_s;
  return std::clamp(static_cast<std::size_t>(wanted), options_.min_window_bytes, options_.max_window_bytes);
}

bool UplinkPacer::maySend() const {
  return in_flight_count_ < kMaxInFlight && in_flight_bytes_ < windowBytes();
}

std::size_t UplinkPacer::batchBudget(std::size_t max_batch_bytes) const {
  const std::size_t window = windowBytes();
  const std::size_t room = window > in_flight_bytes_ ? window - in_flight_bytes_ : 0;
  return std::min(max_batch_bytes, std::max(kMinBatchBytes, room));
}

}  // namespace cvislam::agent

// Per-stage latency samples of the agent, recorded into storage reserved at start-up (a full recorder
// counts what it drops instead of growing), summarised as p50/p90/p99/max, printed as a table and written
// as JSON. Each thread owns its own recorders; they are read after the threads have joined.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "common/core/percentile.hpp"

namespace cvislam::agent {

class LatencyRecorder {
 public:
  LatencyRecorder(std::string name, std::size_t capacity) : name_(std::move(name)) { samples_ms_.reserve(capacity); }

  void add(std::int64_t duration_ns) {
    if (samples_ms_.size() < samples_ms_.capacity()) {
      samples_ms_.push_back(static_cast<double>(duration_ns) * 1e-6);
    } else {
      ++dropped_;
    }
  }
  [[nodiscard]] const std::string& name() const { return name_; }
  [[nodiscard]] const std::vector<double>& samplesMs() const { return samples_ms_; }
  [[nodiscard]] std::uint64_t dropped() const { return dropped_; }

 private:
  std::string name_;
  std::vector<double> samples_ms_;
  std::uint64_t dropped_ = 0;
};

// One stage's samples, in milliseconds.
struct StageSummary {
  std::string name;
  SampleSummary ms;
};

// Nearest-rank percentiles of the recorded samples.
StageSummary summarise(const LatencyRecorder& recorder);

std::string formatLatencyTable(const std::vector<StageSummary>& stages);
std::string latencyJson(const std::vector<StageSummary>& stages);

}  // namespace cvislam::agent

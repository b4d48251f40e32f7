// Mapping's deltas handed to a link thread, and the link's downlink messages handed back to mapping, in tests
// and benchmarks (the agent itself uses iceoryx).
#pragma once

#include <cstddef>
#include <functional>
#include <memory>
#include <mutex>
#include <vector>

#include "agent_rt/link/link.hpp"
#include "agent_rt/runtime/messages.hpp"

namespace cvislam::agent::test {

// Mapping's deltas handed to a link thread: a bounded queue of preallocated messages (the agent uses iceoryx).
class DeltaQueue final : public DeltaSource {
 public:
  explicit DeltaQueue(std::size_t capacity) {
    for (std::size_t i = 0; i < capacity; ++i) slots_.push_back(std::make_unique<MapDeltaMessage>());
  }
  // Copies the delta in; false (and counted) when the link has fallen `capacity` deltas behind.
  bool push(const MapDeltaMessage& delta) {
    std::lock_guard lock(mutex_);
    if (count_ == slots_.size()) {
      ++dropped_;
      return false;
    }
    *slots_[(head_ + count_) % slots_.size()] = delta;
    ++count_;
    return true;
  }
  const MapDeltaMessage* next() override {
    if (on_poll) on_poll();  // on the link thread, every iteration of its loop
    std::lock_guard lock(mutex_);
    return count_ == 0 ? nullptr : slots_[head_].get();
  }
  void release() override {
    std::lock_guard lock(mutex_);
    head_ = (head_ + 1) % slots_.size();
    --count_;
  }
  std::function<void()> on_poll;  // set before the link thread starts

  [[nodiscard]] std::size_t dropped() const {
    std::lock_guard lock(mutex_);
    return dropped_;
  }

 private:
  mutable std::mutex mutex_;
  std::vector<std::unique_ptr<MapDeltaMessage>> slots_;
  std::size_t head_ = 0;
  std::size_t count_ = 0;
  std::size_t dropped_ = 0;
};

// The link's downlink messages handed to mapping: a bounded queue of preallocated messages, filled on the link
// thread (loan, publish) and drained on mapping's (take, done).
class AnchorQueue final : public AnchorSink {
 public:
  explicit AnchorQueue(std::size_t capacity) {
    for (std::size_t i = 0; i < capacity; ++i) slots_.push_back(std::make_unique<AnchorMessage>());
  }
  AnchorMessage* loan() override {
    std::lock_guard lock(mutex_);
    if (count_ == slots_.size()) {
      ++dropped_;
      return nullptr;
    }
    return slots_[(head_ + count_) % slots_.size()].get();
  }
  void publish() override {
    std::lock_guard lock(mutex_);
    ++count_;
  }
  void discard() override {}
  // The oldest message waiting, or nullptr; it stays valid until done().
  const AnchorMessage* take() {
    std::lock_guard lock(mutex_);
    return count_ == 0 ? nullptr : slots_[head_].get();
  }
  void done() {
    std::lock_guard lock(mutex_);
    head_ = (head_ + 1) % slots_.size();
    --count_;
  }
  [[nodiscard]] std::size_t dropped() const {
    std::lock_guard lock(mutex_);
    return dropped_;
  }

 private:
  mutable std::mutex mutex_;
  std::vector<std::unique_ptr<AnchorMessage>> slots_;
  std::size_t head_ = 0;
  std::size_t count_ = 0;
  std::size_t dropped_ = 0;
};

}  // namespace cvislam::agent::test

// Mapping's deltas handed to a link thread, and the link's downlink messages handed back to mapping, in tests
// and benchmarks (the agent itself uses iceoryx).
#pragma once

#include <cstddef>
#include <functional>
#include <memory>
#include <mutex>
#include <vector>

#include "agent_rt/link/link.hpp"
#include "agent_rt/messages/messages.hpp"

namespace cvislam::agent::test {

// A bounded queue of preallocated messages between two threads: the producer fills the slot back() gives
// (nullptr, counted as dropped, when the queue is full) and commits it; the consumer reads front() and pops it.
template <typename Message>
class SlotRing {
 public:
  explicit SlotRing(std::size_t capacity) {
    for (std::size_t i = 0; i < capacity; ++i) slots_.push_back(std::make_unique<Message>());
  }
  Message* back() {
    std::lock_guard lock(mutex_);
    if (count_ == slots_.size()) {
      ++dropped_;
      return nullptr;
    }
    return slots_[(head_ + count_) % slots_.size()].get();
  }
  void commit() {
    std::lock_guard lock(mutex_);
    ++count_;
  }
  Message* front() {
    std::lock_guard lock(mutex_);
    return count_ == 0 ? nullptr : slots_[head_].get();
  }
  void pop() {
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
  std::vector<std::unique_ptr<Message>> slots_;
  std::size_t head_ = 0;
  std::size_t count_ = 0;
  std::size_t dropped_ = 0;
};

// Mapping's deltas handed to a link thread (the agent uses iceoryx).
class DeltaQueue final : public DeltaSource {
 public:
  explicit DeltaQueue(std::size_t capacity) : ring_(capacity) {}
  // Copies the delta in; false (and counted) when the link has fallen `capacity` deltas behind.
  bool push(const MapDeltaMessage& delta) {
    MapDeltaMessage* slot = ring_.back();
    if (slot == nullptr) return false;
    *slot = delta;
    ring_.commit();
    return true;
  }
  const MapDeltaMessage* next() override {
    if (on_poll) on_poll();  // on the link thread, every iteration of its loop
    return ring_.front();
  }
  void release() override { ring_.pop(); }
  std::function<void()> on_poll;  // set before the link thread starts
  [[nodiscard]] std::size_t dropped() const { return ring_.dropped(); }

 private:
  SlotRing<MapDeltaMessage> ring_;
};

// The link's downlink messages handed to mapping: filled on the link thread (loan, publish), drained on
// mapping's (take, done).
class AnchorQueue final : public AnchorSink {
 public:
  explicit AnchorQueue(std::size_t capacity) : ring_(capacity) {}
  AnchorMessage* loan() override { return ring_.back(); }
  void publish() override { ring_.commit(); }
  void discard() override {}
  // The oldest message waiting, or nullptr; it stays valid until done().
  const AnchorMessage* take() { return ring_.front(); }
  void done() { ring_.pop(); }
  [[nodiscard]] std::size_t dropped() const { return ring_.dropped(); }

 private:
  SlotRing<AnchorMessage> ring_;
};

}  // namespace cvislam::agent::test

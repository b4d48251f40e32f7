// The frames the loader thread reads ahead for tracking: a ring of slots whose image buffers are allocated at
// start-up, one producer and one consumer. Each side waits on the other's event (a futex through
// std::atomic::wait), not on a timer: tracking takes a frame the moment it is loaded, the loader refills a slot the
// moment tracking frees it, and neither wakes while there is nothing to do.
#pragma once

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

namespace cvislam::agent {

class FrameRing {
 public:
  struct Slot {
    std::vector<std::uint8_t> left;
    std::vector<std::uint8_t> right;
    std::int64_t t_ns = 0;
    std::int64_t captured_steady_ns = 0;  // when a pushed frame came in (PushFeed)
    std::size_t frame = 0;
    bool ok = true;
    std::string error;
  };

  FrameRing(int size, std::size_t pixels, bool stereo) : slots_(static_cast<std::size_t>(size)) {
    for (Slot& s : slots_) {
      s.left.resize(pixels);
      if (stereo) s.right.resize(pixels);
      s.error.reserve(256);
    }
  }

  // Producer: a free slot to fill, waiting until tracking frees one; nullptr once the ring is closed.
  Slot* waitForFreeSlot() {
    while (true) {
      const std::uint32_t seen = events_.load(std::memory_order_acquire);
      if (closed_.load(std::memory_order_acquire)) return nullptr;
      const std::size_t head = head_.load(std::memory_order_relaxed);
      if (head - tail_.load(std::memory_order_acquire) < slots_.size()) return &slots_[head % slots_.size()];
      events_.wait(seen, std::memory_order_acquire);
    }
  }
  // Producer that must not wait: a free slot, or nullptr when the ring is full or closed.
  Slot* tryFreeSlot() {
    if (closed_.load(std::memory_order_acquire)) return nullptr;
    const std::size_t head = head_.load(std::memory_order_relaxed);
    if (head - tail_.load(std::memory_order_acquire) < slots_.size()) return &slots_[head % slots_.size()];
    return nullptr;
  }
  void produced() {
    head_.fetch_add(1, std::memory_order_release);
    signal();
  }
  // Consumer: the oldest loaded frame, waiting until the loader has one; nullptr when the loader has finished
  // and every frame was taken, or the ring is closed.
  Slot* waitForFrame() {
    while (true) {
      const std::uint32_t seen = events_.load(std::memory_order_acquire);
      const std::size_t tail = tail_.load(std::memory_order_relaxed);
      if (tail != head_.load(std::memory_order_acquire)) return &slots_[tail % slots_.size()];
      if (finished_.load(std::memory_order_acquire) || closed_.load(std::memory_order_acquire)) return nullptr;
      events_.wait(seen, std::memory_order_acquire);
    }
  }
  // Consumer that must not wait: the oldest loaded frame, or nullptr when there is none yet.
  Slot* tryFrame() {
    const std::size_t tail = tail_.load(std::memory_order_relaxed);
    if (tail != head_.load(std::memory_order_acquire)) return &slots_[tail % slots_.size()];
    return nullptr;
  }
  // The producer has finished (or the ring was closed) and every frame was taken.
  [[nodiscard]] bool drained() const {
    return (finished_.load(std::memory_order_acquire) || closed_.load(std::memory_order_acquire)) &&
           tail_.load(std::memory_order_acquire) == head_.load(std::memory_order_acquire);
  }
  void consumed() {
    tail_.fetch_add(1, std::memory_order_release);
    signal();
  }
  // The loader has no more frames.
  void finish() {
    finished_.store(true, std::memory_order_release);
    signal();
  }
  // Tracking stops early: a loader waiting for a free slot returns.
  void close() {
    closed_.store(true, std::memory_order_release);
    signal();
  }

 private:
  // Every change bumps the event counter, so a waiter that saw the old count never misses the change.
  void signal() {
    events_.fetch_add(1, std::memory_order_acq_rel);
    events_.notify_all();
  }

  std::vector<Slot> slots_;
  std::atomic<std::size_t> head_{0};
  std::atomic<std::size_t> tail_{0};
  std::atomic<bool> finished_{false};
  std::atomic<bool> closed_{false};
  std::atomic<std::uint32_t> events_{0};
};

}  // namespace cvislam::agent

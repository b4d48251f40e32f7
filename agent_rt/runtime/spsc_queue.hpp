// A bounded queue between one producer thread and one consumer thread, its storage allocated at construction: push
// and pop never allocate, lock or wait; push fails when the queue is full and pop when it is empty.
#pragma once

#include <atomic>
#include <cstddef>
#include <vector>

namespace cvislam::agent {

template <typename T>
class SpscQueue {
 public:
  explicit SpscQueue(std::size_t capacity) : slots_(capacity > 0 ? capacity : 1) {}

  bool push(const T& value) {
    const std::size_t head = head_.load(std::memory_order_relaxed);
    if (head - tail_.load(std::memory_order_acquire) >= slots_.size()) return false;
    slots_[head % slots_.size()] = value;
    head_.store(head + 1, std::memory_order_release);
    return true;
  }
  bool pop(T& value) {
    const std::size_t tail = tail_.load(std::memory_order_relaxed);
    if (tail == head_.load(std::memory_order_acquire)) return false;
    value = slots_[tail % slots_.size()];
    tail_.store(tail + 1, std::memory_order_release);
    return true;
  }

 private:
  std::vector<T> slots_;
  std::atomic<std::size_t> head_{0};
  std::atomic<std::size_t> tail_{0};
};

}  // namespace cvislam::agent

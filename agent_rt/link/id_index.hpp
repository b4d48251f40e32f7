// IdIndex: id counter -> pool handle, in fixed memory (open addressing, linear probing, deletion by backward
// shift, so no tombstones build up). For the link's store, which must find objects by id without allocating.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>

#include "agent_rt/map/fixed_pool.hpp"

namespace cvislam::agent {

template <std::size_t Capacity>
class IdIndex {
  static constexpr std::size_t slotsFor(std::size_t n) {
    std::size_t s = 16;
    while (s < 2 * n) s *= 2;
    return s;
  }
  static constexpr std::size_t kSlots = slotsFor(Capacity);
  static constexpr std::size_t kMask = kSlots - 1;

 public:
  [[nodiscard]] std::size_t size() const { return size_; }

  // False when the key is present already or the index holds Capacity keys.
  bool insert(std::uint32_t key, PoolHandle handle) {
    if (size_ >= Capacity) return false;
    std::size_t i = home(key);
    while (slots_[i].used) {
      if (slots_[i].key == key) return false;
      i = (i + 1) & kMask;
    }
    slots_[i] = {key, handle, true};
    ++size_;
    return true;
  }

  [[nodiscard]] const PoolHandle* find(std::uint32_t key) const {
    for (std::size_t i = home(key); slots_[i].used; i = (i + 1) & kMask) {
      if (slots_[i].key == key) return &slots_[i].handle;
    }
    return nullptr;
  }

  bool erase(std::uint32_t key) {
    std::size_t i = home(key);
    while (slots_[i].used && slots_[i].key != key) i = (i + 1) & kMask;
    if (!slots_[i].used) return false;
    // Shift later members of the probe run back over the hole when that keeps them reachable.
    std::size_t hole = i;
    for (std::size_t j = (i + 1) & kMask; slots_[j].used; j = (j + 1) & kMask) {
      const std::size_t want = home(slots_[j].key);
      const bool reachable_from_hole = ((j - want) & kMask) >= ((j - hole) & kMask);
      if (reachable_from_hole) {
        slots_[hole] = slots_[j];
        hole = j;
      }
    }
    slots_[hole].used = false;
    --size_;
    return true;
  }

  void clear() {
    for (auto& s : slots_) s.used = false;
    size_ = 0;
  }

 private:
  struct Slot {
    std::uint32_t key = 0;
    PoolHandle handle;
    bool used = false;
  };
  static std::size_t home(std::uint32_t key) {
    return static_cast<std::size_t>((static_cast<std::uint64_t>(key) * 0x9E3779B97F4A7C15ULL) >> 32U) & kMask;
  }

  std::array<Slot, kSlots> slots_{};
  std::size_t size_ = 0;
};

}  // namespace cvislam::agent

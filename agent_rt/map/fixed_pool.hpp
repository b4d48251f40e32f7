// FixedPool<T, Capacity>: the storage of the agent's local map. Every slot is allocated once, with the pool;
// insert() reports "full" instead of growing, and nothing allocates afterwards.
//
// Objects are addressed by a Handle: a slot index plus the slot's generation at insertion. Erasing bumps the
// generation, so a stale handle (to an object since culled, its slot perhaps reused) is detected by get()
// returning nullptr instead of silently aliasing the new object. Iteration visits live slots in index order.
//
// Not thread-safe: a pool belongs to one thread (the mapping thread owns the local map); other threads see
// it only through messages.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <optional>
#include <type_traits>

namespace cvislam::agent {

// A default-constructed handle (generation 0) refers to nothing.
struct PoolHandle {
  std::uint32_t index = 0;
  std::uint32_t generation = 0;
  friend bool operator==(const PoolHandle&, const PoolHandle&) = default;
};

template <typename T, std::size_t Capacity>
class FixedPool {
  static_assert(Capacity > 0 && Capacity < (std::size_t{1} << 31), "FixedPool capacity out of range");
  static_assert(std::is_default_constructible_v<T>, "FixedPool slots are constructed once, up front");

 public:
  using Handle = PoolHandle;

  FixedPool() noexcept {
    generation_.fill(1);  // generation 0 is never issued, so a default PoolHandle{} is never valid
    for (std::size_t i = 0; i < Capacity; ++i) {
      free_[i] = static_cast<std::uint32_t>(Capacity - 1 - i);  // pop() hands out index 0 first
    }
  }

  [[nodiscard]] static constexpr std::size_t capacity() { return Capacity; }
  [[nodiscard]] std::size_t size() const { return Capacity - free_count_; }
  [[nodiscard]] bool empty() const { return free_count_ == Capacity; }
  [[nodiscard]] bool full() const { return free_count_ == 0; }

  // Copies `value` into a free slot; nothing when the pool is full (the caller's cull policy decides).
  [[nodiscard]] std::optional<Handle> insert(const T& value) noexcept(std::is_nothrow_copy_assignable_v<T>) {
    if (full()) return std::nullopt;
    const std::uint32_t index = free_[--free_count_];
    slots_[index] = value;
    live_[index] = true;
    return Handle{index, generation_[index]};
  }

  // Takes a free slot without copying into it (for large objects the caller fills in place); its contents are
  // whatever the slot last held. Nothing when the pool is full.
  [[nodiscard]] std::optional<Handle> acquire() noexcept {
    if (full()) return std::nullopt;
    const std::uint32_t index = free_[--free_count_];
    live_[index] = true;
    return Handle{index, generation_[index]};
  }

  // Frees the slot; false for a stale or invalid handle.
  bool erase(Handle handle) noexcept {
    if (!valid(handle)) return false;
    live_[handle.index] = false;
    ++generation_[handle.index];
    free_[free_count_++] = handle.index;
    return true;
  }

  [[nodiscard]] bool valid(Handle handle) const noexcept {
    return handle.index < Capacity && live_[handle.index] && generation_[handle.index] == handle.generation;
  }
  [[nodiscard]] T* get(Handle handle) noexcept { return valid(handle) ? &slots_[handle.index] : nullptr; }
  [[nodiscard]] const T* get(Handle handle) const noexcept { return valid(handle) ? &slots_[handle.index] : nullptr; }

  // Calls f(handle, value) for every live object, in slot order.
  template <typename F>
  void forEach(F&& f) {
    for (std::uint32_t i = 0; i < Capacity; ++i) {
      if (live_[i]) f(Handle{i, generation_[i]}, slots_[i]);
    }
  }
  template <typename F>
  void forEach(F&& f) const {
    for (std::uint32_t i = 0; i < Capacity; ++i) {
      if (live_[i]) f(Handle{i, generation_[i]}, slots_[i]);
    }
  }

 private:
  std::array<T, Capacity> slots_{};
  std::array<std::uint32_t, Capacity> generation_{};
  std::array<bool, Capacity> live_{};
  std::array<std::uint32_t, Capacity> free_{};  // a stack of free slot indices
  std::size_t free_count_ = Capacity;
};

}  // namespace cvislam::agent

// Synchronized<T>: a value and the lock that guards it, in one object, so that the only way to the value is
// through the lock. No mutex is ever a public member next to the data it guards (ORB-SLAM3's Map.h is the
// counter-example), and "which lock guards this?" has one answer.
//
//   Synchronized<Stats> stats;
//   stats.write()->frames += 1;              // exclusive for this statement
//   { auto s = stats.read(); use(s->frames); }  // shared while `s` lives
//   stats.withWrite([](Stats& s) { ... });
//
// Keep the locked sections short: nothing slow (I/O, optimisation, network) runs under a lock.
#pragma once

#include <mutex>
#include <optional>
#include <shared_mutex>
#include <utility>

namespace cvislam {

template <typename T>
class Synchronized {
 public:
  template <typename Lock, typename Pointee>
  class Locked {
   public:
    Locked(Pointee* value, Lock lock) : value_(value), lock_(std::move(lock)) {}
    Pointee* operator->() const { return value_; }
    Pointee& operator*() const { return *value_; }

   private:
    Pointee* value_;
    Lock lock_;
  };
  using WriteLocked = Locked<std::unique_lock<std::shared_mutex>, T>;
  using ReadLocked = Locked<std::shared_lock<std::shared_mutex>, const T>;

  Synchronized() = default;
  template <typename... Args>
  explicit Synchronized(std::in_place_t /*tag*/, Args&&... args) : value_(std::forward<Args>(args)...) {}
  Synchronized(const Synchronized&) = delete;
  Synchronized& operator=(const Synchronized&) = delete;

  [[nodiscard]] WriteLocked write() { return WriteLocked(&value_, std::unique_lock(mutex_)); }
  [[nodiscard]] ReadLocked read() const { return ReadLocked(&value_, std::shared_lock(mutex_)); }
  // The same when it can be had at once, else nothing: for a reader that must never wait on a slow writer.
  [[nodiscard]] std::optional<ReadLocked> tryRead() const {
    std::shared_lock lock(mutex_, std::try_to_lock);
    if (!lock.owns_lock()) return std::nullopt;
    return ReadLocked(&value_, std::move(lock));
  }

  template <typename F>
  decltype(auto) withWrite(F&& f) {
    std::unique_lock lock(mutex_);
    return std::forward<F>(f)(value_);
  }
  template <typename F>
  decltype(auto) withRead(F&& f) const {
    std::shared_lock lock(mutex_);
    return std::forward<F>(f)(std::as_const(value_));
  }

 private:
  mutable std::shared_mutex mutex_;
  T value_;
};

}  // namespace cvislam

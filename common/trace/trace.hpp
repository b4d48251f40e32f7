// Spans and instants of a process's threads, written as Chrome Trace Event JSON (Perfetto's UI and
// chrome://tracing open it).
//
// Each traced thread records into a ring of events reserved when it binds to the process's Session, so recording
// never allocates and never takes a lock: the hot paths of the agent stay as they are. When a ring is full the
// oldest events give way (counted), as in a flight recorder. Times are on the steady clock, which every process of
// a machine shares; the trace also states the wall clock's offset to it, so that traces of several machines can
// be joined (cvislam_trace estimates what is left from the link's own messages).
//
// Without a session, or on a thread that did not bind, every call here is a thread-local load and a branch. Built
// with -DCVISLAM_LTTNG=ON, every event also fires the LTTng-UST tracepoint cvislam:span when an LTTng session
// listens (common/trace/lttng_tracepoints.h), with or without a session of its own.
#pragma once

#include <array>
#include <atomic>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <initializer_list>
#include <memory>
#include <mutex>
#include <string>
#include <string_view>
#include <vector>

#include "common/core/result.hpp"

namespace cvislam::trace {

// A key (a literal: only the pointer is kept) and an integer, e.g. {"keyframe", 42}.
struct Arg {
  const char* key = nullptr;
  std::int64_t value = 0;
};
inline constexpr std::size_t kMaxArgs = 5;

struct Event {
  const char* name = nullptr;     // a literal: only the pointer is kept
  std::int64_t begin_ns = 0;      // steady clock
  std::int64_t duration_ns = -1;  // -1: an instant
  std::array<Arg, kMaxArgs> args{};
};

// One thread's events: written by that thread only, read once it is quiet.
class ThreadTrack {
 public:
  ThreadTrack(std::string name, std::int64_t tid, std::size_t capacity);

  void record(const Event& event) noexcept {
    const std::uint64_t n = written_.load(std::memory_order_relaxed);
    slots_[n % capacity_] = event;
    written_.store(n + 1, std::memory_order_release);
  }

  [[nodiscard]] const std::string& name() const { return name_; }
  [[nodiscard]] std::int64_t tid() const { return tid_; }
  [[nodiscard]] std::uint64_t written() const { return written_.load(std::memory_order_acquire); }
  [[nodiscard]] std::uint64_t overwritten() const;
  // The events still held, oldest first.
  [[nodiscard]] std::vector<Event> events() const;

 private:
  std::string name_;
  std::int64_t tid_;
  std::size_t capacity_;
  std::unique_ptr<Event[]> slots_;
  std::atomic<std::uint64_t> written_{0};
};

struct SessionOptions {
  std::string process_name;  // e.g. "agent 3", "server"; Perfetto titles the process's tracks with it
  std::int64_t agent = -1;   // an agent's id, for joining its trace with the server's; -1 for the server
  std::string mission;       // an agent's mission; the server's events name theirs by missionKey()
  std::size_t events_per_thread = std::size_t{1} << 16;
  // Threads that record without binding first (a gRPC server's pool) get a track on their first event, named
  // after their thread id. Off, they record nothing.
  bool trace_unbound_threads = false;

  [[nodiscard]] Status validate() const;
};

struct SessionTotals {
  std::size_t threads = 0;
  std::uint64_t events = 0;       // recorded, the overwritten ones included
  std::uint64_t overwritten = 0;  // given way to newer ones in a full ring
};

// The process's trace: at most one at a time. Constructing it makes it the one threads bind to; destroying it
// ends every binding. It must outlive the threads that record into it, or those threads must have bound to a
// later session (or none) first.
class Session {
 public:
  explicit Session(SessionOptions options);
  ~Session();
  Session(const Session&) = delete;
  Session& operator=(const Session&) = delete;

  // The calling thread records into a new track of this session from now on. Allocates the track's ring.
  ThreadTrack& bindCurrentThread(std::string name);

  // Chrome Trace Event JSON, written once the traced threads are quiet (joined, or idle after a shutdown).
  [[nodiscard]] Status writeChromeJson(const std::filesystem::path& file) const;
  [[nodiscard]] std::string chromeJson() const;
  [[nodiscard]] SessionTotals totals() const;
  [[nodiscard]] const SessionOptions& options() const { return options_; }

 private:
  SessionOptions options_;
  std::int64_t unix_minus_steady_ns_;
  mutable std::mutex tracks_mutex_;  // registration only; recording takes no lock
  std::vector<std::unique_ptr<ThreadTrack>> tracks_;
};

// The calling thread records into a track named `name` of the current session; without one, nothing happens.
void bindThread(const char* name);
// The calling thread's track, or null when it does not record (binding an unbound thread first if the session
// traces those).
ThreadTrack* currentTrack() noexcept;
std::int64_t nowNs() noexcept;
// A mission's name as an event argument: 52 bits of its FNV-1a hash (exact as a JSON number in any reader).
std::int64_t missionKey(std::string_view mission) noexcept;

// An event that has happened at once, e.g. a message received.
void instant(const char* name, std::initializer_list<Arg> args = {}) noexcept;
// A span timed by the caller (both on the steady clock).
void complete(const char* name, std::int64_t begin_ns, std::int64_t end_ns,
              std::initializer_list<Arg> args = {}) noexcept;

// A span from construction to destruction on the calling thread.
class Span {
 public:
  explicit Span(const char* name, std::initializer_list<Arg> args = {}) noexcept;
  ~Span();
  Span(const Span&) = delete;
  Span& operator=(const Span&) = delete;

  // Sets an argument known only later (e.g. the sequence a batch got); a key beyond kMaxArgs is ignored.
  void set(const char* key, std::int64_t value) noexcept;
  // Recorded: into the thread's ring, or (CVISLAM_LTTNG) to an LTTng session that listens.
  [[nodiscard]] bool active() const { return track_ != nullptr || lttng_; }

 private:
  ThreadTrack* track_;
  bool lttng_;
  Event event_;
};

}  // namespace cvislam::trace

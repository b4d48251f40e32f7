#include "common/trace/trace.hpp"

#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cinttypes>
#include <cstdio>
#include <fstream>

#include "common/core/hash.hpp"
#include "common/core/steady_clock.hpp"

#ifdef CVISLAM_LTTNG
#include "common/trace/lttng_tracepoints.h"
#endif

namespace cvislam::trace {

namespace {

// The session threads bind to, and a count of sessions made so far: a thread's binding holds the count it was
// made under, so a binding to a session that has gone is seen as none without touching the old track.
std::atomic<Session*> g_session{nullptr};
std::atomic<std::uint64_t> g_generation{0};

struct Binding {
  ThreadTrack* track = nullptr;
  std::uint64_t generation = 0;
  bool tried_unbound = false;  // looked once for an unbound-thread track under `generation`
};
thread_local Binding t_binding;

std::int64_t threadId() {
  return static_cast<std::int64_t>(::syscall(SYS_gettid));
}

// An LTTng session wants cvislam:span (always false without CVISLAM_LTTNG).
bool lttngEnabled() noexcept {
#ifdef CVISLAM_LTTNG
  return lttng_ust_tracepoint_enabled(cvislam, span);
#else
  return false;
#endif
}

void fireLttng([[maybe_unused]] const Event& e) noexcept {
#ifdef CVISLAM_LTTNG
  // The keys joined by commas into a buffer on the stack, the values beside them.
  char keys[128];
  std::int64_t values[kMaxArgs];
  unsigned int count = 0;
  std::size_t used = 0;
  keys[0] = '\0';
  for (const Arg& a : e.args) {
    if (a.key == nullptr) continue;
    const int n = std::snprintf(keys + used, sizeof(keys) - used, "%s%s", count == 0 ? "" : ",", a.key);
    if (n < 0 || used + static_cast<std::size_t>(n) >= sizeof(keys)) break;
    used += static_cast<std::size_t>(n);
    values[count++] = a.value;
  }
  lttng_ust_do_tracepoint(cvislam, span, e.name, e.begin_ns, e.duration_ns, keys, values, count);
#endif
}

// Into the thread's ring and to LTTng, whichever wants it.
void deliver(ThreadTrack* track, bool lttng, const Event& e) noexcept {
  if (track != nullptr) track->record(e);
  if (lttng) fireLttng(e);
}

void fillArgs(Event& event, std::initializer_list<Arg> args) {
  std::size_t i = 0;
  for (const Arg& a : args) {
    if (i == kMaxArgs) break;
    event.args[i++] = a;
  }
}

// Names come from this code base; still, a thread or process name is escaped so the JSON stays valid.
void appendJsonString(std::string& out, const std::string& text) {
  out += '"';
  for (const char c : text) {
    if (c == '"' || c == '\\') {
      out += '\\';
      out += c;
    } else if (static_cast<unsigned char>(c) < 0x20) {
      out += ' ';
    } else {
      out += c;
    }
  }
  out += '"';
}

// Microseconds with nanosecond digits, as Chrome's format takes them.
void appendMicros(std::string& out, std::int64_t ns) {
  char text[40];
  const std::int64_t whole = ns / 1000;
  const std::int64_t frac = ns % 1000;
  if (ns < 0 && frac != 0) {
    std::snprintf(text, sizeof(text), "-%" PRId64 ".%03" PRId64, -whole, -frac);
  } else {
    std::snprintf(text, sizeof(text), "%" PRId64 ".%03" PRId64, whole, frac);
  }
  out += text;
}

void appendEvent(std::string& out, const Event& e, std::int64_t pid, std::int64_t tid) {
  out += R"({"ph":")";
  out += e.duration_ns >= 0 ? 'X' : 'i';
  out += R"(","name":)";
  appendJsonString(out, e.name != nullptr ? e.name : "?");
  out += R"(,"cat":"cvislam","ts":)";
  appendMicros(out, e.begin_ns);
  if (e.duration_ns >= 0) {
    out += R"(,"dur":)";
    appendMicros(out, e.duration_ns);
  } else {
    out += R"(,"s":"t")";
  }
  out += ",\"pid\":" + std::to_string(pid) + ",\"tid\":" + std::to_string(tid) + ",\"args\":{";
  bool first = true;
  for (const Arg& a : e.args) {
    if (a.key == nullptr) continue;
    if (!first) out += ',';
    first = false;
    appendJsonString(out, a.key);
    out += ':' + std::to_string(a.value);
  }
  out += "}}";
}

}  // namespace

ThreadTrack::ThreadTrack(std::string name, std::int64_t tid, std::size_t capacity)
    : name_(std::move(name)), tid_(tid), capacity_(std::max<std::size_t>(capacity, 1)), slots_(new Event[capacity_]) {}

std::uint64_t ThreadTrack::overwritten() const {
  const std::uint64_t n = written();
  return n > capacity_ ? n - capacity_ : 0;
}

std::vector<Event> ThreadTrack::events() const {
  const std::uint64_t n = written();
  const std::uint64_t first = overwritten();
  std::vector<Event> out;
  out.reserve(static_cast<std::size_t>(n - first));
  for (std::uint64_t i = first; i < n; ++i) out.push_back(slots_[i % capacity_]);
  return out;
}

Status SessionOptions::validate() const {
  if (process_name.empty()) return Error{ErrorCode::kInvalidArgument, "a trace needs a process name"};
  if (events_per_thread < 16 || events_per_thread > (std::size_t{1} << 24)) {
    return Error{ErrorCode::kInvalidArgument,
                 "trace events per thread must be in [16, 16777216]; got " + std::to_string(events_per_thread)};
  }
  return Status::Ok();
}

Session::Session(SessionOptions options)
    : options_(std::move(options)),
      unix_minus_steady_ns_(
          std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::system_clock::now().time_since_epoch())
              .count() -
          steadyNowNs()) {
  g_session.store(this);
  g_generation.fetch_add(1);
}

Session::~Session() {
  Session* self = this;
  g_session.compare_exchange_strong(self, nullptr);
  g_generation.fetch_add(1);
}

ThreadTrack& Session::bindCurrentThread(std::string name) {
  auto track = std::make_unique<ThreadTrack>(std::move(name), threadId(), options_.events_per_thread);
  ThreadTrack* raw = track.get();
  {
    const std::lock_guard lock(tracks_mutex_);
    tracks_.push_back(std::move(track));
  }
  t_binding = Binding{raw, g_generation.load(), true};
  return *raw;
}

SessionTotals Session::totals() const {
  const std::lock_guard lock(tracks_mutex_);
  SessionTotals t;
  t.threads = tracks_.size();
  for (const auto& track : tracks_) {
    t.events += track->written();
    t.overwritten += track->overwritten();
  }
  return t;
}

std::string Session::chromeJson() const {
  const std::int64_t pid = static_cast<std::int64_t>(::getpid());
  const SessionTotals t = totals();
  std::string out = R"({"displayTimeUnit":"ms","otherData":{"format":"cvislam trace 1","process":)";
  appendJsonString(out, options_.process_name);
  out += ",\"agent\":" + std::to_string(options_.agent) + ",\"mission\":";
  appendJsonString(out, options_.mission);
  out += ",\"mission_key\":" + std::to_string(missionKey(options_.mission)) + R"(,"clock":"steady",)" +
         "\"unix_minus_steady_ns\":" + std::to_string(unix_minus_steady_ns_) +
         ",\"events\":" + std::to_string(t.events) + ",\"overwritten\":" + std::to_string(t.overwritten) +
         "},\n\"traceEvents\":[\n";
  out += R"({"ph":"M","name":"process_name","pid":)" + std::to_string(pid) + R"(,"tid":0,"args":{"name":)";
  appendJsonString(out, options_.process_name);
  out += "}}";
  const std::lock_guard lock(tracks_mutex_);
  for (const auto& track : tracks_) {
    out += ",\n";
    out += R"({"ph":"M","name":"thread_name","pid":)" + std::to_string(pid) +
           ",\"tid\":" + std::to_string(track->tid()) + R"(,"args":{"name":)";
    appendJsonString(out, track->name());
    out += "}}";
    for (const Event& e : track->events()) {
      out += ",\n";
      appendEvent(out, e, pid, track->tid());
    }
  }
  out += "\n]}\n";
  return out;
}

Status Session::writeChromeJson(const std::filesystem::path& file) const {
  const std::string text = chromeJson();
  std::ofstream out(file, std::ios::binary | std::ios::trunc);
  if (!out) return Error{ErrorCode::kIoError, "cannot write the trace to " + file.string()};
  out.write(text.data(), static_cast<std::streamsize>(text.size()));
  if (!out) return Error{ErrorCode::kIoError, "writing the trace to " + file.string() + " failed"};
  return Status::Ok();
}

void bindThread(const char* name) {
  Session* session = g_session.load();
  if (session != nullptr) session->bindCurrentThread(name);
}

ThreadTrack* currentTrack() noexcept {
  Binding& b = t_binding;
  const std::uint64_t generation = g_generation.load(std::memory_order_relaxed);
  if (b.track != nullptr && b.generation == generation) return b.track;
  if (b.generation == generation && b.tried_unbound) return nullptr;
  b = Binding{nullptr, generation, true};
  Session* session = g_session.load();
  if (session == nullptr || !session->options().trace_unbound_threads) return nullptr;
  try {
    return &session->bindCurrentThread("thread " + std::to_string(threadId()));
  } catch (...) {  // out of memory: this thread records nothing
    return nullptr;
  }
}

std::int64_t nowNs() noexcept {
  return steadyNowNs();
}

std::int64_t missionKey(std::string_view mission) noexcept {
  return static_cast<std::int64_t>(fnv1a64(mission) & ((std::uint64_t{1} << 52) - 1));
}

void instant(const char* name, std::initializer_list<Arg> args) noexcept {
  ThreadTrack* track = currentTrack();
  const bool lttng = lttngEnabled();
  if (track == nullptr && !lttng) return;
  Event e;
  e.name = name;
  e.begin_ns = steadyNowNs();
  fillArgs(e, args);
  deliver(track, lttng, e);
}

void complete(const char* name, std::int64_t begin_ns, std::int64_t end_ns, std::initializer_list<Arg> args) noexcept {
  ThreadTrack* track = currentTrack();
  const bool lttng = lttngEnabled();
  if (track == nullptr && !lttng) return;
  Event e;
  e.name = name;
  e.begin_ns = begin_ns;
  e.duration_ns = std::max<std::int64_t>(end_ns - begin_ns, 0);
  fillArgs(e, args);
  deliver(track, lttng, e);
}

Span::Span(const char* name, std::initializer_list<Arg> args) noexcept
    : track_(currentTrack()), lttng_(lttngEnabled()) {
  if (!active()) return;
  event_.name = name;
  fillArgs(event_, args);
  event_.begin_ns = steadyNowNs();
}

Span::~Span() {
  if (!active()) return;
  event_.duration_ns = std::max<std::int64_t>(steadyNowNs() - event_.begin_ns, 0);
  deliver(track_, lttng_, event_);
}

void Span::set(const char* key, std::int64_t value) noexcept {
  if (!active()) return;
  for (Arg& a : event_.args) {
    if (a.key == nullptr || a.key == key) {
      a = Arg{key, value};
      return;
    }
  }
}

}  // namespace cvislam::trace

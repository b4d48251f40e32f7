// link_impair: a userspace TCP proxy that stands between one robot's agent and the server and impairs the link
// the way a robot's radio link is impaired: one-way latency with jitter, a bandwidth cap shared by all of the
// robot's connections, scheduled blackouts that cut (reset) or freeze the link, and short periodic stalls.
//
//   link_impair --listen HOST:PORT --target HOST:PORT [--latency-ms MS] [--jitter-ms MS] [--up-kbit KBIT]
//               [--down-kbit KBIT] [--blackout START_S:DURATION_S:cut|freeze]... [--stall-every-s S --stall-ms MS]
//               [--seed N] [--port-file FILE] [--log FILE]
//
// One thread: edge-triggered epoll, a timerfd armed at the next due time, a signalfd for SIGTERM/SIGINT. On a
// signal it prints one summary line to stdout and exits 0.
// Exit status: 0 stopped by a signal, 1 could not listen (or another system failure), 2 bad command line.
//
// What is modelled, and what is not: bytes are delayed per direction (FIN too, so half-closes keep their place in
// the stream); the bandwidth cap counts TCP payload only; the target connect and RSTs are not delayed, so a reset
// on one side reaches the other at once.
#include <fcntl.h>
#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <signal.h>
#include <sys/epoll.h>
#include <sys/resource.h>
#include <sys/signalfd.h>
#include <sys/socket.h>
#include <sys/timerfd.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdarg>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <deque>
#include <limits>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <unordered_map>
#include <unordered_set>
#include <utility>
#include <vector>

namespace {

constexpr int64_t kNsPerMs = 1'000'000;
constexpr int64_t kNsPerS = 1'000'000'000;
constexpr int64_t kNever = std::numeric_limits<int64_t>::max();

// Bytes held per direction per connection. A radio's queue is finite too: when this one is full the proxy stops
// reading that side, and TCP's own window pushes back on the sender instead of the proxy growing without bound.
constexpr size_t kPipeBufferBytes = size_t{4} << 20;
// Largest single read. One read becomes one chunk with one due time, so bigger reads only mean fewer timestamps.
constexpr size_t kReadChunkBytes = size_t{64} << 10;
// Bytes one direction of one connection may read per pass, so that a busy connection cannot take every token of a
// shared bandwidth cap while the others wait.
constexpr size_t kPumpBudgetBytes = size_t{256} << 10;
// When accept() runs out of descriptors the listener stays ready; retry after this instead of spinning.
constexpr int64_t kAcceptRetryNs = 100 * kNsPerMs;

// Bounds that refuse the absurd before it overflows nanoseconds or means a typo.
constexpr double kMaxDelayMs = 600'000.0;   // 10 minutes
constexpr double kMaxTimeS = 10'000'000.0;  // ~115 days
constexpr double kMaxKbit = 100'000'000.0;  // 100 Gbit/s

// ---------------------------------------------------------------------------------------------------------------
// Options

enum class BlackoutMode { kCut, kFreeze };

const char* toString(BlackoutMode mode) {
  return mode == BlackoutMode::kCut ? "cut" : "freeze";
}

struct Blackout {
  double start_s = 0.0;
  double duration_s = 0.0;
  BlackoutMode mode = BlackoutMode::kCut;
};

struct HostPort {
  std::string host;
  int port = -1;  // -1: not given
};

struct Options {
  HostPort listen;
  HostPort target;
  double latency_ms = 0.0;
  double jitter_ms = 0.0;
  double up_kbit = 0.0;    // client -> target; 0: no cap
  double down_kbit = 0.0;  // target -> client; 0: no cap
  std::vector<Blackout> blackouts;
  double stall_every_s = 0.0;  // 0: no stalls
  double stall_ms = 0.0;
  uint64_t seed = 1;
  std::string port_file;
  std::string log_file;
};

void printUsage(FILE* out) {
  std::fputs(
      "link_impair: a TCP proxy that impairs the link like a robot's radio link.\n"
      "\n"
      "  link_impair --listen HOST:PORT --target HOST:PORT [options]\n"
      "\n"
      "  --listen HOST:PORT          where the agent connects (PORT 0: any free port, see --port-file)\n"
      "  --target HOST:PORT          where the server listens\n"
      "  --latency-ms MS             one-way delay added in each direction (default 0)\n"
      "  --jitter-ms MS              uniform jitter in [-MS, +MS] on top of the latency; byte order is kept,\n"
      "                              so it must not exceed --latency-ms (default 0)\n"
      "  --up-kbit KBIT              bandwidth cap client->target in kbit/s, shared by all connections (0: none)\n"
      "  --down-kbit KBIT            bandwidth cap target->client in kbit/s, shared by all connections (0: none)\n"
      "  --blackout START_S:DURATION_S:MODE\n"
      "                              from START_S (seconds since start) for DURATION_S; may be repeated.\n"
      "                              MODE cut: open connections are reset (RST) at START_S and new ones are\n"
      "                              accepted then reset until the end. MODE freeze: nothing moves either way,\n"
      "                              connections stay open and data waits until the end.\n"
      "  --stall-every-s S           a freeze of --stall-ms every S seconds (at S, 2S, ...); give both or neither\n"
      "  --stall-ms MS               length of each stall\n"
      "  --seed N                    seed of the jitter (default 1)\n"
      "  --port-file FILE            write the bound port to FILE once listening\n"
      "  --log FILE                  one line per event (connection open/close, blackout start/end), with the\n"
      "                              seconds since start\n"
      "  --help                      this text\n"
      "\n"
      "SIGTERM or SIGINT: prints one summary line and exits 0: bytes delivered each way, connections accepted\n"
      "(those refused during a cut included), connections reset by cuts, connections refused during cuts.\n"
      "Exit status: 0 stopped by a signal, 1 system failure (e.g. cannot bind), 2 bad command line.\n",
      out);
}

// Strict decimal: the whole text, finite. std::from_chars refuses leading blanks and '+', which is what we want.
std::optional<double> parseDecimal(std::string_view text) {
  double value = 0.0;
  const char* end = text.data() + text.size();
  const auto [ptr, ec] = std::from_chars(text.data(), end, value);
  if (ec != std::errc() || ptr != end || !std::isfinite(value)) return std::nullopt;
  return value;
}

std::optional<uint64_t> parseUnsigned(std::string_view text) {
  uint64_t value = 0;
  const char* end = text.data() + text.size();
  const auto [ptr, ec] = std::from_chars(text.data(), end, value);
  if (ec != std::errc() || ptr != end || text.empty()) return std::nullopt;
  return value;
}

// "HOST:PORT" or "[IPV6]:PORT"; the port is split at the last ':' so a bracketed IPv6 address works.
std::optional<HostPort> parseHostPort(std::string_view text) {
  const size_t colon = text.rfind(':');
  if (colon == std::string_view::npos || colon == 0) return std::nullopt;
  std::string_view host = text.substr(0, colon);
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') host = host.substr(1, host.size() - 2);
  const std::optional<uint64_t> port = parseUnsigned(text.substr(colon + 1));
  if (host.empty() || !port || *port > 65535) return std::nullopt;
  return HostPort{std::string(host), static_cast<int>(*port)};
}

std::optional<Blackout> parseBlackout(std::string_view text) {
  const size_t first = text.find(':');
  const size_t second = first == std::string_view::npos ? first : text.find(':', first + 1);
  if (second == std::string_view::npos) return std::nullopt;
  const std::optional<double> start_s = parseDecimal(text.substr(0, first));
  const std::optional<double> duration_s = parseDecimal(text.substr(first + 1, second - first - 1));
  const std::string_view mode = text.substr(second + 1);
  if (!start_s || !duration_s || (mode != "cut" && mode != "freeze")) return std::nullopt;
  return Blackout{*start_s, *duration_s, mode == "cut" ? BlackoutMode::kCut : BlackoutMode::kFreeze};
}

// Applies one option; returns "" or a message naming the option.
std::string applyOption(const std::string& name, const std::string& value, Options& o) {
  const auto decimal = [&](double& out, const char* unit) -> std::string {
    const std::optional<double> v = parseDecimal(value);
    if (!v) return name + ": '" + value + "' is not a number of " + unit;
    out = *v;
    return "";
  };
  if (name == "--listen" || name == "--target") {
    const std::optional<HostPort> hp = parseHostPort(value);
    if (!hp) return name + ": '" + value + "' is not HOST:PORT with PORT in [0, 65535]";
    (name == "--listen" ? o.listen : o.target) = *hp;
    return "";
  }
  if (name == "--latency-ms") return decimal(o.latency_ms, "milliseconds");
  if (name == "--jitter-ms") return decimal(o.jitter_ms, "milliseconds");
  if (name == "--up-kbit") return decimal(o.up_kbit, "kbit/s");
  if (name == "--down-kbit") return decimal(o.down_kbit, "kbit/s");
  if (name == "--stall-every-s") return decimal(o.stall_every_s, "seconds");
  if (name == "--stall-ms") return decimal(o.stall_ms, "milliseconds");
  if (name == "--blackout") {
    const std::optional<Blackout> b = parseBlackout(value);
    if (!b) return name + ": '" + value + "' is not START_S:DURATION_S:MODE with MODE cut or freeze";
    o.blackouts.push_back(*b);
    return "";
  }
  if (name == "--seed") {
    const std::optional<uint64_t> seed = parseUnsigned(value);
    if (!seed) return name + ": '" + value + "' is not an unsigned integer";
    o.seed = *seed;
    return "";
  }
  if (name == "--port-file" || name == "--log") {
    if (value.empty()) return name + ": needs a file name";
    (name == "--log" ? o.log_file : o.port_file) = value;
    return "";
  }
  return "unknown option " + name;
}

// Accepts "--name value" and "--name=value". Returns "" or a message naming the bad option; `wants_help` is set
// by --help, which wins over everything else.
std::string parseCommandLine(int argc, char** argv, Options& o, bool& wants_help) {
  static const std::set<std::string> kKnown = {"--listen",   "--target",    "--latency-ms", "--jitter-ms",
                                               "--up-kbit",  "--down-kbit", "--blackout",   "--stall-every-s",
                                               "--stall-ms", "--seed",      "--port-file",  "--log"};
  for (int i = 1; i < argc; ++i) {
    if (std::string_view(argv[i]) == "--help" || std::string_view(argv[i]) == "-h") wants_help = true;
  }
  if (wants_help) return "";
  std::set<std::string> seen;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    if (arg.rfind("--", 0) != 0) return "unexpected argument '" + arg + "'";
    std::string name = arg;
    std::string value;
    const size_t eq = arg.find('=');
    if (eq != std::string::npos) {
      name = arg.substr(0, eq);
      value = arg.substr(eq + 1);
    }
    if (kKnown.count(name) == 0) return "unknown option " + name;
    if (eq == std::string::npos) {
      if (i + 1 >= argc) return name + ": needs a value";
      value = argv[++i];
    }
    // Only --blackout repeats; a second --latency-ms is more likely a mistake than an intent to override.
    if (name != "--blackout" && !seen.insert(name).second) return name + ": given twice";
    if (std::string error = applyOption(name, value, o); !error.empty()) return error;
  }
  return "";
}

std::string formatNumber(double value) {
  char text[64];
  std::snprintf(text, sizeof(text), "%g", value);
  return text;
}

// Returns "" or what is wrong, naming the option.
std::string validate(const Options& o) {
  if (o.listen.port < 0) return "--listen HOST:PORT is required";
  if (o.target.port < 0) return "--target HOST:PORT is required";
  if (o.target.port == 0) return "--target: port 0 cannot be connected to";
  const auto in_range = [](double v, double max) { return v >= 0.0 && v <= max; };
  if (!in_range(o.latency_ms, kMaxDelayMs)) return "--latency-ms must be in [0, " + formatNumber(kMaxDelayMs) + "]";
  if (!in_range(o.jitter_ms, kMaxDelayMs)) return "--jitter-ms must be in [0, " + formatNumber(kMaxDelayMs) + "]";
  // Jitter below zero latency would deliver a chunk before it was read; refuse rather than clip silently, which
  // would skew the distribution the user asked for.
  if (o.jitter_ms > o.latency_ms) {
    return "--jitter-ms (" + formatNumber(o.jitter_ms) + ") must not exceed --latency-ms (" +
           formatNumber(o.latency_ms) + "): a chunk cannot arrive before it was sent";
  }
  if (!in_range(o.up_kbit, kMaxKbit)) return "--up-kbit must be in [0, " + formatNumber(kMaxKbit) + "] (0: no cap)";
  if (!in_range(o.down_kbit, kMaxKbit)) return "--down-kbit must be in [0, " + formatNumber(kMaxKbit) + "] (0: no cap)";
  for (const Blackout& b : o.blackouts) {
    if (!in_range(b.start_s, kMaxTimeS)) return "--blackout: START_S must be in [0, " + formatNumber(kMaxTimeS) + "]";
    if (!(b.duration_s > 0.0) || b.duration_s > kMaxTimeS) {
      return "--blackout: DURATION_S must be in (0, " + formatNumber(kMaxTimeS) + "]";
    }
  }
  const bool stall_every_given = o.stall_every_s != 0.0;
  const bool stall_ms_given = o.stall_ms != 0.0;
  if (stall_every_given != stall_ms_given) return "--stall-every-s and --stall-ms go together: give both or neither";
  if (stall_every_given) {
    if (!(o.stall_every_s > 0.0) || o.stall_every_s > kMaxTimeS) {
      return "--stall-every-s must be in (0, " + formatNumber(kMaxTimeS) + "]";
    }
    if (!(o.stall_ms > 0.0) || o.stall_ms >= o.stall_every_s * 1000.0) {
      return "--stall-ms must be positive and shorter than --stall-every-s (" + formatNumber(o.stall_every_s) +
             " s), or the link would never be up";
    }
  }
  return "";
}

int64_t msToNs(double ms) {
  return static_cast<int64_t>(std::llround(ms * static_cast<double>(kNsPerMs)));
}
int64_t sToNs(double s) {
  return static_cast<int64_t>(std::llround(s * static_cast<double>(kNsPerS)));
}
double nsToS(int64_t ns) {
  return static_cast<double>(ns) / static_cast<double>(kNsPerS);
}

// ---------------------------------------------------------------------------------------------------------------
// Time, randomness, event log

int64_t monotonicNs() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<int64_t>(ts.tv_sec) * kNsPerS + ts.tv_nsec;
}

// SplitMix64 rather than <random>'s distributions, whose output is not specified across standard libraries: the
// same --seed gives the same jitter wherever the tool was built.
class SplitMix64 {
 public:
  explicit SplitMix64(uint64_t seed) : state_(seed) {}
  uint64_t next() {
    uint64_t z = (state_ += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
  }
  // Uniform in [lo, hi]; the modulo bias of a 64-bit draw is far below anything a link test could see.
  int64_t uniform(int64_t lo, int64_t hi) {
    const uint64_t span = static_cast<uint64_t>(hi - lo) + 1;
    return lo + static_cast<int64_t>(next() % span);
  }

 private:
  uint64_t state_;
};

class EventLog {
 public:
  EventLog() = default;
  ~EventLog() {
    if (file_ != nullptr) std::fclose(file_);
  }
  EventLog(const EventLog&) = delete;
  EventLog& operator=(const EventLog&) = delete;

  bool open(const std::string& path) {
    file_ = std::fopen(path.c_str(), "w");
    return file_ != nullptr;
  }

  // Flushed per line: a test reads the log while the proxy runs, and a killed proxy should leave it complete.
  __attribute__((format(printf, 3, 4))) void line(int64_t t_ns, const char* format, ...) {
    if (file_ == nullptr) return;
    std::fprintf(file_, "%.6f ", nsToS(t_ns));
    va_list args;
    va_start(args, format);
    std::vfprintf(file_, format, args);
    va_end(args);
    std::fputc('\n', file_);
    std::fflush(file_);
  }

 private:
  FILE* file_ = nullptr;
};

// ---------------------------------------------------------------------------------------------------------------
// Bandwidth and schedule

// A token bucket in bytes, shared by every connection in one direction: one proxy stands for one robot's radio.
// Tokens are taken when bytes are read from the sender, i.e. the cap is where the radio serialises; what it has
// not let through waits in the sender's socket buffers, as it would in the robot's.
class TokenBucket {
 public:
  explicit TokenBucket(double kbit) : rate_bytes_per_s_(kbit * 1000.0 / 8.0) {
    if (!capped()) return;
    // Reads wait for a quantum (1 ms of the rate, at least 512 B) so that a starved link makes few reads of
    // useful size rather than many of a few bytes; the burst allowed after idling is a few quanta.
    quantum_bytes_ = std::max(512.0, rate_bytes_per_s_ / 1000.0);
    capacity_bytes_ = 4.0 * quantum_bytes_;
    tokens_bytes_ = capacity_bytes_;
  }

  [[nodiscard]] bool capped() const { return rate_bytes_per_s_ > 0.0; }

  void refill(int64_t now_ns) {
    if (capped() && now_ns > refilled_ns_) {
      tokens_bytes_ = std::min(capacity_bytes_,
                               tokens_bytes_ + static_cast<double>(now_ns - refilled_ns_) * rate_bytes_per_s_ / 1e9);
    }
    refilled_ns_ = now_ns;
  }

  // Bytes that may be read now: none until a quantum has gathered.
  [[nodiscard]] size_t allowanceBytes() const {
    if (!capped()) return std::numeric_limits<size_t>::max();
    return tokens_bytes_ >= quantum_bytes_ ? static_cast<size_t>(tokens_bytes_) : 0;
  }

  void take(size_t bytes) {
    if (capped()) tokens_bytes_ -= static_cast<double>(bytes);
  }

  // When allowanceBytes() will be non-zero again.
  [[nodiscard]] int64_t readyAtNs(int64_t now_ns) const {
    if (allowanceBytes() > 0) return now_ns;
    const double wait_ns = std::ceil((quantum_bytes_ - tokens_bytes_) / rate_bytes_per_s_ * 1e9);
    return std::max(now_ns, refilled_ns_) + static_cast<int64_t>(wait_ns) + 1;
  }

 private:
  double rate_bytes_per_s_;
  double quantum_bytes_ = 0.0;
  double capacity_bytes_ = 0.0;
  double tokens_bytes_ = 0.0;
  int64_t refilled_ns_ = 0;
};

enum class Gate { kOpen, kFrozen, kCut };

// The blackout windows and the periodic stalls, in nanoseconds since start.
class Schedule {
 public:
  struct Window {
    int64_t start_ns;
    int64_t end_ns;
    BlackoutMode mode;
  };

  explicit Schedule(const Options& o) : stall_every_ns_(sToNs(o.stall_every_s)), stall_ns_(msToNs(o.stall_ms)) {
    for (const Blackout& b : o.blackouts) {
      windows_.push_back({sToNs(b.start_s), sToNs(b.start_s) + sToNs(b.duration_s), b.mode});
    }
  }

  [[nodiscard]] const std::vector<Window>& windows() const { return windows_; }

  // Stalls at [k*every, k*every + stall) for k >= 1: the link starts up.
  [[nodiscard]] bool stallAt(int64_t t_ns) const {
    return stall_every_ns_ > 0 && t_ns >= stall_every_ns_ && t_ns % stall_every_ns_ < stall_ns_;
  }

  // A cut anywhere wins over a freeze: there is nothing left to freeze.
  [[nodiscard]] Gate gateAt(int64_t t_ns) const {
    Gate gate = stallAt(t_ns) ? Gate::kFrozen : Gate::kOpen;
    for (const Window& w : windows_) {
      if (t_ns < w.start_ns || t_ns >= w.end_ns) continue;
      if (w.mode == BlackoutMode::kCut) return Gate::kCut;
      gate = Gate::kFrozen;
    }
    return gate;
  }

  // The first time after `t_ns` at which a window or stall starts or ends.
  [[nodiscard]] int64_t nextChangeAfterNs(int64_t t_ns) const {
    int64_t next = kNever;
    for (const Window& w : windows_) {
      if (w.start_ns > t_ns) next = std::min(next, w.start_ns);
      if (w.end_ns > t_ns) next = std::min(next, w.end_ns);
    }
    if (stall_every_ns_ > 0) {
      const int64_t period_start_ns = std::max<int64_t>(1, t_ns / stall_every_ns_) * stall_every_ns_;
      const int64_t stall_end_ns = period_start_ns + stall_ns_;
      next = std::min(next, t_ns < period_start_ns ? period_start_ns
                            : t_ns < stall_end_ns  ? stall_end_ns
                                                   : period_start_ns + stall_every_ns_);
    }
    return next;
  }

 private:
  std::vector<Window> windows_;
  int64_t stall_every_ns_;
  int64_t stall_ns_;
};

// ---------------------------------------------------------------------------------------------------------------
// Sockets

struct SocketAddress {
  sockaddr_storage storage{};
  socklen_t length = 0;
  [[nodiscard]] const sockaddr* get() const { return reinterpret_cast<const sockaddr*>(&storage); }
};

// Resolves to the first address getaddrinfo offers; returns "" or why not.
std::string resolve(const HostPort& hp, bool passive, SocketAddress& out) {
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_NUMERICSERV | (passive ? AI_PASSIVE : 0);
  addrinfo* results = nullptr;
  const std::string port = std::to_string(hp.port);
  if (const int rc = getaddrinfo(hp.host.c_str(), port.c_str(), &hints, &results); rc != 0) {
    return "cannot resolve '" + hp.host + "': " + gai_strerror(rc);
  }
  std::memcpy(&out.storage, results->ai_addr, results->ai_addrlen);
  out.length = results->ai_addrlen;
  freeaddrinfo(results);
  return "";
}

std::string describe(const sockaddr* address, socklen_t length) {
  char host[NI_MAXHOST];
  char port[NI_MAXSERV];
  if (getnameinfo(address, length, host, sizeof(host), port, sizeof(port), NI_NUMERICHOST | NI_NUMERICSERV) != 0) {
    return "?";
  }
  return address->sa_family == AF_INET6 ? "[" + std::string(host) + "]:" + port : std::string(host) + ":" + port;
}

std::string errorText(int error_number) {
  return std::strerror(error_number);
}

// The proxy's own timing is the impairment; Nagle plus delayed ACKs on its sockets would add up to 40 ms of its
// own. The endpoints keep whatever they chose for their sockets.
void setNoDelay(int fd) {
  const int one = 1;
  setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof(one));
}

// Closing with a zero linger sends RST instead of FIN: what the peer sees when a radio link drops and the other
// end has given up on the connection.
void resetAndClose(int fd) {
  if (fd < 0) return;
  const linger abort_now{1, 0};
  setsockopt(fd, SOL_SOCKET, SO_LINGER, &abort_now, sizeof(abort_now));
  close(fd);
}

int pendingSocketError(int fd) {
  int error = 0;
  socklen_t length = sizeof(error);
  if (getsockopt(fd, SOL_SOCKET, SO_ERROR, &error, &length) != 0) return errno;
  return error;
}

// Whether `target` is the listening socket itself (or, for a wildcard listen, loopback on the same port): every
// connection would then be proxied into the proxy again, one more at each hop, without end.
bool isOwnAddress(const SocketAddress& bound, const SocketAddress& target) {
  if (bound.storage.ss_family != target.storage.ss_family) return false;
  if (bound.storage.ss_family == AF_INET) {
    const auto& b = *reinterpret_cast<const sockaddr_in*>(&bound.storage);
    const auto& t = *reinterpret_cast<const sockaddr_in*>(&target.storage);
    const bool loopback = (ntohl(t.sin_addr.s_addr) >> 24) == 127;
    return b.sin_port == t.sin_port &&
           (b.sin_addr.s_addr == t.sin_addr.s_addr || (b.sin_addr.s_addr == htonl(INADDR_ANY) && loopback));
  }
  if (bound.storage.ss_family == AF_INET6) {
    const auto& b = *reinterpret_cast<const sockaddr_in6*>(&bound.storage);
    const auto& t = *reinterpret_cast<const sockaddr_in6*>(&target.storage);
    const bool same = std::memcmp(&b.sin6_addr, &t.sin6_addr, sizeof(in6_addr)) == 0;
    const bool wildcard = std::memcmp(&b.sin6_addr, &in6addr_any, sizeof(in6_addr)) == 0;
    const bool loopback = std::memcmp(&t.sin6_addr, &in6addr_loopback, sizeof(in6_addr)) == 0;
    return b.sin6_port == t.sin6_port && (same || (wildcard && loopback));
  }
  return false;
}

// Writes via a temporary file and rename, so that a test polling for the file never reads half a number.
bool writePortFile(const std::string& path, int port) {
  const std::string temporary = path + ".tmp";
  FILE* file = std::fopen(temporary.c_str(), "w");
  if (file == nullptr) return false;
  const bool written = std::fprintf(file, "%d\n", port) > 0;
  if (std::fclose(file) != 0 || !written) return false;
  return std::rename(temporary.c_str(), path.c_str()) == 0;
}

// Many connections need many descriptors; the soft limit is often 1024 while the hard one is far higher.
void raiseDescriptorLimit() {
  rlimit limit{};
  if (getrlimit(RLIMIT_NOFILE, &limit) == 0 && limit.rlim_cur < limit.rlim_max) {
    limit.rlim_cur = limit.rlim_max;
    setrlimit(RLIMIT_NOFILE, &limit);
  }
}

// ---------------------------------------------------------------------------------------------------------------
// Connections

struct Chunk {
  int64_t due_ns;
  std::vector<char> bytes;
  size_t sent_bytes = 0;
};

// One end of a proxied connection. The flags follow edge-triggered epoll: set by an event, cleared only when the
// socket answers EAGAIN. So a side the proxy chose not to read (buffer full, no tokens, frozen) is still known to
// be readable when reading is allowed again, without any epoll_ctl to stop and restart interest.
struct Endpoint {
  int fd = -1;
  bool readable = false;
  bool writable = false;
};

// One direction of a connection: the delay line between reading from the source and delivering to the sink.
struct Pipe {
  std::deque<Chunk> queue;
  size_t queued_bytes = 0;
  int64_t last_due_ns = 0;  // the next chunk is due no earlier: byte order is kept
  bool source_eof = false;
  int64_t eof_due_ns = kNever;
  bool eof_forwarded = false;
  uint64_t delivered_bytes = 0;
};

enum class TargetState { kNotStarted, kConnecting, kConnected };

struct Connection {
  uint64_t id = 0;
  std::string peer;
  int64_t opened_ns = 0;
  Endpoint client;
  Endpoint target;
  TargetState target_state = TargetState::kNotStarted;
  Pipe up;    // client -> target
  Pipe down;  // target -> client
};

// Everything one direction of one connection needs to move bytes.
struct Flow {
  Pipe& pipe;
  Endpoint& source;
  Endpoint& sink;
  TokenBucket& bucket;
  uint64_t& total_bytes;
  bool sink_connected;
  const char* name;
};

struct Stats {
  uint64_t up_bytes = 0;
  uint64_t down_bytes = 0;
  uint64_t accepted = 0;
  uint64_t reset_by_cut = 0;
  uint64_t refused_in_cut = 0;
};

// epoll tokens: connection endpoints are (id << 1 | side); the few fixed descriptors take the top values, which
// connection ids never reach.
constexpr uint64_t kListenToken = ~uint64_t{0};
constexpr uint64_t kTimerToken = kListenToken - 1;
constexpr uint64_t kSignalToken = kListenToken - 2;
constexpr uint64_t kTargetSide = 1;

// ---------------------------------------------------------------------------------------------------------------
// The proxy

class Proxy {
 public:
  explicit Proxy(const Options& options)
      : options_(options),
        schedule_(options),
        rng_(options.seed),
        up_bucket_(options.up_kbit),
        down_bucket_(options.down_kbit),
        latency_ns_(msToNs(options.latency_ms)),
        jitter_ns_(msToNs(options.jitter_ms)),
        start_mono_ns_(monotonicNs()),
        window_state_(schedule_.windows().size(), WindowState::kPending),
        scratch_(kReadChunkBytes) {}

  ~Proxy() {
    for (auto& [id, c] : connections_) {
      if (c->client.fd >= 0) close(c->client.fd);
      if (c->target.fd >= 0) close(c->target.fd);
    }
    for (int fd : {listen_fd_, timer_fd_, signal_fd_, epoll_fd_}) {
      if (fd >= 0) close(fd);
    }
  }
  Proxy(const Proxy&) = delete;
  Proxy& operator=(const Proxy&) = delete;

  // Returns 0, or the exit status with a message in `error`.
  int setUp(std::string& error);
  // Runs until SIGTERM/SIGINT; returns the exit status.
  int run();

 private:
  enum class WindowState { kPending, kActive, kDone };

  [[nodiscard]] int64_t nowNs() const { return monotonicNs() - start_mono_ns_; }
  int listen(std::string& error);
  int setUpEventSources(std::string& error);
  bool watch(int fd, uint64_t token, uint32_t events);

  void advanceSchedule(int64_t now_ns);
  void cutAll(int64_t now_ns);
  void dispatch(const epoll_event& event, int64_t now_ns);
  void dispatchEndpoint(const epoll_event& event, int64_t now_ns);
  void acceptPending(int64_t now_ns);
  void admit(int fd, std::string peer, int64_t now_ns);

  void pumpConnections(int64_t now_ns);
  bool pumpConnection(Connection& c, int64_t now_ns);
  bool startTargetConnect(Connection& c, int64_t now_ns);
  bool finishTargetConnect(Connection& c, int64_t now_ns);
  Flow upFlow(Connection& c);
  Flow downFlow(Connection& c);
  std::string pumpFlow(const Flow& f, int64_t now_ns);
  bool deliverDue(const Flow& f, int64_t now_ns, std::string& error);
  bool readChunk(const Flow& f, int64_t now_ns, size_t& budget_bytes, std::string& error);
  std::string forwardEofIfDue(const Flow& f, int64_t now_ns);
  int64_t dueNs(Pipe& pipe, int64_t read_ns);
  [[nodiscard]] static bool mayRead(const Flow& f);
  [[nodiscard]] static int64_t flowWakeNs(const Flow& f, int64_t now_ns);
  [[nodiscard]] static bool busy(const Pipe& pipe, const Endpoint& source);

  void abortConnection(uint64_t id, const std::string& reason, int64_t now_ns);
  void closeConnection(uint64_t id, int64_t now_ns);

  [[nodiscard]] int64_t nextWakeNs(int64_t now_ns) const;
  int waitForEvents(int64_t wake_ns);
  void armTimer(int64_t wake_ns);
  void printSummary();

  const Options& options_;
  Schedule schedule_;
  EventLog log_;
  SplitMix64 rng_;
  TokenBucket up_bucket_;
  TokenBucket down_bucket_;
  int64_t latency_ns_;
  int64_t jitter_ns_;
  int64_t start_mono_ns_;

  SocketAddress target_address_;
  int epoll_fd_ = -1;
  int listen_fd_ = -1;
  int timer_fd_ = -1;
  int signal_fd_ = -1;
  int64_t timer_armed_ns_ = kNever;

  std::unordered_map<uint64_t, std::unique_ptr<Connection>> connections_;
  // Connections with something that waits on time, tokens or the gate rather than on an event. Only these (and
  // those an event touched) are pumped, so idle connections cost nothing per wake-up.
  std::unordered_set<uint64_t> pending_;
  uint64_t next_id_ = 1;
  uint64_t pump_round_ = 0;
  int64_t connections_wake_ns_ = kNever;  // earliest wake any pumped connection asked for

  Gate gate_ = Gate::kOpen;
  std::vector<WindowState> window_state_;
  bool stall_active_ = false;
  bool listener_ready_ = false;
  int64_t accept_retry_ns_ = 0;
  bool stop_ = false;
  std::string stop_signal_;
  std::array<epoll_event, 256> events_{};
  int event_count_ = 0;
  std::vector<char> scratch_;
  Stats stats_;
};

int Proxy::setUp(std::string& error) {
  raiseDescriptorLimit();
  if (!options_.log_file.empty() && !log_.open(options_.log_file)) {
    error = "--log: cannot write '" + options_.log_file + "': " + errorText(errno);
    return 2;
  }
  if (std::string e = resolve(options_.target, false, target_address_); !e.empty()) {
    error = "--target: " + e;
    return 2;
  }
  if (const int status = setUpEventSources(error); status != 0) return status;
  return listen(error);
}

int Proxy::setUpEventSources(std::string& error) {
  epoll_fd_ = epoll_create1(EPOLL_CLOEXEC);
  timer_fd_ = timerfd_create(CLOCK_MONOTONIC, TFD_NONBLOCK | TFD_CLOEXEC);
  // Signals arrive as events of the one loop rather than as handlers racing it.
  sigset_t stop_signals;
  sigemptyset(&stop_signals);
  sigaddset(&stop_signals, SIGTERM);
  sigaddset(&stop_signals, SIGINT);
  sigprocmask(SIG_BLOCK, &stop_signals, nullptr);
  signal_fd_ = signalfd(-1, &stop_signals, SFD_NONBLOCK | SFD_CLOEXEC);
  // A write to a reset peer must come back as EPIPE, not kill the proxy (MSG_NOSIGNAL covers send; this the rest).
  signal(SIGPIPE, SIG_IGN);
  if (epoll_fd_ < 0 || timer_fd_ < 0 || signal_fd_ < 0 || !watch(timer_fd_, kTimerToken, EPOLLIN) ||
      !watch(signal_fd_, kSignalToken, EPOLLIN)) {
    error = "cannot set up epoll, timerfd or signalfd: " + errorText(errno);
    return 1;
  }
  return 0;
}

int Proxy::listen(std::string& error) {
  SocketAddress address;
  if (std::string e = resolve(options_.listen, true, address); !e.empty()) {
    error = "--listen: " + e;
    return 2;
  }
  const std::string where = options_.listen.host + ":" + std::to_string(options_.listen.port);
  listen_fd_ = socket(address.storage.ss_family, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  const int one = 1;
  // A test restarting the proxy on the same port must not wait out TIME_WAIT.
  if (listen_fd_ < 0 || setsockopt(listen_fd_, SOL_SOCKET, SO_REUSEADDR, &one, sizeof(one)) != 0 ||
      bind(listen_fd_, address.get(), address.length) != 0 || ::listen(listen_fd_, SOMAXCONN) != 0 ||
      !watch(listen_fd_, kListenToken, EPOLLIN | EPOLLET)) {
    error = "--listen " + where + ": cannot listen: " + errorText(errno);
    return 1;
  }
  listener_ready_ = true;  // connections may already wait; the first pass accepts them
  SocketAddress bound;
  bound.length = sizeof(bound.storage);
  getsockname(listen_fd_, reinterpret_cast<sockaddr*>(&bound.storage), &bound.length);
  if (isOwnAddress(bound, target_address_)) {
    error = "--target " + describe(target_address_.get(), target_address_.length) +
            " is this proxy's own --listen address: every connection would loop back into it";
    return 2;
  }
  const int port =
      ntohs(bound.storage.ss_family == AF_INET6 ? reinterpret_cast<const sockaddr_in6*>(&bound.storage)->sin6_port
                                                : reinterpret_cast<const sockaddr_in*>(&bound.storage)->sin_port);
  if (!options_.port_file.empty() && !writePortFile(options_.port_file, port)) {
    error = "--port-file: cannot write '" + options_.port_file + "': " + errorText(errno);
    return 2;
  }
  log_.line(nowNs(), "listening %s -> %s latency_ms=%g jitter_ms=%g up_kbit=%g down_kbit=%g seed=%llu",
            describe(bound.get(), bound.length).c_str(),
            describe(target_address_.get(), target_address_.length).c_str(), options_.latency_ms, options_.jitter_ms,
            options_.up_kbit, options_.down_kbit, static_cast<unsigned long long>(options_.seed));
  return 0;
}

bool Proxy::watch(int fd, uint64_t token, uint32_t events) {
  epoll_event event{};
  event.events = events;
  event.data.u64 = token;
  return epoll_ctl(epoll_fd_, EPOLL_CTL_ADD, fd, &event) == 0;
}

int Proxy::run() {
  for (;;) {
    const int64_t now_ns = nowNs();
    // The schedule first: an event that woke us at a blackout's start must already see the blackout.
    advanceSchedule(now_ns);
    for (int i = 0; i < event_count_; ++i) dispatch(events_[i], now_ns);
    event_count_ = 0;
    if (stop_) break;
    if (listener_ready_ && now_ns >= accept_retry_ns_) acceptPending(now_ns);
    up_bucket_.refill(now_ns);
    down_bucket_.refill(now_ns);
    pumpConnections(now_ns);
    if (waitForEvents(nextWakeNs(now_ns)) != 0) return 1;
  }
  log_.line(nowNs(), "stop on %s", stop_signal_.c_str());
  printSummary();
  return 0;
}

// Logs each window's and stall's start and end, and resets everything when a cut starts. Windows move
// pending -> active -> done, so a cut is carried out even if the proxy woke only after its end.
void Proxy::advanceSchedule(int64_t now_ns) {
  const std::vector<Schedule::Window>& windows = schedule_.windows();
  for (size_t i = 0; i < windows.size(); ++i) {
    const Schedule::Window& w = windows[i];
    WindowState& state = window_state_[i];
    if (state == WindowState::kPending && now_ns >= w.start_ns) {
      state = WindowState::kActive;
      log_.line(now_ns, "blackout %zu %s start (until %.3f)", i, toString(w.mode), nsToS(w.end_ns));
      if (w.mode == BlackoutMode::kCut) cutAll(now_ns);
    }
    if (state == WindowState::kActive && now_ns >= w.end_ns) {
      state = WindowState::kDone;
      log_.line(now_ns, "blackout %zu %s end", i, toString(w.mode));
    }
  }
  const bool stall = schedule_.stallAt(now_ns);
  if (stall != stall_active_) log_.line(now_ns, stall ? "stall start" : "stall end");
  stall_active_ = stall;
  // Connections held by a freeze stayed in pending_ (they are busy), so they move again at the first pass with
  // the gate open; those with nothing to move need nothing.
  gate_ = schedule_.gateAt(now_ns);
}

void Proxy::cutAll(int64_t now_ns) {
  std::vector<uint64_t> ids;
  ids.reserve(connections_.size());
  for (const auto& [id, c] : connections_) ids.push_back(id);
  for (uint64_t id : ids) {
    abortConnection(id, "cut blackout", now_ns);
    ++stats_.reset_by_cut;
  }
}

void Proxy::dispatch(const epoll_event& event, int64_t now_ns) {
  const uint64_t token = event.data.u64;
  if (token == kListenToken) {
    listener_ready_ = true;
  } else if (token == kTimerToken) {
    uint64_t expirations = 0;
    while (read(timer_fd_, &expirations, sizeof(expirations)) > 0) {
    }
    timer_armed_ns_ = kNever;
  } else if (token == kSignalToken) {
    signalfd_siginfo info{};
    if (read(signal_fd_, &info, sizeof(info)) == static_cast<ssize_t>(sizeof(info))) {
      stop_ = true;
      stop_signal_ = info.ssi_signo == SIGINT ? "SIGINT" : "SIGTERM";
    }
  } else {
    dispatchEndpoint(event, now_ns);
  }
}

void Proxy::dispatchEndpoint(const epoll_event& event, int64_t now_ns) {
  const uint64_t token = event.data.u64;
  const auto it = connections_.find(token >> 1);
  if (it == connections_.end()) return;  // closed earlier in this batch
  Connection& c = *it->second;
  const bool target_side = (token & kTargetSide) != 0;
  Endpoint& e = target_side ? c.target : c.client;
  // Let read and write discover EOF and errors: they say precisely what happened.
  if (event.events & (EPOLLIN | EPOLLRDHUP | EPOLLHUP | EPOLLERR)) e.readable = true;
  if (event.events & (EPOLLOUT | EPOLLHUP | EPOLLERR)) e.writable = true;
  // Except for an error on a side we no longer read or write (e.g. a RST after its FIN): only SO_ERROR tells.
  if (event.events & EPOLLERR) {
    if (const int error = pendingSocketError(e.fd); error != 0) {
      abortConnection(c.id, std::string(target_side ? "target: " : "client: ") + errorText(error), now_ns);
      return;
    }
  }
  pending_.insert(c.id);
}

void Proxy::acceptPending(int64_t now_ns) {
  for (;;) {
    SocketAddress peer;
    peer.length = sizeof(peer.storage);
    const int fd =
        accept4(listen_fd_, reinterpret_cast<sockaddr*>(&peer.storage), &peer.length, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (fd < 0) {
      if (errno == EINTR || errno == ECONNABORTED) continue;
      if (errno == EAGAIN || errno == EWOULDBLOCK) {
        listener_ready_ = false;
      } else {
        // Out of descriptors or memory: the connection stays in the backlog; try again shortly.
        log_.line(now_ns, "accept failed: %s (retrying)", errorText(errno).c_str());
        accept_retry_ns_ = now_ns + kAcceptRetryNs;
      }
      return;
    }
    ++stats_.accepted;
    const std::string who = describe(peer.get(), peer.length);
    if (gate_ == Gate::kCut) {
      // The listening socket cannot refuse a handshake the kernel already completed; a reset right after
      // accept is what the agent sees of a connect over a dead radio link that gives up.
      resetAndClose(fd);
      ++stats_.refused_in_cut;
      log_.line(now_ns, "refused %s: cut blackout", who.c_str());
      continue;
    }
    admit(fd, who, now_ns);
  }
}

void Proxy::admit(int fd, std::string peer, int64_t now_ns) {
  auto c = std::make_unique<Connection>();
  c->id = next_id_++;
  c->peer = std::move(peer);
  c->opened_ns = now_ns;
  c->client = {fd, true, true};
  setNoDelay(fd);
  if (!watch(fd, c->id << 1, EPOLLIN | EPOLLOUT | EPOLLRDHUP | EPOLLET)) {
    log_.line(now_ns, "refused %s: epoll: %s", c->peer.c_str(), errorText(errno).c_str());
    resetAndClose(fd);
    return;
  }
  log_.line(now_ns, "conn %llu open from %s", static_cast<unsigned long long>(c->id), c->peer.c_str());
  // The target connect waits for the first pump: during a freeze it waits for the freeze's end, as a SYN over a
  // frozen radio would.
  pending_.insert(c->id);
  connections_.emplace(c->id, std::move(c));
}

void Proxy::pumpConnections(int64_t now_ns) {
  connections_wake_ns_ = kNever;
  std::vector<uint64_t> order(pending_.begin(), pending_.end());
  pending_.clear();
  // A different connection goes first each pass, so that none is always first at a shared bandwidth cap.
  if (!order.empty()) {
    std::rotate(order.begin(), order.begin() + static_cast<ptrdiff_t>(pump_round_++ % order.size()), order.end());
  }
  for (uint64_t id : order) {
    const auto it = connections_.find(id);
    if (it == connections_.end()) continue;
    Connection& c = *it->second;
    if (!pumpConnection(c, now_ns)) continue;  // closed
    if (c.target_state == TargetState::kNotStarted || busy(c.up, c.client) || busy(c.down, c.target)) {
      pending_.insert(id);
    }
  }
}

// Returns false when the connection was closed.
bool Proxy::pumpConnection(Connection& c, int64_t now_ns) {
  // Frozen: nothing moves. (Cut: there are no connections.) The schedule's next change wakes us.
  if (gate_ != Gate::kOpen) return true;
  if (c.target_state == TargetState::kNotStarted && !startTargetConnect(c, now_ns)) return false;
  if (c.target_state == TargetState::kConnecting && c.target.writable && !finishTargetConnect(c, now_ns)) {
    return false;
  }
  for (const Flow& f : {upFlow(c), downFlow(c)}) {
    if (std::string error = pumpFlow(f, now_ns); !error.empty()) {
      abortConnection(c.id, error, now_ns);
      return false;
    }
    connections_wake_ns_ = std::min(connections_wake_ns_, flowWakeNs(f, now_ns));
  }
  if (c.up.eof_forwarded && c.down.eof_forwarded) {
    closeConnection(c.id, now_ns);
    return false;
  }
  return true;
}

bool Proxy::startTargetConnect(Connection& c, int64_t now_ns) {
  const int fd = socket(target_address_.storage.ss_family, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  if (fd < 0) {
    abortConnection(c.id, "target socket: " + errorText(errno), now_ns);
    return false;
  }
  c.target.fd = fd;
  setNoDelay(fd);
  if (!watch(fd, c.id << 1 | kTargetSide, EPOLLIN | EPOLLOUT | EPOLLRDHUP | EPOLLET)) {
    abortConnection(c.id, "target epoll: " + errorText(errno), now_ns);
    return false;
  }
  if (connect(fd, target_address_.get(), target_address_.length) == 0) {
    c.target_state = TargetState::kConnecting;
    c.target.writable = true;
    return finishTargetConnect(c, now_ns);
  }
  if (errno != EINPROGRESS) {
    abortConnection(c.id, "target connect: " + errorText(errno), now_ns);
    return false;
  }
  c.target_state = TargetState::kConnecting;  // EPOLLOUT (or EPOLLERR) tells how it went
  return true;
}

bool Proxy::finishTargetConnect(Connection& c, int64_t now_ns) {
  if (const int error = pendingSocketError(c.target.fd); error != 0) {
    abortConnection(c.id, "target connect: " + errorText(error), now_ns);
    return false;
  }
  c.target_state = TargetState::kConnected;
  c.target.readable = true;  // finds out with the first read
  log_.line(now_ns, "conn %llu target connected", static_cast<unsigned long long>(c.id));
  return true;
}

Flow Proxy::upFlow(Connection& c) {
  return {c.up, c.client, c.target, up_bucket_, stats_.up_bytes, c.target_state == TargetState::kConnected, "up"};
}

Flow Proxy::downFlow(Connection& c) {
  return {c.down, c.target, c.client, down_bucket_, stats_.down_bytes, true, "down"};
}

// Delivers what is due, reads what the buffer and the bandwidth cap allow, until neither moves. Returns "" or
// why the connection failed.
std::string Proxy::pumpFlow(const Flow& f, int64_t now_ns) {
  size_t budget_bytes = kPumpBudgetBytes;
  for (;;) {
    std::string error;
    const bool delivered = deliverDue(f, now_ns, error);
    if (!error.empty()) return error;
    const bool read_some = readChunk(f, now_ns, budget_bytes, error);
    if (!error.empty()) return error;
    if (!delivered && !read_some) break;
  }
  return forwardEofIfDue(f, now_ns);
}

bool Proxy::deliverDue(const Flow& f, int64_t now_ns, std::string& error) {
  bool progressed = false;
  Pipe& p = f.pipe;
  while (f.sink_connected && f.sink.writable && !p.queue.empty() && p.queue.front().due_ns <= now_ns) {
    Chunk& chunk = p.queue.front();
    const ssize_t n =
        send(f.sink.fd, chunk.bytes.data() + chunk.sent_bytes, chunk.bytes.size() - chunk.sent_bytes, MSG_NOSIGNAL);
    if (n < 0) {
      if (errno == EINTR) continue;
      if (errno == EAGAIN || errno == EWOULDBLOCK) {
        f.sink.writable = false;  // EPOLLOUT says when there is room again
        break;
      }
      error = std::string(f.name) + " write: " + errorText(errno);
      return progressed;
    }
    const auto sent = static_cast<size_t>(n);
    chunk.sent_bytes += sent;
    p.queued_bytes -= sent;  // frees room for reading as soon as the bytes are out
    p.delivered_bytes += sent;
    f.total_bytes += sent;
    progressed = true;
    if (chunk.sent_bytes == chunk.bytes.size()) p.queue.pop_front();
  }
  return progressed;
}

bool Proxy::mayRead(const Flow& f) {
  return !f.pipe.source_eof && f.source.readable && f.pipe.queued_bytes < kPipeBufferBytes;
}

bool Proxy::readChunk(const Flow& f, int64_t now_ns, size_t& budget_bytes, std::string& error) {
  if (!mayRead(f) || budget_bytes == 0) return false;
  const size_t want_bytes =
      std::min({kReadChunkBytes, kPipeBufferBytes - f.pipe.queued_bytes, budget_bytes, f.bucket.allowanceBytes()});
  if (want_bytes == 0) return false;  // waiting for tokens
  ssize_t n = 0;
  do {
    n = recv(f.source.fd, scratch_.data(), want_bytes, 0);
  } while (n < 0 && errno == EINTR);
  if (n < 0) {
    if (errno == EAGAIN || errno == EWOULDBLOCK) {
      f.source.readable = false;
      return false;
    }
    error = std::string(f.name) + " read: " + errorText(errno);
    return false;
  }
  Pipe& p = f.pipe;
  if (n == 0) {
    // A FIN travels the link like data: forwarded once everything before it is delivered and its own delay passed.
    p.source_eof = true;
    p.eof_due_ns = dueNs(p, now_ns);
    return true;
  }
  const auto got = static_cast<size_t>(n);
  p.queue.push_back({dueNs(p, now_ns), std::vector<char>(scratch_.begin(), scratch_.begin() + n), 0});
  p.queued_bytes += got;
  f.bucket.take(got);
  budget_bytes -= got;
  return true;
}

// Read at `read_ns`, due after latency plus jitter, and never before what was read before it.
int64_t Proxy::dueNs(Pipe& pipe, int64_t read_ns) {
  const int64_t jitter_ns = jitter_ns_ > 0 ? rng_.uniform(-jitter_ns_, jitter_ns_) : 0;
  pipe.last_due_ns = std::max(read_ns + latency_ns_ + jitter_ns, pipe.last_due_ns);
  return pipe.last_due_ns;
}

std::string Proxy::forwardEofIfDue(const Flow& f, int64_t now_ns) {
  Pipe& p = f.pipe;
  if (!p.source_eof || p.eof_forwarded || !p.queue.empty() || now_ns < p.eof_due_ns || !f.sink_connected) return "";
  if (shutdown(f.sink.fd, SHUT_WR) != 0) return std::string(f.name) + " shutdown: " + errorText(errno);
  p.eof_forwarded = true;
  return "";
}

// When this flow can next make progress on its own; kNever when only an event (or the schedule) can help.
int64_t Proxy::flowWakeNs(const Flow& f, int64_t now_ns) {
  const Pipe& p = f.pipe;
  int64_t wake_ns = kNever;
  if (f.sink_connected && !p.queue.empty()) {
    const int64_t due_ns = p.queue.front().due_ns;
    if (due_ns > now_ns) {
      wake_ns = due_ns;
    } else if (f.sink.writable) {
      wake_ns = now_ns;  // the pass ran out of budget
    }
  }
  if (mayRead(f)) wake_ns = std::min(wake_ns, f.bucket.readyAtNs(now_ns));
  if (f.sink_connected && p.source_eof && !p.eof_forwarded && p.queue.empty()) {
    wake_ns = std::min(wake_ns, std::max(now_ns, p.eof_due_ns));
  }
  return wake_ns;
}

bool Proxy::busy(const Pipe& pipe, const Endpoint& source) {
  return !pipe.queue.empty() || (source.readable && !pipe.source_eof) || (pipe.source_eof && !pipe.eof_forwarded);
}

void Proxy::abortConnection(uint64_t id, const std::string& reason, int64_t now_ns) {
  const auto it = connections_.find(id);
  if (it == connections_.end()) return;
  Connection& c = *it->second;
  resetAndClose(c.client.fd);
  resetAndClose(c.target.fd);
  log_.line(now_ns, "conn %llu reset: %s (up %llu B, down %llu B, %.3f s)", static_cast<unsigned long long>(id),
            reason.c_str(), static_cast<unsigned long long>(c.up.delivered_bytes),
            static_cast<unsigned long long>(c.down.delivered_bytes), nsToS(now_ns - c.opened_ns));
  pending_.erase(id);
  connections_.erase(it);
}

void Proxy::closeConnection(uint64_t id, int64_t now_ns) {
  const auto it = connections_.find(id);
  if (it == connections_.end()) return;
  Connection& c = *it->second;
  // Both FINs were read, so no unread data is left to turn this close into a RST.
  close(c.client.fd);
  close(c.target.fd);
  log_.line(now_ns, "conn %llu close (up %llu B, down %llu B, %.3f s)", static_cast<unsigned long long>(id),
            static_cast<unsigned long long>(c.up.delivered_bytes),
            static_cast<unsigned long long>(c.down.delivered_bytes), nsToS(now_ns - c.opened_ns));
  pending_.erase(id);
  connections_.erase(it);
}

int64_t Proxy::nextWakeNs(int64_t now_ns) const {
  int64_t wake_ns = std::min(connections_wake_ns_, schedule_.nextChangeAfterNs(now_ns));
  if (listener_ready_) wake_ns = std::min(wake_ns, std::max(now_ns, accept_retry_ns_));
  return wake_ns;
}

// Sleeps in epoll_wait until an event or `wake_ns`; the timerfd gives the wake-up nanosecond resolution, which
// epoll_wait's millisecond timeout would not. Returns 0, or 1 when epoll fails.
int Proxy::waitForEvents(int64_t wake_ns) {
  const bool due_now = wake_ns <= nowNs();
  if (!due_now) armTimer(wake_ns);
  int n = 0;
  do {
    n = epoll_wait(epoll_fd_, events_.data(), static_cast<int>(events_.size()), due_now ? 0 : -1);
  } while (n < 0 && errno == EINTR);
  if (n < 0) {
    std::fprintf(stderr, "link_impair: epoll_wait: %s\n", errorText(errno).c_str());
    return 1;
  }
  event_count_ = n;
  return 0;
}

void Proxy::armTimer(int64_t wake_ns) {
  if (wake_ns == timer_armed_ns_) return;
  itimerspec spec{};  // all zero disarms
  if (wake_ns != kNever) {
    const int64_t at_ns = start_mono_ns_ + wake_ns;
    spec.it_value.tv_sec = static_cast<time_t>(at_ns / kNsPerS);
    spec.it_value.tv_nsec = static_cast<long>(at_ns % kNsPerS);
  }
  timerfd_settime(timer_fd_, TFD_TIMER_ABSTIME, &spec, nullptr);
  timer_armed_ns_ = wake_ns;
}

void Proxy::printSummary() {
  std::printf(
      "link_impair: up_bytes=%llu down_bytes=%llu connections_accepted=%llu reset_by_cut=%llu refused_in_cut=%llu\n",
      static_cast<unsigned long long>(stats_.up_bytes), static_cast<unsigned long long>(stats_.down_bytes),
      static_cast<unsigned long long>(stats_.accepted), static_cast<unsigned long long>(stats_.reset_by_cut),
      static_cast<unsigned long long>(stats_.refused_in_cut));
  std::fflush(stdout);
}

}  // namespace

int main(int argc, char** argv) {
  Options options;
  bool wants_help = false;
  std::string error = parseCommandLine(argc, argv, options, wants_help);
  if (wants_help) {
    printUsage(stdout);
    return 0;
  }
  if (error.empty()) error = validate(options);
  if (!error.empty()) {
    std::fprintf(stderr, "link_impair: %s\n(link_impair --help lists the options)\n", error.c_str());
    return 2;
  }
  Proxy proxy(options);
  if (const int status = proxy.setUp(error); status != 0) {
    std::fprintf(stderr, "link_impair: %s\n", error.c_str());
    return status;
  }
  return proxy.run();
}

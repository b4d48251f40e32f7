// cvislam_state_monitor: reads an agent's live state topics (agent_rt/live/state_topics.hpp) as a flight controller
// or planner would, through the same iox-roudi, and prints the newest state now and then.
//
//   cvislam_state_monitor [--agent N] [--every S] [--quiet]
//
// Each health message (once a second) is printed as a line "health: ...". At the end (SIGINT, SIGTERM, or RouDi
// shutting down) it prints two lines of counts:
//   states: frames F (metric M, sequence gaps G), propagated P, latency p50/p99 frame A/B ms, imu C/D ms
//   health: H messages, the last at frames F
// Exit status: 0 done, 1 no iox-roudi.
#include <algorithm>
#include <atomic>
#include <csignal>
#include <cstdio>
#include <iostream>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "agent_rt/ipc/embedded_roudi.hpp"
#include "agent_rt/live/live_service.hpp"
#include "agent_rt/live/state_topics.hpp"
#include "common/core/percentile.hpp"
#include "common/core/steady_clock.hpp"
#include "iceoryx_posh/popo/subscriber.hpp"
#include "iceoryx_posh/popo/wait_set.hpp"

namespace {

using cvislam::agent::live::AgentStateMessage;
namespace live = cvislam::agent::live;

std::atomic<bool> g_stop{false};
extern "C" void onSignal(int /*signal*/) {
  g_stop.store(true);
}

struct Counts {
  std::uint64_t frames = 0;
  std::uint64_t metric = 0;
  std::uint64_t gaps = 0;
  std::uint64_t propagated = 0;
  std::int64_t next_sequence = -1;
  std::uint64_t health = 0;
  std::uint64_t health_frames = 0;  // the newest health message's frame count
  std::vector<double> frame_latency_ms;
  std::vector<double> imu_latency_ms;
};

double percentile(std::vector<double> v, double fraction) {
  std::sort(v.begin(), v.end());
  return cvislam::nearestRankPercentile(v, fraction);
}

const char* statusText(live::StateStatus status) {
  switch (status) {
    case live::StateStatus::kWaitingForMap:
      return "waiting for map";
    case live::StateStatus::kTracking:
      return "tracking";
    case live::StateStatus::kRelocalising:
      return "relocalising";
  }
  return "?";
}

void printState(const AgentStateMessage& m, const Counts& counts) {
  std::printf("t=%.3f s  %-15s %s  p=(%.3f %.3f %.3f) m  v=(%.2f %.2f %.2f) m/s  map %u  frames %llu  imu-rate %llu\n",
              static_cast<double>(m.t_ns) * 1e-9, statusText(m.status),
              (m.flags & live::kMetric) != 0U ? "metric" : "up to scale", m.p_w_s[0], m.p_w_s[1], m.p_w_s[2], m.v_w[0],
              m.v_w[1], m.v_w[2], m.map_id, static_cast<unsigned long long>(counts.frames),
              static_cast<unsigned long long>(counts.propagated));
  std::fflush(stdout);
}

void printHealth(const live::AgentHealthMessage& h) {
  std::printf("health: %-15s %5.1f fps  frames %llu (tracked %llu, lost %llu)  keyframes %llu, %d pending  IMU %s",
              statusText(h.status), h.frame_rate_hz, static_cast<unsigned long long>(h.frames),
              static_cast<unsigned long long>(h.tracked_frames), static_cast<unsigned long long>(h.lost_frames),
              static_cast<unsigned long long>(h.keyframes), h.pending_keyframes,
              (h.flags & live::kImuInitialised) != 0U ? "initialised" : "not yet");
  if ((h.flags & live::kLinkEnabled) != 0U) {
    std::printf("  link %s, %llu batches acknowledged, %llu keyframes waiting",
                (h.flags & live::kLinkConnected) != 0U ? "up" : "DOWN",
                static_cast<unsigned long long>(h.link_acked_batches),
                static_cast<unsigned long long>(h.link_keyframes_waiting));
  }
  std::printf("  CPU");
  for (std::uint32_t i = 0; i < live::kHealthThreadCount; ++i) {
    if (h.cpu_percent[i] >= 0.0) std::printf(" %s %.0f%%", live::kHealthThreads[i], h.cpu_percent[i]);
  }
  std::printf("\n");
  std::fflush(stdout);
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"cvislam_state_monitor: prints an agent's live state, read from its iceoryx state topics"};
  unsigned agent = 0;
  double every_s = 1.0;
  bool quiet = false;
  app.add_option("--agent", agent, "The agent's id (--agent-id of cvislam_agent) [0]");
  app.add_option("--every", every_s, "Seconds between printed states [1]")->check(CLI::PositiveNumber);
  app.add_flag("--quiet", quiet, "Print only the counts at the end");
  CLI11_PARSE(app, argc, argv);

  if (auto s = cvislam::agent::attachToExternalRouDi("cvislam_state_monitor_" + std::to_string(::getpid())); !s.ok()) {
    std::cerr << "cvislam_state_monitor: " << s.error().toString() << "\n";
    return 1;
  }
  std::signal(SIGINT, onSignal);
  std::signal(SIGTERM, onSignal);
  iox::popo::SubscriberOptions options;
  // Every queued state holds a chunk of RouDi's pool until it is read: a deep queue on a reader that stalls would
  // take chunks the agent needs. 64 is over 3 s of frames and 0.3 s of IMU-rate states.
  options.queueCapacity = 64;
  iox::popo::Subscriber<AgentStateMessage> frames(live::stateService(agent, live::kStateFramesEvent), options);
  iox::popo::Subscriber<AgentStateMessage> imu(live::stateService(agent, live::kStateImuEvent), options);
  iox::popo::Subscriber<live::AgentHealthMessage> health(live::stateService(agent, live::kStateHealthEvent), options);
  iox::popo::WaitSet<3> wait;
  if (wait.attachState(frames, iox::popo::SubscriberState::HAS_DATA).has_error() ||
      wait.attachState(imu, iox::popo::SubscriberState::HAS_DATA).has_error() ||
      wait.attachState(health, iox::popo::SubscriberState::HAS_DATA).has_error()) {
    std::cerr << "cvislam_state_monitor: iceoryx refused to wait on the state topics\n";
    return 1;
  }
  Counts counts;
  std::int64_t next_print_ns = 0;
  while (!g_stop.load()) {
    // The timeout only lets a signal in.
    (void)wait.timedWait(iox::units::Duration::fromMilliseconds(100));
    const std::int64_t now_ns = cvislam::steadyNowNs();
    const AgentStateMessage* newest = nullptr;
    AgentStateMessage copy;
    for (auto taken = frames.take(); !taken.has_error(); taken = frames.take()) {
      const AgentStateMessage& m = *taken.value();
      if (counts.next_sequence >= 0 && static_cast<std::int64_t>(m.sequence) != counts.next_sequence) ++counts.gaps;
      counts.next_sequence = static_cast<std::int64_t>(m.sequence) + 1;
      ++counts.frames;
      if ((m.flags & live::kMetric) != 0U) ++counts.metric;
      counts.frame_latency_ms.push_back(static_cast<double>(m.published_steady_ns - m.captured_steady_ns) * 1e-6);
      copy = m;
      newest = &copy;
    }
    for (auto taken = imu.take(); !taken.has_error(); taken = imu.take()) {
      const AgentStateMessage& m = *taken.value();
      ++counts.propagated;
      counts.imu_latency_ms.push_back(static_cast<double>(m.published_steady_ns - m.captured_steady_ns) * 1e-6);
      copy = m;
      newest = &copy;
    }
    for (auto taken = health.take(); !taken.has_error(); taken = health.take()) {
      ++counts.health;
      counts.health_frames = taken.value()->frames;
      if (!quiet) printHealth(*taken.value());
    }
    if (newest != nullptr && !quiet && now_ns >= next_print_ns) {
      printState(*newest, counts);
      next_print_ns = now_ns + static_cast<std::int64_t>(every_s * 1e9);
    }
  }
  std::printf(
      "states: frames %llu (metric %llu, sequence gaps %llu), propagated %llu, latency p50/p99 frame %.2f/%.2f ms, "
      "imu %.3f/%.3f ms\n",
      static_cast<unsigned long long>(counts.frames), static_cast<unsigned long long>(counts.metric),
      static_cast<unsigned long long>(counts.gaps), static_cast<unsigned long long>(counts.propagated),
      percentile(counts.frame_latency_ms, 0.5), percentile(counts.frame_latency_ms, 0.99),
      percentile(counts.imu_latency_ms, 0.5), percentile(counts.imu_latency_ms, 0.99));
  std::printf("health: %llu messages, the last at frames %llu\n", static_cast<unsigned long long>(counts.health),
              static_cast<unsigned long long>(counts.health_frames));
  return 0;
}

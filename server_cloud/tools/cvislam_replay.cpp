// cvislam_replay: streams recorded agent uplinks into servers, as the agents sent them: for scale-out tests and
// capacity benchmarks, where running the agents themselves would take more cores than the servers under test.
//
// The recording is a map store (SQLite) written by a server during a real mission: its records are exactly the
// Hellos and batches the agents sent, in order (server_cloud/store/map_store.hpp). Each recorded agent becomes
// one stream (a thread) that speaks the link protocol like the agent's link: Hello, then the batches from the
// Welcome's stored sequence on, paced by their sensor times (--rate 1: real time), resending after a reconnect
// what the server had not stored, and following a replica's redirect to the mission's owner.
//
// With --copies N each recorded agent flies N times at once, under new agent ids and in world frames of their own
// (server_cloud/replay/replay_copies.hpp), each copy starting --copy-delay seconds after the one before: a mission
// of many agents from a recording of a few.
//
//   cvislam_replay --recording rec.db --server 127.0.0.1:50051,127.0.0.1:50061 --mission m1 --report m1.json
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <map>
#include <mutex>
#include <optional>
#include <thread>
#include <vector>

#include <unistd.h>
#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "agent_rt/link/link_client.hpp"
#include "common/core/percentile.hpp"
#include "cvislam/v1/agent_link.pb.h"
#include "server_cloud/replay/replay_copies.hpp"
#include "server_cloud/store/sqlite_store.hpp"

namespace {

using Clock = std::chrono::steady_clock;
using cvislam::AgentId;
using cvislam::Status;

struct RecordedAgent {
  AgentId agent = 0;
  AgentId recorded_as = 0;  // the recording's id (differs for a copy)
  double start_delay_s = 0.0;
  cvislam::v1::AgentUplink hello;
  std::vector<cvislam::v1::AgentUplink> batches;  // batches[i] has sequence i + 1
};

struct AgentResult {
  AgentId agent = 0;
  std::uint64_t batches = 0;
  AgentId recorded_as = 0;
  std::uint64_t acked = 0;    // the newest sequence the server acknowledged
  std::uint64_t sent = 0;     // batch messages written (resends included)
  std::uint64_t streams = 0;  // Welcomes received
  std::uint64_t failed_attempts = 0;
  std::uint64_t redirects = 0;
  double longest_gap_s = 0.0;  // the longest time without a stream, after the first Welcome
  std::vector<double> ack_ms;  // per batch: first write to its acknowledgement
  std::string last_error;
  bool finished = false;
};

struct ReplayOptions {
  std::string server;
  std::string mission;
  std::string token;
  double rate = 1.0;  // of real time; 0: as fast as the server acknowledges
  double connect_timeout_s = 2.0;
  double flush_timeout_s = 60.0;
};

// Replays one agent; returns when every batch is acknowledged, or the flush timeout after the last one was sent.
AgentResult replayAgent(const RecordedAgent& recorded, const ReplayOptions& options) {
  AgentResult result;
  result.agent = recorded.agent;
  result.recorded_as = recorded.recorded_as;
  result.batches = recorded.batches.size();
  std::this_thread::sleep_for(std::chrono::duration<double>(recorded.start_delay_s));
  cvislam::agent::LinkClientOptions client_options;
  client_options.server = options.server;
  client_options.token = options.token;
  client_options.connect_timeout = std::chrono::milliseconds(static_cast<int>(options.connect_timeout_s * 1000));
  cvislam::agent::LinkClient client(client_options);

  cvislam::v1::AgentUplink hello = recorded.hello;
  hello.mutable_hello()->set_mission(options.mission);
  hello.mutable_hello()->set_agent_id(recorded.agent);
  // A session number of this process: a reconnect takes over its own stream.
  hello.mutable_hello()->set_session(
      (static_cast<std::uint64_t>(::getpid()) << 40U) ^
      (static_cast<std::uint64_t>(Clock::now().time_since_epoch().count()) + recorded.agent));
  const std::int64_t t0_ns = recorded.batches.empty() ? 0 : recorded.batches.front().batch().sensor_time_ns();
  const auto start = Clock::now();
  const auto due = [&](std::size_t index) {
    if (!(options.rate > 0.0)) return start;
    const double dt_s = 1e-9 * static_cast<double>(recorded.batches[index].batch().sensor_time_ns() - t0_ns);
    return start + std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(dt_s / options.rate));
  };
  std::vector<Clock::time_point> first_sent(recorded.batches.size());
  std::vector<bool> was_sent(recorded.batches.size(), false);
  std::uint64_t next = 1;
  bool connected = false;
  auto backoff = std::chrono::milliseconds(100);
  Clock::time_point disconnected_at{};  // valid while `disconnected`
  bool disconnected = false;
  std::optional<Clock::time_point> all_sent_at;
  cvislam::v1::ServerDownlink down;

  while (true) {
    const auto now = Clock::now();
    if (!connected) {
      hello.mutable_hello()->set_last_acked_sequence(result.acked);
      auto welcome = client.connect(hello);
      result.redirects = client.redirects();
      if (!welcome) {
        ++result.failed_attempts;
        result.last_error = welcome.error().message();
        if (result.failed_attempts % 10 == 1) {
          std::fprintf(stderr, "[replay] agent %u of '%s': %s (attempt %llu; trying on)\n",
                       static_cast<unsigned>(recorded.agent), options.mission.c_str(), result.last_error.c_str(),
                       static_cast<unsigned long long>(result.failed_attempts));
        }
        if (!disconnected && result.streams > 0) {
          disconnected = true;
          disconnected_at = now;
        }
        std::this_thread::sleep_for(backoff);
        backoff = std::min(backoff * 2, std::chrono::milliseconds(1000));
        continue;
      }
      connected = true;
      backoff = std::chrono::milliseconds(100);
      ++result.streams;
      if (disconnected) {
        result.longest_gap_s =
            std::max(result.longest_gap_s, std::chrono::duration<double>(Clock::now() - disconnected_at).count());
        disconnected = false;
      }
      const std::uint64_t stored = (*welcome)->welcome().stored_sequence();
      result.acked = std::max(result.acked, stored);
      next = stored + 1;
    }
    // Acknowledgements.
    while (client.poll(down)) {
      const std::uint64_t acked = down.acked_sequence();
      const auto arrived = Clock::now();
      for (std::uint64_t s = result.acked + 1; s <= acked && s <= recorded.batches.size(); ++s) {
        if (was_sent[s - 1]) {
          result.ack_ms.push_back(std::chrono::duration<double, std::milli>(arrived - first_sent[s - 1]).count());
        }
      }
      result.acked = std::max(result.acked, acked);
    }
    if (!client.connected()) {
      connected = false;
      result.last_error = client.lastError();
      disconnected = true;
      disconnected_at = Clock::now();
      continue;
    }
    if (result.acked >= recorded.batches.size()) break;
    if (next <= recorded.batches.size() && Clock::now() >= due(next - 1)) {
      if (!client.send(recorded.batches[next - 1])) {
        connected = false;
        result.last_error = client.lastError();
        disconnected = true;
        disconnected_at = Clock::now();
        continue;
      }
      if (!was_sent[next - 1]) {
        was_sent[next - 1] = true;
        first_sent[next - 1] = Clock::now();
      }
      ++result.sent;
      ++next;
      continue;
    }
    if (next > recorded.batches.size()) {
      if (!all_sent_at) all_sent_at = Clock::now();
      if (Clock::now() - *all_sent_at > std::chrono::duration<double>(options.flush_timeout_s)) break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  if (connected) {
    cvislam::v1::AgentUplink goodbye;
    goodbye.mutable_goodbye()->set_end_of_mission(true);
    client.send(goodbye);
    (void)client.close(std::chrono::milliseconds(2000));
  }
  result.finished = result.acked >= recorded.batches.size();
  return result;
}

nlohmann::json toJson(const AgentResult& r) {
  std::vector<double> sorted = r.ack_ms;
  std::sort(sorted.begin(), sorted.end());
  nlohmann::json j = {{"agent", r.agent},
                      {"recorded_agent", r.recorded_as},
                      {"batches", r.batches},
                      {"acked", r.acked},
                      {"sent", r.sent},
                      {"streams", r.streams},
                      {"failed_attempts", r.failed_attempts},
                      {"redirects", r.redirects},
                      {"longest_gap_s", r.longest_gap_s},
                      {"finished", r.finished},
                      {"last_error", r.last_error}};
  if (!sorted.empty()) {
    j["ack_ms_p50"] = cvislam::nearestRankPercentile(sorted, 0.5);
    j["ack_ms_p99"] = cvislam::nearestRankPercentile(sorted, 0.99);
    j["ack_ms_max"] = sorted.back();
  }
  j["ack_ms"] = r.ack_ms;  // per batch, in sequence order
  return j;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "cvislam_replay: streams the agent uplinks recorded in a map store into cvislam servers, one stream per "
      "recorded agent, as the agents sent them (scale-out tests, capacity benchmarks)"};
  std::string recording;
  std::string from_mission;
  std::string report;
  std::vector<unsigned> only_agents;
  ReplayOptions options;
  app.add_option("--recording", recording, "Map store (SQLite) a server wrote during a mission (--store)")->required();
  app.add_option("--from-mission", from_mission, "The recorded mission to replay [the only one in the recording]");
  app.add_option("--server", options.server, "host:port of the server, or of several replicas, comma-separated")
      ->required();
  app.add_option("--mission", options.mission, "The mission name to send [--from-mission]");
  app.add_option("--agents", only_agents, "Replay only these recorded agent ids [all]");
  app.add_option("--rate", options.rate, "Pace as a multiple of real time (batch sensor times); 0: no pacing [1]");
  double seconds = 0.0;
  app.add_option("--seconds", seconds,
                 "Replay only each agent's first S seconds of sensor time (a shorter benchmark step); 0: all [0]")
      ->check(CLI::NonNegativeNumber);
  cvislam::server::replay::CopyOptions copies;
  double copy_delay_s = 1.0;
  app.add_option("--copies", copies.copies,
                 "Fly each recorded agent N times at once: copy k under agent id (recorded id + k * (largest "
                 "recorded id + 1)), in its own world frame (turned k * 0.6 rad about gravity, moved k * (4, -3, 0) "
                 "m) [1]")
      ->check(CLI::Range(1, 1000));
  app.add_option("--copy-delay", copy_delay_s, "Seconds between the starts of successive copies [1]")
      ->check(CLI::NonNegativeNumber);
  app.add_option("--token", options.token, "The mission's token [none]");
  app.add_option("--flush-timeout", options.flush_timeout_s,
                 "Seconds to wait for the last acknowledgements after the last batch was sent [60]");
  app.add_option("--report", report,
                 "Write a JSON report here (per agent: acknowledged, streams, redirects, "
                 "acknowledgement latency p50/p99)");
  CLI11_PARSE(app, argc, argv);
  if (options.rate < 0.0 || !std::isfinite(options.rate)) {
    std::cerr << "cvislam_replay: --rate must be >= 0\n";
    return 2;
  }

  cvislam::server::SqliteStoreOptions store_options;
  store_options.path = recording;
  store_options.create_if_missing = false;
  store_options.check_on_open = false;
  store_options.read_only = true;  // several replay clients read one recording
  auto store = cvislam::server::openSqliteStore(store_options);
  if (!store) {
    std::cerr << "cvislam_replay: --recording: " << store.error().message() << "\n";
    return 2;
  }
  if (from_mission.empty()) {
    auto missions = (*store)->missions();
    if (!missions || missions->size() != 1) {
      std::cerr << "cvislam_replay: give --from-mission: the recording holds "
                << (missions ? std::to_string(missions->size()) : std::string("unreadable")) << " missions\n";
      return 2;
    }
    from_mission = missions->front();
  }
  if (options.mission.empty()) options.mission = from_mission;

  std::map<AgentId, RecordedAgent> agents;
  Status read = (*store)->replay(from_mission, [&](const cvislam::server::StoreRecord& r) -> Status {
    if (!only_agents.empty() && std::find(only_agents.begin(), only_agents.end(), r.agent) == only_agents.end()) {
      return Status::Ok();
    }
    RecordedAgent& a = agents[r.agent];
    a.agent = r.agent;
    cvislam::v1::AgentUplink message;
    const bool parsed = r.kind == cvislam::server::StoreRecord::Kind::kHello
                            ? message.mutable_hello()->ParseFromString(r.body)
                            : message.mutable_batch()->ParseFromString(r.body);
    if (!parsed)
      return cvislam::Error{cvislam::ErrorCode::kDataError, "record " + std::to_string(r.number) + " does not parse"};
    if (r.kind == cvislam::server::StoreRecord::Kind::kHello) {
      if (!a.hello.has_hello()) a.hello = std::move(message);
    } else if (r.sequence == a.batches.size() + 1) {
      a.batches.push_back(std::move(message));
    }
    return Status::Ok();
  });
  store->reset();  // the recording is read: let it go
  if (!read.ok()) {
    std::cerr << "cvislam_replay: reading " << recording << ": " << read.error().message() << "\n";
    return 2;
  }
  if (agents.empty()) {
    std::cerr << "cvislam_replay: mission '" << from_mission << "' of " << recording << " has no agents to replay\n";
    return 2;
  }
  if (seconds > 0.0) {
    for (auto& [id, a] : agents) {
      if (a.batches.empty()) continue;
      const std::int64_t t0_ns = a.batches.front().batch().sensor_time_ns();
      const auto late = std::find_if(a.batches.begin(), a.batches.end(), [&](const cvislam::v1::AgentUplink& b) {
        return 1e-9 * static_cast<double>(b.batch().sensor_time_ns() - t0_ns) > seconds;
      });
      a.batches.erase(late, a.batches.end());
    }
  }
  for (auto& [id, a] : agents) a.recorded_as = id;
  if (copies.copies > 1) {
    copies.id_stride = static_cast<AgentId>(agents.rbegin()->first + 1);
    const int largest = agents.rbegin()->first + (copies.copies - 1) * copies.id_stride;
    if (largest > 0xFFFF) {
      std::cerr << "cvislam_replay: --copies " << copies.copies << " would give agent id " << largest
                << ", over 65535: give fewer copies\n";
      return 2;
    }
    std::map<AgentId, RecordedAgent> flown;
    for (const auto& [id, recorded] : agents) {
      for (int k = 0; k < copies.copies; ++k) {
        RecordedAgent copy = recorded;
        copy.agent = cvislam::server::replay::copyAgentId(id, k, copies);
        copy.start_delay_s = k * copy_delay_s;
        for (cvislam::v1::AgentUplink& b : copy.batches) {
          cvislam::server::replay::moveToCopyWorld(*b.mutable_batch(), k, copies);
        }
        flown.emplace(copy.agent, std::move(copy));
      }
    }
    agents = std::move(flown);
  }
  std::size_t total = 0;
  for (const auto& [id, a] : agents) total += a.batches.size();
  std::fprintf(stderr, "[replay] mission '%s' as '%s': %zu agents, %zu batches, rate %.2f, into %s\n",
               from_mission.c_str(), options.mission.c_str(), agents.size(), total, options.rate,
               options.server.c_str());

  std::vector<AgentResult> results(agents.size());
  std::vector<std::thread> threads;
  std::size_t index = 0;
  for (const auto& [id, a] : agents) {
    threads.emplace_back([&, i = index++, &recorded = a] { results[i] = replayAgent(recorded, options); });
  }
  for (auto& t : threads) t.join();

  bool all = true;
  nlohmann::json j = {{"mission", options.mission}, {"recording", recording}, {"rate", options.rate}};
  for (const AgentResult& r : results) {
    all = all && r.finished;
    j["agents"].push_back(toJson(r));
    std::fprintf(stderr,
                 "[replay] agent %u: %llu of %llu batches acknowledged, %llu streams, %llu redirects, longest gap "
                 "%.2f s%s%s\n",
                 static_cast<unsigned>(r.agent), static_cast<unsigned long long>(r.acked),
                 static_cast<unsigned long long>(r.batches), static_cast<unsigned long long>(r.streams),
                 static_cast<unsigned long long>(r.redirects), r.longest_gap_s,
                 r.finished ? "" : "; last error: ", r.finished ? "" : r.last_error.c_str());
  }
  j["finished"] = all;
  if (!report.empty()) std::ofstream(report) << j.dump(2) << "\n";
  return all ? 0 : 1;
}

// bench_store_ingest: what durability costs ingest. Batches go through the server core's agent sessions (no gRPC,
// no workers) with the map store off (maps in memory only) and on at each sync level; per level: keyframes per
// second over the whole feed, and the time per batch (ingest plus the store's commit) p50 / p99, over
// `--repetitions` feeds, each into a fresh core and a fresh store file.
//
// The batches are either a mission's real uplinks, read from a map store the main job wrote
// (--from-store out/mission/store.db: every agent's Hello and batches in the order the server accepted them), or
// SYNTHETIC ones (test/server_cloud/link_messages: 50 keypoints per keyframe, --keyframes-per-batch).
//
//   bench_store_ingest [--from-store FILE | --batches 400 --keyframes-per-batch 2] [--repetitions 5] [--json OUT]
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "cvislam/v1/agent_link.pb.h"
#include "server_cloud/core/server_core.hpp"
#include "server_cloud/store/sqlite_store.hpp"
#include "test/bench/percentiles.hpp"
#include "test/server_cloud/link_messages.hpp"
#include "test/support/temp_dir.hpp"

namespace {

using Clock = std::chrono::steady_clock;
namespace v1 = cvislam::v1;
using cvislam::server::StoreRecord;

struct Feed {
  std::vector<StoreRecord> records;  // Hellos and batches in order
  std::size_t keyframes = 0;
  std::size_t bytes = 0;
  std::string source;
};

Feed syntheticFeed(int batches, int keyframes_per_batch) {
  Feed feed;
  feed.source = "SYNTHETIC: " + std::to_string(batches) + " batches of " + std::to_string(keyframes_per_batch) +
                " keyframes (50 keypoints each), one agent";
  feed.records.push_back({0, StoreRecord::Kind::kHello, "bench", 1, 0,
                          cvislam::server::test::makeHello("bench", 1, 42).SerializeAsString()});
  for (int b = 0; b < batches; ++b) {
    const auto first = static_cast<std::uint32_t>(b * keyframes_per_batch);
    auto batch = cvislam::server::test::makeKeyframeBatch(static_cast<std::uint64_t>(b + 1), first,
                                                          static_cast<std::uint32_t>(keyframes_per_batch));
    feed.records.push_back(
        {0, StoreRecord::Kind::kBatch, "bench", 1, static_cast<std::uint64_t>(b + 1), batch.SerializeAsString()});
    feed.keyframes += static_cast<std::size_t>(keyframes_per_batch);
  }
  return feed;
}

cvislam::Result<Feed> recordedFeed(const std::string& path) {
  cvislam::server::SqliteStoreOptions o;
  o.path = path;
  o.create_if_missing = false;
  auto store = cvislam::server::openSqliteStore(o);
  if (!store) return store.error();
  Feed feed;
  feed.source = "recorded uplinks of " + path;
  std::map<std::pair<std::string, cvislam::AgentId>, bool> greeted;
  cvislam::Status s = (*store)->replay("", [&](const StoreRecord& r) {
    if (r.kind == StoreRecord::Kind::kHello) {
      if (greeted[{r.mission, r.agent}]) return cvislam::Status::Ok();  // reconnects: one stream here
      greeted[{r.mission, r.agent}] = true;
    } else {
      v1::MapBatch batch;
      if (batch.ParseFromString(r.body)) feed.keyframes += static_cast<std::size_t>(batch.keyframes_size());
    }
    feed.records.push_back(r);
    return cvislam::Status::Ok();
  });
  if (!s.ok()) return s.error();
  return feed;
}

struct Level {
  std::string name;
  bool store = false;
  cvislam::server::SqliteStoreOptions::Sync sync = cvislam::server::SqliteStoreOptions::Sync::kFull;
};

}  // namespace

int main(int argc, char** argv) {
  std::string from_store;
  int batches = 400;
  int keyframes_per_batch = 2;
  int repetitions = 5;
  std::string json_path;
  CLI::App app{"bench_store_ingest: ingest throughput with the map store off and on (sync off, normal, full)"};
  app.add_option("--from-store", from_store, "Feed a mission's recorded uplinks from this map store (read only)");
  app.add_option("--batches", batches, "SYNTHETIC batches [400]")->check(CLI::Range(1, 1000000));
  app.add_option("--keyframes-per-batch", keyframes_per_batch, "SYNTHETIC keyframes per batch [2]")
      ->check(CLI::Range(1, 1000));
  app.add_option("--repetitions", repetitions, "Feeds per level [5]")->check(CLI::Range(1, 1000));
  app.add_option("--json", json_path, "Also write the figures here");
  CLI11_PARSE(app, argc, argv);

  Feed feed;
  if (!from_store.empty()) {
    auto recorded = recordedFeed(from_store);
    if (!recorded) {
      std::cerr << "bench_store_ingest: " << recorded.error().message() << "\n";
      return 1;
    }
    feed = std::move(recorded).value();
  } else {
    feed = syntheticFeed(batches, keyframes_per_batch);
  }
  for (const auto& r : feed.records) feed.bytes += r.body.size();
  std::printf("bench_store_ingest: %s; %zu records, %zu keyframes, %.2f MB; %d feeds per level\n", feed.source.c_str(),
              feed.records.size(), feed.keyframes, static_cast<double>(feed.bytes) / 1e6, repetitions);

  using Sync = cvislam::server::SqliteStoreOptions::Sync;
  const std::vector<Level> levels = {{"no store", false, Sync::kOff},
                                     {"store, sync off", true, Sync::kOff},
                                     {"store, sync normal", true, Sync::kNormal},
                                     {"store, sync full", true, Sync::kFull}};
  nlohmann::json out = {{"source", feed.source}, {"keyframes", feed.keyframes}, {"bytes", feed.bytes}};
  std::printf("%-20s %14s %14s %12s %12s\n", "level", "keyframes/s", "batches/s", "batch p50", "batch p99");
  for (const Level& level : levels) {
    std::vector<double> batch_ms;
    std::vector<double> keyframes_per_s;
    std::vector<double> batches_per_s;
    for (int rep = 0; rep < repetitions; ++rep) {
      cvislam::test::TempDir dir;
      cvislam::server::ServerOptions options;
      options.recognition.enabled = false;
      options.backend.enabled = false;
      cvislam::server::ServerCore core(options);
      if (level.store) {
        cvislam::server::SqliteStoreOptions o;
        o.path = dir / "bench.db";
        o.sync = level.sync;
        auto store = cvislam::server::openSqliteStore(o);
        if (!store || !core.attachStore(std::move(store).value()).ok()) {
          std::cerr << "bench_store_ingest: cannot open a store in " << dir.path() << "\n";
          return 1;
        }
      }
      std::map<std::pair<std::string, cvislam::AgentId>, std::unique_ptr<cvislam::server::AgentSession>> sessions;
      v1::AgentUplink message;
      v1::ServerDownlink reply;
      bool reply_due = false;
      std::size_t batch_count = 0;
      const auto start = Clock::now();
      for (const StoreRecord& r : feed.records) {
        auto& session = sessions[{r.mission, r.agent}];
        if (!session) session = core.openSession({});
        message.Clear();
        const bool parsed = r.kind == StoreRecord::Kind::kHello ? message.mutable_hello()->ParseFromString(r.body)
                                                                : message.mutable_batch()->ParseFromString(r.body);
        if (!parsed) {
          std::cerr << "bench_store_ingest: record " << r.number << " does not parse\n";
          return 1;
        }
        const auto t0 = Clock::now();
        const cvislam::Status s = session->handle(message, r.body.size(), reply, reply_due);
        if (!s.ok()) {
          std::cerr << "bench_store_ingest: record " << r.number << ": " << s.error().toString() << "\n";
          return 1;
        }
        if (r.kind == StoreRecord::Kind::kBatch) {
          batch_ms.push_back(std::chrono::duration<double, std::milli>(Clock::now() - t0).count());
          ++batch_count;
        }
      }
      const double seconds = std::chrono::duration<double>(Clock::now() - start).count();
      keyframes_per_s.push_back(static_cast<double>(feed.keyframes) / seconds);
      batches_per_s.push_back(static_cast<double>(batch_count) / seconds);
    }
    const double kf_s = cvislam::bench::percentile(keyframes_per_s, 0.5);
    const double b_s = cvislam::bench::percentile(batches_per_s, 0.5);
    const double p50 = cvislam::bench::percentile(batch_ms, 0.5);
    const double p99 = cvislam::bench::percentile(batch_ms, 0.99);
    std::printf("%-20s %14.0f %14.0f %9.2f ms %9.2f ms\n", level.name.c_str(), kf_s, b_s, p50, p99);
    out["levels"].push_back({{"level", level.name},
                             {"keyframes_per_s_median", kf_s},
                             {"batches_per_s_median", b_s},
                             {"batch_p50_ms", p50},
                             {"batch_p99_ms", p99},
                             {"feeds", repetitions}});
  }
  if (!json_path.empty()) std::ofstream(json_path) << out.dump(2) << "\n";
  return 0;
}

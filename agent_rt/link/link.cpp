#include "agent_rt/link/link.hpp"

#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>
#include <random>
#include <thread>
#include <vector>

#include <google/protobuf/arena.h>
#include <nlohmann/json.hpp>

#include "agent_rt/link/anchor_decoder.hpp"
#include "agent_rt/link/link_client.hpp"
#include "common/core/text.hpp"
#include "common/trace/trace.hpp"
#include "cvislam/v1/agent_link.pb.h"
#include "proto/wire/wire.hpp"

namespace cvislam::agent {

using Clock = std::chrono::steady_clock;

namespace {

void writeLivePose(const LivePose& pose, v1::LivePose& out) {
  out.set_t_ns(pose.t_ns);
  out.set_agent_map(pose.map_id);
  const Eigen::Vector3d& p = pose.T_w_s.translation();
  const Eigen::Quaterniond& q = pose.T_w_s.so3().quaternion();
  for (double v : {p.x(), p.y(), p.z()}) out.add_p_w_s(static_cast<float>(v));
  for (double v : {q.x(), q.y(), q.z(), q.w()}) out.add_q_w_s(static_cast<float>(v));
  out.set_metric(pose.metric);
}

}  // namespace

Status LinkOptions::validate() const {
  const auto bad = [](const std::string& what) { return Error{ErrorCode::kInvalidArgument, "link: " + what}; };
  if (server.empty()) return Status::Ok();
  for (const std::string& one : splitServerList(server)) {
    if (one.find(':') == std::string::npos)
      return bad("server '" + one + "': give host:port (or several, comma-separated)");
  }
  if (mission.empty()) return bad("mission must not be empty");
  if (!token.empty() && !text::isPrintableToken(token)) {
    return bad("the token may hold printable ASCII characters only, without spaces");
  }
  if (!(max_rate_hz > 0.0) || max_rate_hz > 100.0) return bad("max_rate_hz must be in (0, 100]");
  if (max_batch_bytes < kMinBatchBytes) return bad("max_batch_bytes must be at least 16 KiB");
  if (!(reconnect_min_s > 0.0) || reconnect_max_s < reconnect_min_s) {
    return bad("reconnect times must satisfy 0 < reconnect_min_s <= reconnect_max_s");
  }
  if (!(connect_timeout_s > 0.0) || !(flush_timeout_s >= 0.0)) return bad("timeouts must be positive");
  if (keepalive_ms < 100) return bad("keepalive_ms must be >= 100");
  if (keepalive_timeout_ms < 100) return bad("keepalive_timeout_ms must be >= 100");
  if (Status s = pacer.validate(); !s.ok()) return s;
  return store.validate();
}

struct Link::Impl {
  struct TimelineRow {
    double t_s;
    std::uint64_t up_bytes;
    std::uint64_t down_bytes;
    bool connected;
    std::size_t keyframes_waiting;
    std::size_t unacked_bytes;
    std::size_t window_bytes;
  };

  Impl(const LinkOptions& o, AgentId a)
      : options(o),
        agent(a),
        store(a, o.store),
        pacer(o.pacer),
        client(LinkClientOptions{o.server, o.keepalive_ms, o.keepalive_timeout_ms,
                                 std::chrono::milliseconds(static_cast<int>(o.connect_timeout_s * 1000)), 16U << 20U,
                                 o.token, o.tls_ca_pem}) {
    timeline.reserve(4096);
  }

  LinkOptions options;
  AgentId agent;
  LinkStore store;
  UplinkPacer pacer;
  LinkClient client;
  v1::AgentUplink hello;
  v1::AgentUplink goodbye;
  v1::ServerDownlink downlink;
  std::vector<char> arena_block;
  google::protobuf::Arena arena;
  v1::AgentUplink* uplink = nullptr;  // on `arena`
  // Where the covisible map is decoded when no sink takes it (a megabyte: allocated once, when first needed).
  std::unique_ptr<AnchorMessage> scratch_anchors;
  std::uint64_t covisible_accepted = 0;
  std::uint64_t covisible_refused = 0;
  std::string covisible_last_refusal;
  std::uint64_t corrections_refused = 0;
  std::uint64_t anchors_published = 0;
  std::uint64_t anchors_dropped = 0;
  std::uint32_t streams = 0;

  // The server's covisible map and corrections: checked, and passed on to mapping through `sink`.
  void passDown(const v1::ServerDownlink& down, AnchorSink* sink) {
    const bool covisible = down.has_covisible();
    if (!covisible && down.corrected_keyframes_size() == 0) return;
    AnchorMessage* out = sink != nullptr ? sink->loan() : nullptr;
    if (sink != nullptr && out == nullptr) ++anchors_dropped;
    if (out == nullptr) {
      if (!scratch_anchors) scratch_anchors = std::make_unique<AnchorMessage>();
      out = scratch_anchors.get();
    }
    out->stream = streams;
    out->sequence = down.sequence();
    // Without a covisible map, the empty one: the message's counts are cleared all the same.
    const Status decoded =
        decodeCovisibleMap(covisible ? down.covisible() : v1::CovisibleMap::default_instance(), down.sequence(), *out);
    out->has_covisible = covisible && decoded.ok() ? 1 : 0;
    if (covisible) ++(decoded.ok() ? covisible_accepted : covisible_refused);
    if (!decoded.ok()) covisible_last_refusal = decoded.error().message();
    bool any = out->has_covisible != 0;
    if (Status c = decodeCorrections(down.corrected_keyframes(), agent, *out); !c.ok()) {
      ++corrections_refused;
      covisible_last_refusal = c.error().message();
    }
    any = any || out->correction_count > 0;
    if (sink == nullptr || out == scratch_anchors.get()) return;
    if (any) {
      out->publish_steady_ns =
          std::chrono::duration_cast<std::chrono::nanoseconds>(Clock::now().time_since_epoch()).count();
      sink->publish();
      ++anchors_published;
    } else {
      sink->discard();
    }
  }

  void resetArena() {
    uplink = nullptr;
    arena.Reset();
  }
  using ByKind = std::map<std::string, std::pair<std::uint64_t, std::uint64_t>>;  // kind -> (messages, bytes)
  ByKind up_by_kind;
  ByKind down_by_kind;
  std::vector<TimelineRow> timeline;
  Clock::time_point start = Clock::now();
  double flush_wait_s = 0.0;

  mutable std::mutex status_mutex;
  LinkStatus status;  // guarded by status_mutex

  static void count(ByKind& by_kind, const std::string& kind, std::uint64_t n, std::uint64_t bytes) {
    auto& c = by_kind[kind];
    c.first += n;
    c.second += bytes;
  }

  void countBatch(const v1::MapBatch& b, std::uint64_t bytes) {
    count(up_by_kind, "message", 1, bytes);
    count(up_by_kind, "batch", 1, bytes);
    for (const wire::BatchPart& part : wire::batchParts(b)) count(up_by_kind, part.kind, part.count, part.bytes);
  }

  static std::uint64_t messageBytes(const ByKind& by_kind) {
    auto it = by_kind.find("message");
    return it == by_kind.end() ? 0 : it->second.second;
  }

  void addTimelineRow(Clock::time_point now, bool connected) {
    const LinkBacklog b = store.backlog();
    timeline.push_back({std::chrono::duration<double>(now - start).count(), messageBytes(up_by_kind),
                        messageBytes(down_by_kind), connected, b.keyframes_unsent + b.keyframes_unacked,
                        pacer.inFlightBytes(), pacer.windowBytes()});
  }

  // Publishes a copy for other threads; everything is computed before the lock is taken.
  void publishStatus(bool connected, bool flushed, std::uint64_t sent_sequence) {
    const LinkBacklog backlog = store.backlog();
    const std::uint64_t up = messageBytes(up_by_kind);
    const std::uint64_t down = messageBytes(down_by_kind);
    std::string error = connected ? std::string() : client.lastError();
    std::lock_guard lock(status_mutex);
    status.connected = connected;
    status.last_error.swap(error);
    status.backlog = backlog;
    status.store = store.counters();
    status.acked_sequence = store.acked();
    status.sent_sequence = sent_sequence;
    status.flushed = flushed;
    status.up_bytes = up;
    status.down_bytes = down;
    status.covisible_accepted = covisible_accepted;
    status.covisible_refused = covisible_refused;
    status.covisible_last_refusal = covisible_last_refusal;
    status.corrections_refused = corrections_refused;
    status.anchor_messages_published = anchors_published;
    status.anchor_messages_dropped = anchors_dropped;
    status.unacked_bytes = pacer.inFlightBytes();
    status.window_bytes = pacer.windowBytes();
    status.uplink_rate_bytes_per_s = pacer.rateBytesPerS();
  }
};

Result<std::unique_ptr<Link>> Link::create(const LinkOptions& options, AgentId agent, const LinkSensors& sensors) {
  if (options.server.empty()) return Error{ErrorCode::kInvalidArgument, "link: no server given"};
  if (Status s = options.validate(); !s.ok()) return s.error();
  auto impl = std::make_unique<Impl>(options, agent);
  v1::Hello& hello = *impl->hello.mutable_hello();
  hello.set_protocol_version(wire::kProtocolVersion);
  hello.set_mission(options.mission);
  hello.set_agent_id(agent);
  // A number of this process, different for every run: a reconnect of this process takes over its old stream,
  // another process claiming the same agent id is refused. Random, so that no one who knows the process can
  // guess it and take the agent's stream over.
  std::random_device entropy;
  hello.set_session((static_cast<std::uint64_t>(entropy()) << 32U) ^ entropy());
  hello.set_mode(sensors.stereo ? v1::SENSOR_MODE_STEREO : v1::SENSOR_MODE_MONO);
  hello.set_uses_imu(sensors.uses_imu);
  hello.set_local_map_keyframes(options.local_map_keyframes);
  wire::toProto(sensors.cam0, sensors.T_s_c0, hello.mutable_cam0());
  if (sensors.stereo && sensors.cam1) wire::toProto(*sensors.cam1, sensors.T_s_c1, hello.mutable_cam1());
  if (sensors.uses_imu) wire::toProto(sensors.imu_noise, sensors.imu_rate_hz, hello.mutable_imu());
  hello.set_software("cvislam_agent 0.1.0");
  return std::unique_ptr<Link>(new Link(std::move(impl)));
}

Link::Link(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Link::~Link() = default;

void Link::run(DeltaSource& source, const std::atomic<bool>& stop, AnchorSink* anchors, PoseSource* poses) {
  Impl& s = *impl_;
  const auto seconds = [](double v) {
    return std::chrono::duration_cast<Clock::duration>(std::chrono::duration<double>(v));
  };
  const auto period = seconds(1.0 / s.options.max_rate_hz);
  const auto backoff_min = seconds(s.options.reconnect_min_s);
  const auto backoff_max = seconds(s.options.reconnect_max_s);
  auto backoff = backoff_min;
  auto next_attempt = Clock::now();
  auto next_build = Clock::now();
  auto next_sample = Clock::now();
  auto next_status = Clock::now();
  std::optional<Clock::time_point> stop_at;
  std::uint64_t next_sequence = 1;
  std::uint64_t last_sent = 0;
  bool connected = false;
  bool nothing_due = false;
  bool flushed = false;

  while (true) {
    // Read the stop request before draining: a delta published before it is then always applied.
    const bool stopping = stop.load();
    for (const MapDeltaMessage* d = source.next(); d != nullptr; d = source.next()) {
      s.store.onDelta(*d);
      source.release();
      nothing_due = false;
      next_build = std::min(next_build, Clock::now());
    }
    const auto now = Clock::now();
    if (stopping && !stop_at) stop_at = now;
    flushed = connected && nothing_due && s.store.acked() >= last_sent;
    if (stop_at) {
      const double waited = std::chrono::duration<double>(now - *stop_at).count();
      if (flushed || waited >= s.options.flush_timeout_s) {
        s.flush_wait_s = waited;
        break;
      }
    }

    if (!connected && now >= next_attempt) {
      s.hello.mutable_hello()->set_last_acked_sequence(s.store.acked());
      auto welcome = s.client.connect(s.hello);
      if (welcome) {
        connected = true;
        ++s.streams;
        const std::uint64_t stored = (*welcome)->welcome().stored_sequence();
        s.store.onWelcome(stored, (*welcome)->welcome().resend_from_sequence());
        s.pacer.onReconnect();
        next_sequence = stored + 1;
        last_sent = std::min(last_sent, stored);
        backoff = backoff_min;
        nothing_due = false;
        next_build = now;
        const std::uint64_t bytes = (*welcome)->ByteSizeLong();
        s.count(s.down_by_kind, "message", 1, bytes);
        s.count(s.down_by_kind, "welcome", 1, bytes);
        s.count(s.up_by_kind, "message", 1, s.hello.ByteSizeLong());
        s.count(s.up_by_kind, "hello", 1, s.hello.ByteSizeLong());
      } else {
        next_attempt = now + backoff;
        backoff = std::min(backoff * 2, backoff_max);
      }
      std::lock_guard lock(s.status_mutex);
      (welcome ? s.status.connections : s.status.failed_attempts) += 1;
    }
    if (connected) {
      while (s.client.poll(s.downlink)) {
        trace::instant("downlink_received", {{"downlink", static_cast<std::int64_t>(s.downlink.sequence())},
                                             {"acked", static_cast<std::int64_t>(s.downlink.acked_sequence())},
                                             {"corrections", s.downlink.corrected_keyframes_size()}});
        const std::uint64_t bytes = s.downlink.ByteSizeLong();
        s.count(s.down_by_kind, "message", 1, bytes);
        if (s.downlink.acked_sequence() > 0) {
          s.store.onAck(s.downlink.acked_sequence());
          s.pacer.onAck(s.downlink.acked_sequence(), Clock::now());
          s.count(s.down_by_kind, "ack", 1, 0);
        }
        if (s.downlink.corrected_keyframes_size() > 0) {
          s.store.onCorrections(s.downlink.corrected_keyframes_size());
          std::uint64_t correction_bytes = 0;
          for (const auto& c : s.downlink.corrected_keyframes()) correction_bytes += c.ByteSizeLong();
          s.count(s.down_by_kind, "correction", static_cast<std::uint64_t>(s.downlink.corrected_keyframes_size()),
                  correction_bytes);
        }
        if (s.downlink.removed_keyframes_size() > 0) {
          // Counted only: the agent's local map keeps its own keyframes (it does not adopt the server's map).
          std::uint64_t removal_bytes = 0;
          for (std::uint32_t c : s.downlink.removed_keyframes()) removal_bytes += wire::varintBytes(c);
          s.count(s.down_by_kind, "removal", static_cast<std::uint64_t>(s.downlink.removed_keyframes_size()),
                  removal_bytes);
        }
        if (s.downlink.has_covisible()) {
          for (const wire::BatchPart& part : wire::covisibleParts(s.downlink.covisible())) {
            if (part.count > 0) s.count(s.down_by_kind, part.kind, part.count, part.bytes);
          }
        }
        s.passDown(s.downlink, anchors);
      }
      if (!s.client.connected()) {
        connected = false;
        next_attempt = now + backoff;
      }
    }
    // At most max_rate_hz batches a second; while nothing is due, the store is looked at again only after a
    // delta, a reconnection, or one period.
    // Within the pacer's window only: what does not fit waits in the store, where newer states replace older ones.
    if (connected && now >= next_build && s.pacer.maySend()) {
      // Made on the arena once, reused while nothing is due, and dropped with the arena's reset after a send.
      if (s.uplink == nullptr) s.uplink = google::protobuf::Arena::CreateMessage<v1::AgentUplink>(&s.arena);
      v1::AgentUplink* uplink = s.uplink;
      v1::MapBatch& batch = *uplink->mutable_batch();
      next_build = now + period;
      trace::Span span("uplink_batch", {{"batch", static_cast<std::int64_t>(next_sequence)}});
      if (s.store.buildBatch(next_sequence, s.store.newestSensorTime(), s.pacer.batchBudget(s.options.max_batch_bytes),
                             batch)) {
        LivePose pose;
        if (poses != nullptr && poses->newest(pose)) writeLivePose(pose, *batch.mutable_live_pose());
        const std::uint64_t bytes = uplink->ByteSizeLong();
        span.set("keyframes", batch.keyframes_size());
        span.set("bytes", static_cast<std::int64_t>(bytes));
        for (const v1::Keyframe& k : batch.keyframes()) {
          trace::instant(
              "keyframe_sent",
              {{"keyframe", k.counter()}, {"batch", static_cast<std::int64_t>(next_sequence)}, {"map", k.agent_map()}});
        }
        const bool sent = s.client.send(*uplink);
        if (sent) {
          s.pacer.onSent(next_sequence, bytes, Clock::now());
          last_sent = next_sequence++;
          s.countBatch(batch, bytes);
        } else {
          connected = false;  // what the batch carried is sent again after the next Welcome
          next_attempt = now + backoff;
        }
        s.resetArena();
      } else {
        nothing_due = true;
      }
    }
    if (now >= next_sample) {
      s.addTimelineRow(now, connected);
      next_sample += std::chrono::seconds(1);
    }
    if (now >= next_status) {
      s.publishStatus(connected, false, last_sent);
      next_status = now + std::chrono::milliseconds(100);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  s.addTimelineRow(Clock::now(), connected);  // the last row: everything, the final flush included
  if (connected && flushed) {
    s.goodbye.mutable_goodbye()->set_end_of_mission(true);
    if (s.client.send(s.goodbye)) {
      s.count(s.up_by_kind, "message", 1, s.goodbye.ByteSizeLong());
      s.count(s.up_by_kind, "goodbye", 1, s.goodbye.ByteSizeLong());
    }
    (void)s.client.close(std::chrono::milliseconds(2000));
  } else {
    s.client.abandon();  // no goodbye to a server that is away or not reading: a write could block
  }
  s.publishStatus(false, flushed, last_sent);
}

void Link::abort() {
  impl_->client.cancel();
}

LinkStatus Link::status() const {
  std::lock_guard lock(impl_->status_mutex);
  return impl_->status;
}

LinkHealth Link::health() const {
  std::lock_guard lock(impl_->status_mutex);
  const LinkStatus& s = impl_->status;
  return {s.connected, s.acked_sequence, s.backlog.keyframes_unsent + s.backlog.keyframes_unacked};
}

std::string Link::progressText() const {
  const LinkStatus st = status();
  const std::size_t waiting = st.backlog.keyframes_unsent + st.backlog.keyframes_unacked;
  char text[256];
  if (st.connected) {
    std::snprintf(text, sizeof(text), "link up, %zu KF waiting, %.2f MB up", waiting,
                  static_cast<double>(st.up_bytes) * 1e-6);
  } else {
    std::snprintf(text, sizeof(text), "link DOWN (%s), %zu KF waiting",
                  st.last_error.empty() ? "connecting" : st.last_error.c_str(), waiting);
  }
  return text;
}

Status Link::writeReport(const std::filesystem::path& dir) const {
  const Impl& s = *impl_;
  const LinkStatus st = status();
  nlohmann::json up = nlohmann::json::object();
  for (const auto& [kind, c] : s.up_by_kind) up[kind] = {{"messages", c.first}, {"bytes", c.second}};
  nlohmann::json down = nlohmann::json::object();
  for (const auto& [kind, c] : s.down_by_kind) down[kind] = {{"messages", c.first}, {"bytes", c.second}};
  const double duration_s = std::chrono::duration<double>(Clock::now() - s.start).count();
  nlohmann::json j = {{"server", s.options.server},
                      {"mission", s.options.mission},
                      {"agent", s.agent},
                      {"duration_s", duration_s},
                      {"connections", st.connections},
                      {"failed_attempts", st.failed_attempts},
                      {"flushed", st.flushed},
                      {"flush_wait_s", s.flush_wait_s},
                      {"acked_sequence", st.acked_sequence},
                      {"sent_sequence", st.sent_sequence},
                      {"keyframes_unacknowledged", st.backlog.keyframes_unsent + st.backlog.keyframes_unacked},
                      {"keyframes_stored", st.store.keyframes_stored},
                      {"keyframes_dropped", st.store.keyframes_dropped},
                      {"points_dropped", st.store.points_dropped},
                      {"removals_dropped", st.store.removals_dropped},
                      {"deltas", st.store.deltas},
                      {"deltas_lost", st.store.deltas_lost},
                      {"delta_events_lost", st.store.delta_events_lost},
                      {"corrections_received", st.store.corrections_received},
                      {"acked_batches_lost", st.store.acked_batches_lost},
                      {"welcomes_asking_resend", st.store.batches_to_resend},
                      {"covisible_maps_accepted", st.covisible_accepted},
                      {"covisible_maps_refused", st.covisible_refused},
                      {"covisible_last_refusal", st.covisible_last_refusal},
                      {"corrections_refused", st.corrections_refused},
                      {"anchor_messages_to_mapping", st.anchor_messages_published},
                      {"anchor_messages_dropped", st.anchor_messages_dropped},
                      {"up", up},
                      {"down", down},
                      {"up_mb_per_s", duration_s > 0 ? static_cast<double>(st.up_bytes) * 1e-6 / duration_s : 0.0},
                      {"uplink_window_bytes", st.window_bytes},
                      {"uplink_rate_mbit_per_s", st.uplink_rate_bytes_per_s * 8e-6},
                      {"down_mb_per_s", duration_s > 0 ? static_cast<double>(st.down_bytes) * 1e-6 / duration_s : 0.0}};
  std::ofstream json(dir / "link.json");
  json << j.dump(2) << "\n";
  std::ofstream csv(dir / "link_timeline.csv");
  csv << "t_s,up_bytes,down_bytes,connected,keyframes_waiting,unacked_bytes,window_bytes\n";
  for (const auto& r : s.timeline) {
    csv << r.t_s << ',' << r.up_bytes << ',' << r.down_bytes << ',' << (r.connected ? 1 : 0) << ','
        << r.keyframes_waiting << ',' << r.unacked_bytes << ',' << r.window_bytes << '\n';
  }
  if (!json || !csv) return Error{ErrorCode::kIoError, "cannot write the link report into " + dir.string()};
  return Status::Ok();
}

}  // namespace cvislam::agent

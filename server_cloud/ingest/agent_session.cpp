#include "server_cloud/ingest/agent_session.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <functional>
#include <optional>
#include <vector>

#include "common/core/steady_clock.hpp"
#include "common/core/text.hpp"
#include "common/trace/trace.hpp"
#include "cvislam/v1/agent_link.pb.h"
#include "proto/wire/wire.hpp"
#include "server_cloud/store/operator_log.hpp"

namespace cvislam::server {

namespace {

Error invalid(const std::string& what) {
  return Error{ErrorCode::kInvalidArgument, what};
}

Result<AgentSensors> sensorsFromHello(const v1::Hello& hello) {
  SensorMode mode = SensorMode::kMono;
  if (hello.mode() == v1::SENSOR_MODE_MONO) {
    mode = SensorMode::kMono;
  } else if (hello.mode() == v1::SENSOR_MODE_STEREO) {
    mode = SensorMode::kStereo;
  } else {
    return invalid("hello: sensor mode must be MONO or STEREO");
  }
  if (!hello.has_cam0()) return invalid("hello: no cam0 calibration");
  auto cam0 = wire::fromProto(hello.cam0(), "hello cam0");
  if (!cam0) return cam0.error();
  auto model0 = camera::CameraModel::create(cam0->first);
  if (!model0) return model0.error().withContext("hello cam0");
  AgentSensors sensors{.mode = mode,
                       .uses_imu = hello.uses_imu(),
                       .cam0 = *model0,
                       .cam1 = std::nullopt,
                       .T_s_c0 = cam0->second,
                       .T_s_c1 = {},
                       .imu_noise = {},
                       .imu_rate_hz = 200.0};
  if (mode == SensorMode::kStereo) {
    if (!hello.has_cam1()) return invalid("hello: a stereo agent without cam1 calibration");
    auto cam1 = wire::fromProto(hello.cam1(), "hello cam1");
    if (!cam1) return cam1.error();
    auto model1 = camera::CameraModel::create(cam1->first);
    if (!model1) return model1.error().withContext("hello cam1");
    sensors.cam1 = *model1;
    sensors.T_s_c1 = cam1->second;
  }
  if (sensors.uses_imu) {
    if (!hello.has_imu()) return invalid("hello: an agent that uses its IMU sent no IMU calibration");
    auto noise = wire::fromProto(hello.imu(), "hello imu");
    if (!noise) return noise.error();
    sensors.imu_noise = *noise;
    sensors.imu_rate_hz = hello.imu().rate_hz();
  }
  return sensors;
}

// The agent's newest keyframes that the server holds, newest first and at most `n`, all from the agent map of
// the newest; with that agent map and its server map.
std::vector<KeyframeId> newestKeyframes(const AgentRecord& record, int n, MapId& map, std::uint32_t& agent_map) {
  std::vector<std::uint32_t> counters;
  counters.reserve(record.keyframes.size());
  for (const auto& [counter, held] : record.keyframes) {
    if (record.server_removed_keyframes.count(counter) == 0) counters.push_back(counter);
  }
  std::vector<KeyframeId> out;
  if (counters.empty()) return out;
  std::sort(counters.begin(), counters.end(), std::greater<>());
  const AgentRecord::HeldKeyframe& newest = record.keyframes.at(counters.front());
  map = newest.map;
  agent_map = newest.agent_map;
  for (std::uint32_t counter : counters) {
    if (static_cast<int>(out.size()) >= n) break;
    const AgentRecord::HeldKeyframe& held = record.keyframes.at(counter);
    if (held.agent_map == agent_map && held.map == map) out.push_back(KeyframeId{record.id, counter});
  }
  return out;
}

// Applies a batch the store holds (record `held`) without storing it again: what a session does where an append's
// outcome was in doubt and the store, not memory, says what the sequence number holds.
Result<IngestReport> applyStoredBatch(Mission& mission, AgentRecord& record, const StoreRecord& held,
                                      const SessionOptions& options) {
  const std::string what = "the batch " + std::to_string(held.sequence) + " of agent " + std::to_string(record.id) +
                           " that the store holds (record " + std::to_string(held.number) + ")";
  v1::MapBatch batch;
  if (!batch.ParseFromString(held.body) || batch.sequence() != held.sequence) {
    return Error{ErrorCode::kDataError, what + " does not parse as that batch"};
  }
  auto report = applyBatch(mission, record, batch, options.ingest, {});
  if (!report) return Error{ErrorCode::kDataError, what + " does not apply (" + report.error().message() + ")"};
  return report;
}

// Applies the batches the store holds of the agent beyond record.stored_sequence, in order. They are appends
// whose outcome was in doubt: the store refused or lost the answer, but the database had committed them. A Welcome
// that left them out would tell the agent those numbers are free, and the agent would build new batches under
// them that the store then refuses as held. Returns how many it applied.
Result<std::uint64_t> applyStoredBeyond(Mission& mission, AgentRecord& record, const MapStore& store,
                                        const SessionOptions& options, const AgentSession::StoredListener& on_stored) {
  std::uint64_t applied = 0;
  for (;;) {
    auto held = store.findBatch(mission.name(), record.id, record.stored_sequence + 1);
    if (!held) return held.error();
    if (!*held) return applied;
    auto report = applyStoredBatch(mission, record, **held, options);
    if (!report) return report.error();
    if (on_stored) on_stored(mission.name(), *report);
    ++applied;
  }
}

// The Hello as the store keeps it: without last_acked_sequence, the one field that changes between reconnects of
// one process.
std::string normalizedHello(const v1::Hello& hello) {
  v1::Hello copy = hello;
  copy.clear_last_acked_sequence();
  return copy.SerializeAsString();
}

// Takes one Hello from the agent's allowance: OK, or RESOURCE_EXHAUSTED saying when to come back.
Status takeHelloAllowance(AgentRecord& record, const SessionOptions& options,
                          std::chrono::steady_clock::time_point now) {
  const double per_s = options.agent_hellos_per_minute / 60.0;
  if (record.hello_allowance < 0.0) {
    record.hello_allowance = options.agent_hello_burst;
  } else {
    const double elapsed_s = std::max(0.0, std::chrono::duration<double>(now - record.hello_allowance_at).count());
    record.hello_allowance = std::min(options.agent_hello_burst, record.hello_allowance + elapsed_s * per_s);
  }
  record.hello_allowance_at = now;
  if (record.hello_allowance >= 1.0) {
    record.hello_allowance -= 1.0;
    return Status::Ok();
  }
  ++record.hellos_refused;
  const double wait_s = (1.0 - record.hello_allowance) / per_s;
  return Error{ErrorCode::kResourceExhausted,
               "agent " + std::to_string(record.id) + " reconnects too often (more than " +
                   text::formatDouble(options.agent_hellos_per_minute) +
                   " Hellos a minute after a burst; limits.agent_hellos_per_minute): connect again in " +
                   text::formatDouble(std::ceil(wait_s)) + " s"};
}

}  // namespace

Status checkMissionName(const std::string& name) {
  if (name.empty() || name.size() > 128) {
    return invalid("mission name must have 1 to 128 characters, got " + std::to_string(name.size()));
  }
  for (char c : name) {
    if (std::isalnum(static_cast<unsigned char>(c)) == 0 && c != '.' && c != '_' && c != '-') {
      return invalid("mission name '" + name + "': use letters, digits, '.', '_' and '-' only");
    }
  }
  if (name == "." || name == "..") return invalid("mission name '" + name + "' is reserved");
  return Status::Ok();
}

Status SessionOptions::validate() const {
  if (!std::isfinite(downlink_rate_hz) || !(downlink_rate_hz > 0.0) || downlink_rate_hz > 100.0) {
    return invalid("downlink_rate_hz must be in (0, 100]");
  }
  if (max_corrections_per_message < 1) return invalid("max_corrections_per_message must be >= 1");
  if (!std::isfinite(hello_timeout_s) || !(hello_timeout_s > 0.0)) return invalid("limits.hello_timeout_s must be > 0");
  if (!(agent_hello_burst >= 1.0) || !std::isfinite(agent_hello_burst) || !(agent_hellos_per_minute > 0.0) ||
      !std::isfinite(agent_hellos_per_minute)) {
    return invalid("limits.agent_hello_burst must be >= 1 and limits.agent_hellos_per_minute > 0");
  }
  if (max_missions < 1 || max_agents_per_mission < 1) {
    return invalid("limits.max_missions and limits.max_agents_per_mission must be >= 1");
  }
  if (ingest.max_keypoints_per_keyframe < 1 || ingest.max_imu_samples_per_keyframe < 1 ||
      ingest.max_maps_per_agent < 1) {
    return invalid("ingest limits must be >= 1");
  }
  if (ingest.max_keypoints_per_keyframe > 65535) {
    return invalid("max_keypoints_per_keyframe must be at most 65535 (keypoint indices are 16-bit)");
  }
  return covisible.validate();
}

AgentSession::AgentSession(MissionRegistry& missions, const SessionOptions& options,
                           std::function<void()> cancel_stream, StoredListener on_stored, MapStore* store,
                           SessionCredentials credentials, MissionOwnership* ownership, IngestMetrics* metrics)
    : missions_(missions),
      options_(options),
      cancel_stream_(std::move(cancel_stream)),
      on_stored_(std::move(on_stored)),
      store_(store),
      credentials_(std::move(credentials)),
      ownership_(ownership),
      metrics_(metrics),
      covisible_(options.covisible) {}

AgentSession::~AgentSession() {
  close(Status::Ok());
}

Status AgentSession::handle(const v1::AgentUplink& message, std::size_t wire_bytes, v1::ServerDownlink& reply,
                            bool& reply_due) {
  reply_due = false;
  if (closed_) return Error{ErrorCode::kFailedPrecondition, "the stream is closed"};
  Status result;
  if (message.has_hello()) {
    if (record_) {
      result = Error{ErrorCode::kFailedPrecondition, "a second Hello on one stream"};
    } else {
      result = onHello(message, wire_bytes, reply);
      reply_due = result.ok();
    }
  } else if (!record_) {
    result = Error{ErrorCode::kFailedPrecondition, "the first message of a stream must be a Hello"};
  } else if (message.has_batch()) {
    result = onBatch(message, wire_bytes);
  } else if (message.has_goodbye()) {
    auto record = record_->write();
    record->up["message"].add(1, wire_bytes);
    record->up["goodbye"].add(1, wire_bytes);
    if (message.goodbye().end_of_mission()) record->finished = true;
  } else {
    result = invalid("an empty message (no hello, batch or goodbye)");
  }
  if (!result.ok() && record_) {
    auto record = record_->write();
    ++record->refused_messages;
    record->last_error = result.error().toString();
  }
  return result;
}

Status AgentSession::onHello(const v1::AgentUplink& message, std::size_t wire_bytes, v1::ServerDownlink& reply) {
  const v1::Hello& hello = message.hello();
  if (hello.protocol_version() != wire::kProtocolVersion) {
    return Error{ErrorCode::kFailedPrecondition, "protocol version " + std::to_string(hello.protocol_version()) +
                                                     " is not supported: this server speaks version " +
                                                     std::to_string(wire::kProtocolVersion)};
  }
  if (Status s = checkMissionName(hello.mission()); !s.ok()) return s;
  if (credentials_.tokens != nullptr) {
    if (Status s = credentials_.tokens->authorize(hello.mission(), credentials_.token); !s.ok()) return s;
  }
  if (hello.agent_id() > 0xFFFF) return invalid("agent id " + std::to_string(hello.agent_id()) + " is over 65535");
  auto sensors = sensorsFromHello(hello);
  if (!sensors) return sensors.error();
  // Everything the Hello says is checked before a replica takes the mission's lease for it.
  if (ownership_ != nullptr) {
    if (Status room = missions_.checkRoom(hello.mission(), options_.max_missions); !room.ok()) return room;
    auto owner = ownership_->claim(hello.mission());
    if (!owner) {
      return Error{ErrorCode::kUnavailable, "this replica cannot serve mission '" + hello.mission() + "' now (" +
                                                owner.error().message() + "); connect again"};
    }
    if (!owner->here) {
      redirect_ = owner->address;
      return Error{ErrorCode::kUnavailable, "mission '" + hello.mission() + "' is served by replica " + owner->holder +
                                                " at " + owner->address + ": connect there"};
    }
  }

  const auto agent_id = static_cast<AgentId>(hello.agent_id());
  auto opened = missions_.open(hello.mission(), options_.max_missions);
  if (!opened) return opened.error();
  std::shared_ptr<Mission> mission = std::move(opened).value();
  auto admitted = mission->admitAgent(agent_id, options_.max_agents_per_mission);
  if (!admitted) return admitted.error();
  SharedAgentRecord shared_record = std::move(admitted).value();
  std::function<void()> replace_old;
  {
    auto record = shared_record->write();
    if (!record->connected && record->session != 0 && record->session != hello.session() &&
        record->stored_sequence > 0) {
      // Another process streamed as this agent before. A new process counts its keyframes and points from 0
      // again: its ids would land on the old process's objects.
      return Error{ErrorCode::kFailedPrecondition,
                   "agent " + std::to_string(agent_id) + " of mission '" + hello.mission() +
                       "' was streamed by another process before (" + std::to_string(record->keyframes.size()) +
                       " keyframes held): a new process starts its ids again, so give it another --agent-id or "
                       "--mission"};
    }
    if (record->connected) {
      if (record->session != hello.session()) {
        return Error{ErrorCode::kAlreadyExists, "agent " + std::to_string(agent_id) + " of mission '" +
                                                    hello.mission() +
                                                    "' is connected already, from another process; give this "
                                                    "agent another --agent-id"};
      }
    }
    if (Status s = takeHelloAllowance(*record, options_, Clock::now()); !s.ok()) return s;
    // Durable before anything changes: the batches that follow need the sensors when the store is replayed. A
    // Hello that says what the stored one says is not stored again.
    const std::string normalized = normalizedHello(hello);
    if (store_ != nullptr && normalized != record->stored_hello) {
      StoreRecord stored{0, StoreRecord::Kind::kHello, hello.mission(), agent_id, 0, normalized};
      if (Status s = store_->append(stored); !s.ok()) {
        return Error{ErrorCode::kUnavailable,
                     "the server could not store the Hello (" + logForOperator(s.error()) + "); connect again later"};
      }
      record->stored_hello = normalized;
    }
    if (store_ != nullptr) {
      auto caught_up = applyStoredBeyond(*mission, *record, *store_, options_, on_stored_);
      if (!caught_up) {
        return Error{ErrorCode::kUnavailable, "the server could not read what its store holds of this agent (" +
                                                  logForOperator(caught_up.error()) + "); connect again later"};
      }
      record->caught_up_batches += *caught_up;
    }
    if (record->connected) {
      // The same process again: its old stream is stale (it broke without the server noticing yet).
      replace_old = std::move(record->cancel_stream);
    }
    record->cancel_stream = cancel_stream_;
    record->connected = true;
    ++record->connections;
    stream_ = record->connections;
    record->finished = false;
    applyHello(*mission, *record, hello, std::move(sensors).value());
    record->up["message"].add(1, wire_bytes);
    record->up["hello"].add(1, wire_bytes);

    auto* welcome = reply.mutable_welcome();
    welcome->set_stored_sequence(record->stored_sequence);
    welcome->set_keyframes_held(record->keyframes.size());
    welcome->set_points_held(record->points.size());
    welcome->set_server(options_.server_name);
    welcome->set_downlink_rate_hz(options_.downlink_rate_hz);
    welcome->set_resend_from_sequence(record->resend_from);
    resend_told_ = record->resend_from;
    reply.set_sequence(++down_sequence_);
    reply.set_acked_sequence(record->stored_sequence);
    acked_sent_ = record->stored_sequence;
    countDown(*record, reply, 0);
    record->down["welcome"].add(1, reply.ByteSizeLong());
  }
  if (replace_old) replace_old();
  MissionEvent connected;
  connected.kind = MissionEvent::Kind::kAgentConnected;
  connected.agent = agent_id;
  mission->events().append(std::move(connected));
  mission_ = std::move(mission);
  record_ = std::move(shared_record);
  mission_name_ = hello.mission();
  mission_trace_key_ = trace::missionKey(mission_name_);
  agent_ = agent_id;
  last_down_ = Clock::now();
  return Status::Ok();
}

Status AgentSession::onBatch(const v1::AgentUplink& message, std::size_t wire_bytes) {
  const v1::MapBatch& batch = message.batch();
  const std::uint64_t sequence = batch.sequence();
  const auto arrived = Clock::now();  // before the lock: waits for the back-end count
  const double cpu_at_arrival_ms = threadCpuMs();
  const trace::Span span(
      "ingest", {{"mission", mission_trace_key_}, {"agent", agent_}, {"batch", static_cast<std::int64_t>(sequence)}});
  const bool gba_at_arrival = mission_->gbaRunning();
  if (mission_->retired()) {
    return Error{ErrorCode::kUnavailable,
                 "mission '" + mission_name_ + "' moved to another replica: connect again (the Hello is redirected)"};
  }
  const auto locking_from = Clock::now();
  auto record = record_->write();
  const double record_lock_wait_ms = std::chrono::duration<double, std::milli>(Clock::now() - locking_from).count();
  if (record->connections != stream_) {
    return Error{ErrorCode::kAlreadyExists, "a newer stream of this agent took over"};
  }
  record->up["message"].add(1, wire_bytes);
  record->up["batch"].add(1, wire_bytes);
  if (sequence == 0) return invalid("batch sequence 0: sequences start at 1");
  if (sequence < last_sequence_) {
    return invalid("batch sequence went back from " + std::to_string(last_sequence_) + " to " +
                   std::to_string(sequence));
  }
  if (sequence == last_sequence_) {
    return invalid("batch sequence " + std::to_string(sequence) + " sent twice on one stream");
  }
  last_sequence_ = sequence;
  if (sequence <= record->stored_sequence) {
    ++record->duplicate_batches;  // stored already (a resend after a reconnect): dropped, acknowledged again
    return Status::Ok();
  }
  if (sequence > record->stored_sequence + 1) {
    return invalid("batch sequence " + std::to_string(sequence) + " skips ahead: the server holds up to " +
                   std::to_string(record->stored_sequence) + ", so the next is " +
                   std::to_string(record->stored_sequence + 1));
  }
  std::function<Status()> commit;
  std::optional<StoreRecord> held;  // set when the store holds other content under this number
  if (store_ != nullptr) {
    commit = [&]() -> Status {
      const trace::Span commit_span(
          "store_commit",
          {{"mission", mission_trace_key_}, {"agent", agent_}, {"batch", static_cast<std::int64_t>(sequence)}});
      StoreRecord stored{0, StoreRecord::Kind::kBatch, mission_name_, agent_, sequence, storedBody(batch)};
      const auto append_start = Clock::now();
      Status appended = store_->append(stored);
      if (metrics_ != nullptr) {
        metrics_->store_commit.observe(std::chrono::duration<double>(Clock::now() - append_start).count());
      }
      if (appended.ok()) return Status::Ok();
      if (appended.error().code() != ErrorCode::kAlreadyExists) {
        return Error{ErrorCode::kUnavailable, "the server could not store it (" + logForOperator(appended.error()) +
                                                  "); it was not applied: send it again"};
      }
      // The store holds this number already, though memory does not: an earlier attempt committed unseen. The
      // stored body is what a restart will replay, so it decides: the same bytes are applied as received; other
      // bytes are not, and the stored batch is applied in their place below.
      auto found = store_->findBatch(mission_name_, agent_, sequence);
      if (!found || !*found) {
        return Error{ErrorCode::kUnavailable, "the store says it holds it but could not give it back (" +
                                                  (found ? std::string("not found") : logForOperator(found.error())) +
                                                  "); it was not applied: send it again"};
      }
      if ((*found)->body == stored.body) return Status::Ok();
      held = std::move(*found);
      return Error{ErrorCode::kAborted, "the store holds other content under this number"};
    };
  }
  auto report = applyBatch(*mission_, *record, batch, options_.ingest, commit);
  if (!report && held) return applyHeldInstead(*record, *held);
  if (!report) return report.error();
  if (resend_told_ != 0 && record->resend_from == resend_told_) record->resend_from = 0;  // the agent was told
  const double ingest_ms = std::chrono::duration<double, std::milli>(Clock::now() - arrived).count();
  record->ingest_ms.add(ingest_ms);
  record->ingest_record_wait_ms.add(record_lock_wait_ms);
  record->ingest_map_wait_ms.add(report->map_lock_wait_ms);
  record->ingest_cpu_ms.add(threadCpuMs() - cpu_at_arrival_ms);
  if (metrics_ != nullptr) metrics_->ingest.observe(ingest_ms * 1e-3);
  if (gba_at_arrival || mission_->gbaRunning()) record->ingest_during_gba_ms.add(ingest_ms);

  // Traffic by kind: the serialized size of each part.
  for (const wire::BatchPart& part : wire::batchParts(batch)) record->up[part.kind].add(part.count, part.bytes);
  if (on_stored_) on_stored_(mission_name_, *report);
  return Status::Ok();
}

Status AgentSession::applyHeldInstead(AgentRecord& record, const StoreRecord& held) {
  const std::uint64_t sequence = held.sequence;
  auto report = applyStoredBatch(*mission_, record, held, options_);
  if (!report) return report.error();
  if (on_stored_) on_stored_(mission_name_, *report);
  ++record.resend_conflicts;
  if (record.resend_from == 0 || sequence < record.resend_from) record.resend_from = sequence;
  // Not acknowledged: the stream ends, and the next Welcome asks the agent to send its batch's content again.
  return Error{ErrorCode::kAborted,
               "batch " + std::to_string(sequence) + " differs from the batch " + std::to_string(sequence) +
                   " the server had stored (an earlier attempt committed): the stored one was applied; connect "
                   "again and send what yours carried after the Welcome's stored sequence"};
}

void applyHello(Mission& mission, AgentRecord& record, const v1::Hello& hello, AgentSensors sensors) {
  mission.setSensors(record.id, sensors);
  record.session = hello.session();
  record.software = hello.software();
  record.local_map_keyframes = hello.local_map_keyframes();
  record.sensors = std::move(sensors);
}

Result<IngestReport> applyBatch(Mission& mission, AgentRecord& record, const v1::MapBatch& batch,
                                const IngestLimits& limits, const std::function<Status()>& commit) {
  const std::uint64_t sequence = batch.sequence();
  auto report = ingestBatch(batch, record, mission.stack(), limits, commit);
  if (!report) return report.error().withContext("batch " + std::to_string(sequence));
  record.stored_sequence = sequence;
  record.duplicate_objects += static_cast<std::uint64_t>(report->duplicate_objects);
  record.imu_links_missing += static_cast<std::uint64_t>(report->imu_links_missing);
  for (const auto& [map, id] : report->added_keyframes) {
    MissionEvent added;
    added.kind = MissionEvent::Kind::kKeyframeAdded;
    added.agent = id.agent;
    added.keyframe = id;
    added.map = map;
    mission.events().append(std::move(added));
  }
  for (std::size_t i = 0; i < report->removed_keyframe_ids.size(); ++i) {
    MissionEvent removed;
    removed.kind = MissionEvent::Kind::kKeyframeRemoved;
    removed.agent = report->removed_keyframe_ids[i].agent;
    removed.keyframe = report->removed_keyframe_ids[i];
    removed.map = report->removed_keyframe_maps[i];
    removed.cause = "agent";
    mission.events().append(std::move(removed));
  }
  return report;
}

Status replayStored(MissionRegistry& missions, const SessionOptions& options, const StoreRecord& stored,
                    const AgentSession::StoredListener& on_stored) {
  const std::string where = "store record " + std::to_string(stored.number) + " (" +
                            std::string(toString(stored.kind)) + " of agent " + std::to_string(stored.agent) +
                            ", mission '" + stored.mission + "')";
  const auto damaged = [&](const std::string& what) { return Error{ErrorCode::kDataError, where + ": " + what}; };
  if (Status s = checkMissionName(stored.mission); !s.ok()) return damaged(s.error().message());
  auto mission = missions.getOrCreate(stored.mission);
  auto shared_record = mission->agent(stored.agent);
  if (stored.kind == StoreRecord::Kind::kHello) {
    v1::Hello hello;
    if (!hello.ParseFromString(stored.body)) return damaged("the Hello does not parse");
    if (hello.agent_id() != stored.agent || hello.mission() != stored.mission) {
      return damaged("the Hello names agent " + std::to_string(hello.agent_id()) + " of mission '" + hello.mission() +
                     "'");
    }
    auto sensors = sensorsFromHello(hello);
    if (!sensors) return damaged(sensors.error().message());
    auto record = shared_record->write();
    applyHello(*mission, *record, hello, std::move(sensors).value());
    record->stored_hello = normalizedHello(hello);
    return Status::Ok();
  }
  v1::MapBatch batch;
  if (!batch.ParseFromString(stored.body)) return damaged("the batch does not parse");
  if (batch.sequence() != stored.sequence) {
    return damaged("the batch says it is sequence " + std::to_string(batch.sequence()));
  }
  auto record = shared_record->write();
  if (stored.sequence != record->stored_sequence + 1) {
    return damaged("batch " + std::to_string(stored.sequence) + " follows batch " +
                   std::to_string(record->stored_sequence) + ": the store has a gap");
  }
  auto report = applyBatch(*mission, *record, batch, options.ingest, {});
  if (!report) return damaged(report.error().message());
  if (on_stored) on_stored(stored.mission, *report);
  return Status::Ok();
}

void AgentSession::countDown(AgentRecord& record, const v1::ServerDownlink& message, int corrections) {
  const std::uint64_t bytes = message.ByteSizeLong();
  record.down["message"].add(1, bytes);
  if (corrections > 0) {
    std::uint64_t correction_bytes = 0;
    for (const auto& c : message.corrected_keyframes()) correction_bytes += c.ByteSizeLong();
    record.down["correction"].add(static_cast<std::uint64_t>(corrections), correction_bytes);
  }
  if (message.has_covisible()) {
    for (const wire::BatchPart& part : wire::covisibleParts(message.covisible())) {
      if (part.count > 0) record.down[part.kind].add(part.count, part.bytes);
    }
  }
}

bool AgentSession::nextDownlink(Clock::time_point now, v1::ServerDownlink& out) {
  if (!record_ || closed_ || mission_->retired()) return false;
  const auto period = std::chrono::duration<double>(1.0 / options_.downlink_rate_hz);
  if (now - last_down_ < period) return false;
  const std::int64_t begin_ns = trace::nowNs();
  out.Clear();
  int corrections = 0;
  int removals = 0;
  std::size_t removal_bytes = 0;
  bool new_ack = false;
  {
    auto record = record_->write();
    if (record->connections != stream_) return false;
    new_ack = record->stored_sequence > acked_sent_;
    // The server's states of corrected keyframes, in the agent's world frame (T_m_w inverted).
    while (!record->corrections.empty() && corrections < options_.max_corrections_per_message) {
      const std::uint32_t counter = *record->corrections.begin();
      record->corrections.erase(record->corrections.begin());
      auto held = record->keyframes.find(counter);
      if (held == record->keyframes.end()) continue;
      auto map = mission_->stack().find(held->second.map);
      if (!map) continue;
      const geometry::SE3d T_w_m_held = record->agent_maps.count(held->second.agent_map) != 0
                                            ? record->agent_maps.at(held->second.agent_map).T_m_w.inverse()
                                            : geometry::SE3d();
      auto content = map->read();
      const ServerKeyframe* kf = content->keyframe(KeyframeId{record->id, counter});
      if (kf == nullptr) continue;
      wire::KeyframeStateValues state{T_w_m_held * kf->T_w_s, T_w_m_held.so3() * kf->v_w, kf->bias};
      wire::toProto(counter, state, out.add_corrected_keyframes());
      ++corrections;
    }
    // Keyframes removed as redundant, oldest first, within the same per-message bound.
    const std::size_t bytes_before = out.ByteSizeLong();
    while (!record->removals_to_send.empty() && removals < options_.max_corrections_per_message) {
      out.add_removed_keyframes(*record->removals_to_send.begin());
      record->removals_to_send.erase(record->removals_to_send.begin());
      ++removals;
    }
    removal_bytes = out.ByteSizeLong() - bytes_before;
  }
  // The covisible map. The cameras first (every agent's record, one at a time); then this agent's record and
  // the map together (records before maps), so that a correction cannot land between reading the agent's
  // newest keyframes and frame and the map they belong to.
  if (options_.covisible.enabled) {
    const CovisibleCameras cameras = covisibleCameras(*mission_);
    const auto record = record_->read();
    MapId seed_map = 0;
    std::uint32_t agent_map = 0;
    const std::vector<KeyframeId> seeds =
        newestKeyframes(*record, options_.covisible.seed_keyframes, seed_map, agent_map);
    const auto frame = record->agent_maps.find(agent_map);
    const std::shared_ptr<ServerMap> map = seeds.empty() ? nullptr : mission_->stack().find(seed_map);
    if (map && frame != record->agent_maps.end()) {
      const auto content = map->read();
      covisible_.fill(*content, seeds, agent_map, frame->second.T_m_w.inverse(), cameras, *out.mutable_covisible(),
                      record->local_map_keyframes);
    }
    if (out.covisible().ByteSizeLong() == 0) out.clear_covisible();  // nothing new to say
  }
  if (!new_ack && corrections == 0 && removals == 0 && !out.has_covisible()) return false;
  {
    auto record = record_->write();
    out.set_acked_sequence(record->stored_sequence);
    out.set_sequence(++down_sequence_);
    acked_sent_ = record->stored_sequence;
    if (removals > 0) record->down["removal"].add(static_cast<std::uint64_t>(removals), removal_bytes);
    countDown(*record, out, corrections);
    if (new_ack) record->down["ack"].add(1, 0);
  }
  last_down_ = now;
  // Its end stands for the send: the adapter writes the message right after.
  trace::complete("downlink_build", begin_ns, trace::nowNs(),
                  {{"mission", mission_trace_key_},
                   {"agent", agent_},
                   {"downlink", static_cast<std::int64_t>(out.sequence())},
                   {"corrections", corrections},
                   {"covisible", out.has_covisible() ? 1 : 0}});
  return true;
}

Status AgentSession::checkHelloDeadline(Clock::time_point now) const {
  if (record_ || closed_) return Status::Ok();
  if (std::chrono::duration<double>(now - opened_).count() < options_.hello_timeout_s) return Status::Ok();
  return Error{ErrorCode::kFailedPrecondition, "no Hello within " + text::formatDouble(options_.hello_timeout_s) +
                                                   " s" +
                                                   " of opening the stream (limits.hello_timeout_s): a stream "
                                                   "starts with the agent's Hello"};
}

void AgentSession::countRefused(const Status& reason) {
  if (!record_ || reason.ok()) return;
  auto record = record_->write();
  ++record->refused_messages;
  record->last_error = reason.error().toString();
}

void AgentSession::close(const Status& reason) {
  if (closed_) return;
  closed_ = true;
  if (!record_) return;
  auto record = record_->write();
  if (record->connections == stream_) {
    record->connected = false;
    record->cancel_stream = nullptr;
    if (mission_) {
      MissionEvent gone;
      gone.kind = MissionEvent::Kind::kAgentDisconnected;
      gone.agent = agent_;
      mission_->events().append(std::move(gone));
    }
  }
  if (!reason.ok()) record->last_error = reason.error().toString();
}

}  // namespace cvislam::server

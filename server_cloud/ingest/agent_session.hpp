// One agent's link stream on the server: the protocol's state machine, without gRPC. The service adapter
// (server_cloud/service) hands it every message it reads and sends what it returns; tests drive it directly.
//
//   Hello    -> Welcome at once: the newest batch the server stored of this agent, so the agent continues
//               with the next one (after a server restart that lost its state: 0, and the agent resends).
//   MapBatch -> stored when its sequence is stored + 1; dropped (and acknowledged) when the server has it
//               already; refused when it goes back within the stream or skips ahead.
//   Goodbye  -> the agent has finished.
//   every 1/downlink_rate_hz at most: an acknowledgement, the keyframes the server corrected or removed, and
//               the covisible map (covisible_downlink.hpp).
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>

#include "common/core/result.hpp"
#include "server_cloud/access/mission_tokens.hpp"
#include "server_cloud/ingest/batch_ingest.hpp"
#include "server_cloud/ingest/covisible_downlink.hpp"
#include "server_cloud/ingest/mission_ownership.hpp"
#include "server_cloud/stack/latency_histogram.hpp"
#include "server_cloud/stack/map_stack.hpp"
#include "server_cloud/store/map_store.hpp"

namespace cvislam::v1 {
class AgentUplink;
class Hello;
class MapBatch;
class ServerDownlink;
}  // namespace cvislam::v1

namespace cvislam::server {

class MissionRegistry;

struct SessionOptions {
  double downlink_rate_hz = 2.0;           // paper: at most 2 messages per second to an agent
  int max_corrections_per_message = 1000;  // the rest follow in the next messages
  IngestLimits ingest;
  CovisibleOptions covisible;  // the map data of the downlink
  std::string server_name = "cvislam_server";
  std::size_t max_missions = 64;            // missions a server holds; a Hello for one more is refused
  std::size_t max_agents_per_mission = 32;  // agents of one mission; a Hello of one more is refused
  double hello_timeout_s = 5.0;             // a stream that says nothing for this long after opening is ended
  // Hellos of one agent: a burst, then this many a minute. Beyond it a Hello is refused before it is stored or
  // logged (an agent on a bad radio link reconnects a few times a minute; a loop would do so hundreds of times).
  double agent_hello_burst = 20.0;
  double agent_hellos_per_minute = 12.0;

  [[nodiscard]] Status validate() const;
};

// What the stream presented: the mission tokens decide whether its Hello may open the mission it names.
struct SessionCredentials {
  const MissionTokens* tokens = nullptr;  // nullptr: no check
  std::string token;                      // the bearer token of the stream's metadata; "" when none
};

class AgentSession {
 public:
  using Clock = std::chrono::steady_clock;

  // `cancel_stream` ends this session's stream from outside, when a reconnect of the same agent process takes
  // over from it. It is called without any lock held, possibly after the stream ended, so it must be safe to
  // call at any time; it may be empty.
  // `on_stored`, when set, hears of every batch stored (mission name, what changed); it is called with the
  // agent's record locked, so it must only hand the news on (place recognition queues it).
  using StoredListener = std::function<void(const std::string& mission, const IngestReport& report)>;
  // `store`, when set, makes every Hello and batch durable before it takes effect (map_store.hpp); a batch the
  // store refuses is not applied, and the stream ends with UNAVAILABLE so that the agent sends it again.
  // `credentials`: the Hello is refused with UNAUTHENTICATED, before anything is made, unless they open its mission.
  // `ownership`, when set (scale-out), decides whether this replica serves the Hello's mission: when another one
  // does, the Hello is refused with UNAVAILABLE and redirect() names where to go.
  // `metrics`, when set, counts every batch's ingest and store-commit time (the metrics endpoint).
  AgentSession(MissionRegistry& missions, const SessionOptions& options, std::function<void()> cancel_stream,
               StoredListener on_stored = {}, MapStore* store = nullptr, SessionCredentials credentials = {},
               MissionOwnership* ownership = nullptr, IngestMetrics* metrics = nullptr);
  ~AgentSession();
  AgentSession(const AgentSession&) = delete;
  AgentSession& operator=(const AgentSession&) = delete;

  // Handles one message; `wire_bytes` is its serialized size. On success *reply_due says whether `reply` holds
  // a message to send at once (the Welcome). An error ends the stream with that status.
  Status handle(const v1::AgentUplink& message, std::size_t wire_bytes, v1::ServerDownlink& reply, bool& reply_due);

  // The periodic message (acknowledgement, corrections) when one is due at `now`; false when none is.
  bool nextDownlink(Clock::time_point now, v1::ServerDownlink& out);

  // An error once the stream has been open hello_timeout_s at `now` without a Hello: the stream is to end.
  [[nodiscard]] Status checkHelloDeadline(Clock::time_point now) const;

  // A message the adapter refused before it reached handle() (bytes that do not parse): counted like any other
  // refused message. The stream ends with it.
  void countRefused(const Status& reason);

  // The stream ended: the agent closed it, it broke, or a message was refused (`reason`).
  void close(const Status& reason);

  [[nodiscard]] bool greeted() const { return record_ != nullptr; }
  [[nodiscard]] AgentId agent() const { return agent_; }
  [[nodiscard]] const std::string& mission() const { return mission_name_; }
  // After a refused Hello: the address (host:port) of the replica that serves its mission; "" otherwise.
  [[nodiscard]] const std::string& redirect() const { return redirect_; }

 private:
  Status onHello(const v1::AgentUplink& message, std::size_t wire_bytes, v1::ServerDownlink& reply);
  Status onBatch(const v1::AgentUplink& message, std::size_t wire_bytes);
  void countDown(AgentRecord& record, const v1::ServerDownlink& message, int corrections);
  // The store holds `held` under the number of a batch just received, with other content: applies the stored one
  // and returns the error that ends the stream.
  Status applyHeldInstead(AgentRecord& record, const StoreRecord& held);

  MissionRegistry& missions_;
  SessionOptions options_;
  std::function<void()> cancel_stream_;
  StoredListener on_stored_;
  MapStore* store_ = nullptr;
  SessionCredentials credentials_;
  MissionOwnership* ownership_ = nullptr;
  IngestMetrics* metrics_ = nullptr;
  std::string redirect_;
  std::shared_ptr<Mission> mission_;
  SharedAgentRecord record_;
  std::string mission_name_;
  std::int64_t mission_trace_key_ = 0;  // trace::missionKey(mission_name_), the mission in trace events
  AgentId agent_ = 0;
  std::uint64_t stream_ = 0;         // this stream's number among the agent's streams
  std::uint64_t last_sequence_ = 0;  // the newest batch sequence seen on this stream
  std::uint64_t acked_sent_ = 0;     // the newest acknowledgement sent on this stream
  std::uint64_t resend_told_ = 0;    // the Welcome's resend_from_sequence
  std::uint64_t down_sequence_ = 0;
  CovisibleSender covisible_;  // what this stream has sent of the covisible map
  Clock::time_point last_down_{};
  Clock::time_point opened_ = Clock::now();
  bool closed_ = false;
};

// A mission name: 1 to 128 characters of [A-Za-z0-9._-], so that it can name files and metrics safely.
Status checkMissionName(const std::string& name);

// What a Hello sets in the agent's record and its mission (live and when the store is replayed).
void applyHello(Mission& mission, AgentRecord& record, const v1::Hello& hello, AgentSensors sensors);

// Stores the next batch of the agent (record.stored_sequence + 1; the caller checked that): ingest, the stored
// sequence, the counters and the mission's events. `commit`, when set, runs after ingest's checks and before
// anything changes (the store's append); its error leaves everything as it was.
Result<IngestReport> applyBatch(Mission& mission, AgentRecord& record, const v1::MapBatch& batch,
                                const IngestLimits& limits, const std::function<Status()>& commit);

// Applies one record of a map store (map_store.hpp) to `missions`, as the live stream applied it; `on_stored`
// hears of the batch as it did then. A record that does not apply (a gap in an agent's sequences, a body that
// does not parse or that ingest refuses) is an error that names it.
Status replayStored(MissionRegistry& missions, const SessionOptions& options, const StoreRecord& stored,
                    const AgentSession::StoredListener& on_stored);

}  // namespace cvislam::server

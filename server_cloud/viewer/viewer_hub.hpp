// The Foxglove WebSocket protocol (foxglove.websocket.v1) without the sockets: who may connect, which channels each
// client is told of, what it subscribed to, and a bounded queue of frames per client. The endpoint
// (viewer_endpoint.cpp) only moves these frames and the clients' text messages; tests drive the hub directly.
//
// A slow client never holds anything up: data frames wait in its queue, and when that is full the oldest goes
// (counted). Protocol frames (serverInfo, advertise, status) are never dropped; there are few of them.
// Thread-safe: the publisher thread publishes, the endpoint's thread opens, reads and drains clients.
#pragma once

#include <cstddef>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <set>
#include <string>
#include <string_view>
#include <vector>

#include "common/core/result.hpp"
#include "common/core/synchronized.hpp"
#include "server_cloud/viewer/mission_feed.hpp"

namespace cvislam::server {
class MissionTokens;
}

namespace cvislam::server::viewer {

inline constexpr const char* kSubprotocol = "foxglove.websocket.v1";

struct HubOptions {
  std::size_t client_queue = 256;  // data frames waiting per client at most

  [[nodiscard]] Status validate() const;
};

// Which missions a client may see, decided from its upgrade request.
struct ClientAccess {
  bool every_mission = false;  // no tokens on this server and no mission named
  std::string mission;
};

// The upgrade request's say: the mission (`?mission=`) and the token (`Authorization: Bearer`, else `?token=`).
// UNAUTHENTICATED (the endpoint answers 401) when the token does not open the mission, or when tokens are on and no
// mission is named. The message says what to fix and never echoes a token.
Result<ClientAccess> admitViewer(const MissionTokens& tokens, std::string_view authorization, std::string_view query);

// A query string's parameter, percent-decoded ("" when absent).
std::string queryParameter(std::string_view query, std::string_view name);

class ViewerHub {
 public:
  using ClientId = std::uint64_t;

  struct Frame {
    bool binary = false;
    std::string bytes;
  };
  struct ClientCounters {
    std::uint64_t frames_sent = 0;  // handed to the endpoint
    std::uint64_t bytes_sent = 0;
    std::uint64_t dropped = 0;  // data frames dropped because the queue was full
    std::size_t queued = 0;
  };
  // A client's new subscriptions since the last takeCatchUps(): it needs the channels' newest state first. Also a
  // client that lost messages to its full queue and has read half of it since: every channel it subscribed to.
  struct CatchUp {
    ClientId client = 0;
    std::string mission;
    std::set<std::size_t> channels;  // indices into the mission feed's channels
  };

  explicit ViewerHub(HubOptions options = {});

  // Called after frames were queued (from any thread): the endpoint wakes up to send them.
  void setWake(std::function<void()> wake);

  // A client connected: it gets the serverInfo and the channels it may see now.
  ClientId open(ClientAccess access);
  void close(ClientId client);
  // A text message from the client: subscribe and unsubscribe. Anything else, or malformed JSON, gets a status
  // message back (the client stays connected); the returned error says what it was.
  Status onText(ClientId client, std::string_view text);

  // The publisher: the mission's channels now (new ones are advertised to the clients that may see the mission).
  void registerChannels(const std::string& mission, const std::vector<FeedChannel>& channels);
  // Messages of the mission's channels, to every client subscribed to them.
  void publish(const std::string& mission, const std::vector<FeedMessage>& messages);
  // To one client only, on its subscriptions (its catch-up).
  void publishTo(ClientId client, const std::string& mission, const std::vector<FeedMessage>& messages);
  [[nodiscard]] std::vector<CatchUp> takeCatchUps();
  // Whether any client may see the mission (the publisher looks only at those, and at recorded ones).
  [[nodiscard]] bool watched(const std::string& mission) const;
  [[nodiscard]] bool watchedByAll() const;  // some client sees every mission

  // The endpoint: the next frame for the client, false when none.
  bool pop(ClientId client, Frame& frame);
  [[nodiscard]] std::vector<ClientId> clients() const;
  [[nodiscard]] ClientCounters counters(ClientId client) const;
  [[nodiscard]] std::uint64_t droppedTotal() const;

 private:
  struct Channel {
    std::uint32_t id = 0;  // the protocol's channel id, unique on this server
    std::string mission;
    std::size_t index = 0;  // in the mission feed
    FeedChannel channel;
  };
  struct Client {
    ClientAccess access;
    std::map<std::uint32_t, std::uint32_t> subscriptions;  // subscription id -> channel id
    std::deque<Frame> control;
    std::deque<Frame> data;  // oldest first
    CatchUp pending;
    // Messages were dropped: the client's scene misses changes (only changes are sent), so once it reads again it
    // gets the full state of every channel it subscribed to.
    bool resync = false;
    ClientCounters counters;
  };
  struct State {
    std::map<ClientId, Client> clients;
    std::vector<Channel> channels;
    std::map<std::pair<std::string, std::size_t>, std::uint32_t> channel_ids;
    ClientId next_client = 1;
    std::uint64_t dropped = 0;
  };

  static bool sees(const Client& client, const std::string& mission);
  static const Channel* channelById(const State& state, std::uint64_t id);
  void pushData(State& state, Client& client, Frame frame) const;
  // Queues the message for each of the client's subscriptions to its channel; whether there was one.
  bool queueFor(State& state, Client& client, const std::string& mission, const FeedMessage& message) const;
  static std::string advertise(const std::vector<const Channel*>& channels);
  void wake() const;

  HubOptions options_;
  std::function<void()> wake_;
  Synchronized<State> state_;
};

// A MessageData frame: opcode 1, the subscription id (uint32) and the timestamp (uint64, ns), little-endian, then
// the payload.
std::string messageData(std::uint32_t subscription, std::uint64_t t_ns, std::string_view payload);

}  // namespace cvislam::server::viewer

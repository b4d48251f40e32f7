#include "server_cloud/viewer/viewer_hub.hpp"

#include <nlohmann/json.hpp>

#include "server_cloud/access/mission_tokens.hpp"

namespace cvislam::server::viewer {
namespace {

using nlohmann::json;

std::string statusMessage(int level, const std::string& message) {
  return json{{"op", "status"}, {"level", level}, {"message", message}}.dump();
}

int hexValue(char c) {
  if (c >= '0' && c <= '9') return c - '0';
  if (c >= 'a' && c <= 'f') return c - 'a' + 10;
  if (c >= 'A' && c <= 'F') return c - 'A' + 10;
  return -1;
}

}  // namespace

Status HubOptions::validate() const {
  if (client_queue < 1 || client_queue > 1000000) {
    return Error{ErrorCode::kInvalidArgument, "viewer: the client queue must hold 1 to 1000000 messages"};
  }
  return Status::Ok();
}

std::string queryParameter(std::string_view query, std::string_view name) {
  if (!query.empty() && query.front() == '?') query.remove_prefix(1);
  while (!query.empty()) {
    const std::size_t amp = query.find('&');
    const std::string_view pair = query.substr(0, amp);
    query = amp == std::string_view::npos ? std::string_view() : query.substr(amp + 1);
    const std::size_t eq = pair.find('=');
    if (pair.substr(0, eq) != name) continue;
    const std::string_view raw = eq == std::string_view::npos ? std::string_view() : pair.substr(eq + 1);
    std::string out;
    for (std::size_t i = 0; i < raw.size(); ++i) {
      if (raw[i] == '+') {
        out.push_back(' ');
      } else if (raw[i] == '%' && i + 2 < raw.size() && hexValue(raw[i + 1]) >= 0 && hexValue(raw[i + 2]) >= 0) {
        out.push_back(static_cast<char>(hexValue(raw[i + 1]) * 16 + hexValue(raw[i + 2])));
        i += 2;
      } else {
        out.push_back(raw[i]);
      }
    }
    return out;
  }
  return {};
}

Result<ClientAccess> admitViewer(const MissionTokens& tokens, std::string_view authorization, std::string_view query) {
  ClientAccess access;
  access.mission = queryParameter(query, "mission");
  std::string token(bearerToken(authorization));
  if (token.empty()) token = queryParameter(query, "token");
  if (access.mission.empty()) {
    if (tokens.enabled()) {
      return Error{ErrorCode::kUnauthenticated,
                   "this server needs a mission and its token: open ?mission=NAME&token=TOKEN (or send the token as "
                   "'Authorization: Bearer TOKEN')"};
    }
    access.every_mission = true;
    return access;
  }
  if (Status s = tokens.authorize(access.mission, token); !s.ok()) return s.error();
  return access;
}

std::string messageData(std::uint32_t subscription, std::uint64_t t_ns, std::string_view payload) {
  std::string frame(13 + payload.size(), '\0');
  frame[0] = 0x01;
  for (unsigned i = 0; i < 4; ++i) frame[1 + i] = static_cast<char>((subscription >> (8U * i)) & 0xFFU);
  for (unsigned i = 0; i < 8; ++i) frame[5 + i] = static_cast<char>((t_ns >> (8U * i)) & 0xFFU);
  frame.replace(13, payload.size(), payload);
  return frame;
}

ViewerHub::ViewerHub(HubOptions options) : options_(options) {}

void ViewerHub::setWake(std::function<void()> wake) {
  wake_ = std::move(wake);
}

void ViewerHub::wake() const {
  if (wake_) wake_();
}

bool ViewerHub::sees(const Client& client, const std::string& mission) {
  return client.access.every_mission || client.access.mission == mission;
}

std::string ViewerHub::advertise(const std::vector<const Channel*>& channels) {
  json list = json::array();
  for (const Channel* c : channels) {
    list.push_back({{"id", c->id},
                    {"topic", c->channel.topic},
                    {"encoding", "json"},
                    {"schemaName", c->channel.schema_name},
                    {"schema", schemaJson(c->channel.schema_name)},
                    {"schemaEncoding", "jsonschema"}});
  }
  return json{{"op", "advertise"}, {"channels", std::move(list)}}.dump();
}

ViewerHub::ClientId ViewerHub::open(ClientAccess access) {
  ClientId id = 0;
  {
    auto state = state_.write();
    id = state->next_client++;
    Client& client = state->clients[id];
    client.access = std::move(access);
    client.pending.client = id;
    const json info = {
        {"op", "serverInfo"},
        {"name", "cvislam_server"},
        {"capabilities", json::array()},
        {"supportedEncodings", {"json"}},
        {"metadata", {{"mission", client.access.every_mission ? std::string("*") : client.access.mission}}},
        {"sessionId", std::to_string(id)}};
    client.control.push_back({false, info.dump()});
    std::vector<const Channel*> visible;
    for (const Channel& c : state->channels) {
      if (sees(client, c.mission)) visible.push_back(&c);
    }
    if (!visible.empty()) client.control.push_back({false, advertise(visible)});
  }
  wake();
  return id;
}

void ViewerHub::close(ClientId client) {
  state_.write()->clients.erase(client);
}

Status ViewerHub::onText(ClientId id, std::string_view text) {
  Status result = Status::Ok();
  {
    auto state = state_.write();
    auto it = state->clients.find(id);
    if (it == state->clients.end()) return Status::Ok();
    Client& client = it->second;
    const auto refuse = [&](const std::string& why) {
      client.control.push_back({false, statusMessage(2, why)});
      result = Error{ErrorCode::kInvalidArgument, why};
    };
    const json message = json::parse(text, nullptr, false);
    const std::string op = message.is_object() && message.contains("op") && message["op"].is_string()
                               ? message["op"].get<std::string>()
                               : std::string();
    if (message.is_discarded()) {
      refuse("not JSON: the protocol's client messages are JSON objects");
    } else if (op == "subscribe" && message.contains("subscriptions") && message["subscriptions"].is_array()) {
      for (const json& s : message["subscriptions"]) {
        if (!s.is_object() || !s.contains("id") || !s.contains("channelId") || !s["id"].is_number_unsigned() ||
            !s["channelId"].is_number_unsigned()) {
          refuse("subscribe: each subscription needs an unsigned 'id' and 'channelId'");
          continue;
        }
        const auto sub = s["id"].get<std::uint64_t>();
        const auto channel_id = s["channelId"].get<std::uint64_t>();
        const Channel* channel = channelById(*state, channel_id);
        if (channel == nullptr || !sees(client, channel->mission) || sub > UINT32_MAX) {
          refuse("subscribe: channel " + std::to_string(channel_id) + " is not advertised to this client");
          continue;
        }
        client.subscriptions[static_cast<std::uint32_t>(sub)] = channel->id;
        if (client.pending.mission.empty() || client.pending.mission == channel->mission) {
          client.pending.mission = channel->mission;
          client.pending.channels.insert(channel->index);
        }
      }
    } else if (op == "unsubscribe" && message.contains("subscriptionIds") && message["subscriptionIds"].is_array()) {
      for (const json& s : message["subscriptionIds"]) {
        if (s.is_number_unsigned()) client.subscriptions.erase(static_cast<std::uint32_t>(s.get<std::uint64_t>()));
      }
    } else {
      refuse("unsupported operation '" + op + "': this server takes subscribe and unsubscribe");
    }
  }
  wake();
  return result;
}

void ViewerHub::registerChannels(const std::string& mission, const std::vector<FeedChannel>& channels) {
  bool woke = false;
  {
    auto state = state_.write();
    const std::size_t first_new = state->channels.size();
    for (std::size_t i = 0; i < channels.size(); ++i) {
      const auto key = std::make_pair(mission, i);
      if (state->channel_ids.count(key) != 0) continue;
      const auto id = static_cast<std::uint32_t>(state->channels.size() + 1);
      state->channel_ids[key] = id;
      state->channels.push_back({id, mission, i, channels[i]});
    }
    if (state->channels.size() == first_new) return;
    // Pointers into the vector only once it has stopped growing.
    std::vector<const Channel*> added;
    for (std::size_t i = first_new; i < state->channels.size(); ++i) added.push_back(&state->channels[i]);
    const std::string text = advertise(added);
    for (auto& [id, client] : state->clients) {
      if (!sees(client, mission)) continue;
      client.control.push_back({false, text});
      woke = true;
    }
  }
  if (woke) wake();
}

void ViewerHub::pushData(State& state, Client& client, Frame frame) const {
  if (client.data.size() >= options_.client_queue) {
    client.data.pop_front();
    ++client.counters.dropped;
    ++state.dropped;
    client.resync = true;
  }
  client.data.push_back(std::move(frame));
}

const ViewerHub::Channel* ViewerHub::channelById(const State& state, std::uint64_t id) {
  // Ids are dense from 1, in the order the channels were registered.
  return id >= 1 && id <= state.channels.size() ? &state.channels[id - 1] : nullptr;
}

bool ViewerHub::queueFor(State& state, Client& client, const std::string& mission, const FeedMessage& m) const {
  auto id = state.channel_ids.find({mission, m.channel});
  if (id == state.channel_ids.end()) return false;
  bool any = false;
  for (const auto& [sub, channel] : client.subscriptions) {
    if (channel != id->second) continue;
    pushData(state, client, {true, messageData(sub, static_cast<std::uint64_t>(m.t_unix_ns), m.payload)});
    any = true;
  }
  return any;
}

void ViewerHub::publish(const std::string& mission, const std::vector<FeedMessage>& messages) {
  bool any = false;
  {
    auto state = state_.write();
    for (auto& [client_id, client] : state->clients) {
      for (const FeedMessage& m : messages) any = queueFor(*state, client, mission, m) || any;
    }
  }
  if (any) wake();
}

void ViewerHub::publishTo(ClientId client_id, const std::string& mission, const std::vector<FeedMessage>& messages) {
  bool any = false;
  {
    auto state = state_.write();
    auto it = state->clients.find(client_id);
    if (it == state->clients.end()) return;
    for (const FeedMessage& m : messages) any = queueFor(*state, it->second, mission, m) || any;
  }
  if (any) wake();
}

std::vector<ViewerHub::CatchUp> ViewerHub::takeCatchUps() {
  std::vector<CatchUp> out;
  auto state = state_.write();
  for (auto& [id, client] : state->clients) {
    // Not while the client still has half a queue to read: a client that stays stalled would only drop it again.
    if (client.resync && client.data.size() < options_.client_queue / 2) {
      client.resync = false;
      for (const auto& [sub, channel_id] : client.subscriptions) {
        const Channel& c = *channelById(*state, channel_id);
        if (client.pending.mission.empty() || client.pending.mission == c.mission) {
          client.pending.mission = c.mission;
          client.pending.channels.insert(c.index);
        }
      }
    }
    if (client.pending.channels.empty()) continue;
    out.push_back(std::move(client.pending));
    client.pending = CatchUp{};
    client.pending.client = id;
  }
  return out;
}

bool ViewerHub::watched(const std::string& mission) const {
  auto state = state_.read();
  for (const auto& [id, client] : state->clients) {
    if (sees(client, mission)) return true;
  }
  return false;
}

bool ViewerHub::watchedByAll() const {
  auto state = state_.read();
  for (const auto& [id, client] : state->clients) {
    if (client.access.every_mission) return true;
  }
  return false;
}

bool ViewerHub::pop(ClientId id, Frame& frame) {
  auto state = state_.write();
  auto it = state->clients.find(id);
  if (it == state->clients.end()) return false;
  Client& client = it->second;
  std::deque<Frame>& queue = client.control.empty() ? client.data : client.control;
  if (queue.empty()) return false;
  frame = std::move(queue.front());
  queue.pop_front();
  ++client.counters.frames_sent;
  client.counters.bytes_sent += frame.bytes.size();
  return true;
}

std::vector<ViewerHub::ClientId> ViewerHub::clients() const {
  std::vector<ClientId> out;
  auto state = state_.read();
  for (const auto& [id, client] : state->clients) out.push_back(id);
  return out;
}

ViewerHub::ClientCounters ViewerHub::counters(ClientId id) const {
  auto state = state_.read();
  auto it = state->clients.find(id);
  if (it == state->clients.end()) return {};
  ClientCounters c = it->second.counters;
  c.queued = it->second.data.size() + it->second.control.size();
  return c;
}

std::uint64_t ViewerHub::droppedTotal() const {
  return state_.read()->dropped;
}

}  // namespace cvislam::server::viewer

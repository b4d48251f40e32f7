#include "server_cloud/stack/map_stack.hpp"

#include <limits>

namespace cvislam::server {

std::shared_ptr<ServerMap> MapStack::createMap(MapOrigin origin) {
  auto maps = maps_.write();
  auto map = std::make_shared<ServerMap>(maps->next_id++);
  maps->by_id.emplace(map->id(), map);
  maps->origins.emplace(map->id(), origin);
  return map;
}

std::optional<MapOrigin> MapStack::origin(MapId id) const {
  auto maps = maps_.read();
  const auto it = maps->origins.find(id);
  if (it == maps->origins.end()) return std::nullopt;
  return it->second;
}

std::shared_ptr<ServerMap> MapStack::find(MapId id) const {
  auto maps = maps_.read();
  auto it = maps->by_id.find(id);
  return it == maps->by_id.end() ? nullptr : it->second;
}

void MapStack::remove(MapId id) {
  maps_.write()->by_id.erase(id);
}

std::vector<std::shared_ptr<ServerMap>> MapStack::maps() const {
  auto maps = maps_.read();
  std::vector<std::shared_ptr<ServerMap>> out;
  out.reserve(maps->by_id.size());
  for (const auto& [id, map] : maps->by_id) out.push_back(map);
  return out;
}

void Mission::setSensors(AgentId id, const AgentSensors& sensors) {
  auto shared = std::make_shared<const AgentSensors>(sensors);
  sensors_.write()->insert_or_assign(id, std::move(shared));
}

std::map<AgentId, std::shared_ptr<const AgentSensors>> Mission::sensors() const {
  return *sensors_.read();
}

SharedAgentRecord Mission::agent(AgentId id) {
  return admitAgent(id, std::numeric_limits<std::size_t>::max()).value();  // no limit: never fails
}

Result<SharedAgentRecord> Mission::admitAgent(AgentId id, std::size_t max_agents) {
  auto agents = agents_.write();
  auto it = agents->find(id);
  if (it != agents->end()) return it->second;
  if (agents->size() >= max_agents) {
    return Error{ErrorCode::kResourceExhausted, "mission '" + name_ + "' has " + std::to_string(agents->size()) +
                                                    " agents, its limit (limits.max_agents_per_mission); agent " +
                                                    std::to_string(id) + " cannot join it"};
  }
  // Named before it is published, so that no record's lock is ever taken under the agents' lock (the back-end
  // takes them the other way round).
  AgentRecord named;
  named.id = id;
  auto record = std::make_shared<Synchronized<AgentRecord>>(std::in_place, std::move(named));
  agents->emplace(id, record);
  return record;
}

SharedAgentRecord Mission::findAgent(AgentId id) const {
  auto agents = agents_.read();
  auto it = agents->find(id);
  return it == agents->end() ? nullptr : it->second;
}

std::vector<SharedAgentRecord> Mission::agents() const {
  auto agents = agents_.read();
  std::vector<SharedAgentRecord> out;
  for (const auto& [id, record] : *agents) out.push_back(record);
  return out;
}

std::shared_ptr<Mission> MissionRegistry::getOrCreate(const std::string& name) {
  return open(name, std::numeric_limits<std::size_t>::max()).value();  // no limit: never fails
}

namespace {
Status roomFor(const std::map<std::string, std::shared_ptr<Mission>>& missions, const std::string& name,
               std::size_t max_missions) {
  if (missions.count(name) != 0U || missions.size() < max_missions) return Status::Ok();
  return Error{ErrorCode::kResourceExhausted, "this server holds " + std::to_string(missions.size()) +
                                                  " missions, its limit (limits.max_missions); mission '" + name +
                                                  "' cannot start here (use another server, or raise the limit)"};
}
}  // namespace

std::size_t MissionRegistry::size() const {
  return missions_.read()->size();
}

Status MissionRegistry::checkRoom(const std::string& name, std::size_t max_missions) const {
  return roomFor(*missions_.read(), name, max_missions);
}

Result<std::shared_ptr<Mission>> MissionRegistry::open(const std::string& name, std::size_t max_missions) {
  auto missions = missions_.write();
  auto it = missions->find(name);
  if (it != missions->end()) return it->second;
  if (Status room = roomFor(*missions, name, max_missions); !room.ok()) return room.error();
  auto mission = std::make_shared<Mission>(name);
  missions->emplace(name, mission);
  return mission;
}

std::shared_ptr<Mission> MissionRegistry::remove(const std::string& name) {
  auto missions = missions_.write();
  auto it = missions->find(name);
  if (it == missions->end()) return nullptr;
  std::shared_ptr<Mission> out = std::move(it->second);
  missions->erase(it);
  return out;
}

std::shared_ptr<Mission> MissionRegistry::find(const std::string& name) const {
  auto missions = missions_.read();
  auto it = missions->find(name);
  return it == missions->end() ? nullptr : it->second;
}

std::vector<std::shared_ptr<Mission>> MissionRegistry::missions() const {
  auto missions = missions_.read();
  std::vector<std::shared_ptr<Mission>> out;
  for (const auto& [name, mission] : *missions) out.push_back(mission);
  return out;
}

}  // namespace cvislam::server

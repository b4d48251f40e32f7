// Identifiers of keyframes and map points across agents: an (agent, counter) pair, where each agent counts
// its own objects. No global counter exists anywhere, so ids made by different agents (or processes) never
// collide and need no coordination.
#pragma once

#include <compare>
#include <cstdint>
#include <functional>
#include <string>

namespace cvislam {

using AgentId = std::uint16_t;

template <typename Tag>
struct ObjectId {
  AgentId agent = 0;
  std::uint32_t counter = 0;

  // NOLINTNEXTLINE(modernize-use-nullptr): clang-tidy 14 misreads the defaulted three-way comparison
  friend auto operator<=>(const ObjectId&, const ObjectId&) = default;
  [[nodiscard]] std::string toString() const { return std::to_string(agent) + ":" + std::to_string(counter); }
};

struct KeyframeTag {};
struct MapPointTag {};
using KeyframeId = ObjectId<KeyframeTag>;
using MapPointId = ObjectId<MapPointTag>;

// Hands out the next id of one agent; each agent (or each of its modules that creates objects) owns one.
template <typename Id>
class IdCounter {
 public:
  explicit IdCounter(AgentId agent) : agent_(agent) {}
  Id next() noexcept { return Id{agent_, next_++}; }
  [[nodiscard]] AgentId agent() const { return agent_; }

 private:
  AgentId agent_;
  std::uint32_t next_ = 0;
};

}  // namespace cvislam

template <typename Tag>
struct std::hash<cvislam::ObjectId<Tag>> {
  std::size_t operator()(const cvislam::ObjectId<Tag>& id) const noexcept {
    return (static_cast<std::size_t>(id.agent) << 32U) ^ id.counter;
  }
};

// What happened to a mission's maps, as a numbered log: the map service's WatchMission streams it, and a client
// that lost its stream resumes from the next number it wants. Ingest and the back-end append; nothing waits.
// The log keeps the newest `capacity` events; a reader that asks for older ones learns how many it missed.
#pragma once

#include <cstddef>
#include <cstdint>
#include <deque>
#include <string>
#include <vector>

#include "common/core/ids.hpp"
#include "common/core/synchronized.hpp"

namespace cvislam::server {

struct MissionEvent {
  enum class Kind {
    kAgentConnected,     // agent
    kAgentDisconnected,  // agent
    kKeyframeAdded,      // keyframe, map
    kKeyframeRemoved,    // keyframe, map, cause: "agent" (its mapper culled it) or "redundant" (the server)
    kMapsMerged,         // from_map went into map (map fusion)
    kMapCorrected,       // map, keyframes moved, cause: "global BA" or "loop closure"
  };
  std::uint64_t number = 0;  // from 1 within the mission, in the order appended
  std::int64_t t_unix_ns = 0;
  Kind kind = Kind::kKeyframeAdded;
  AgentId agent = 0;
  KeyframeId keyframe;
  std::uint32_t map = 0;
  std::uint32_t from_map = 0;
  std::uint32_t keyframes = 0;
  std::string cause;
};

class MissionEventLog {
 public:
  static constexpr std::size_t kDefaultCapacity = 1U << 16U;
  explicit MissionEventLog(std::size_t capacity = kDefaultCapacity);

  // Numbers and stamps the event (number, t_unix_ns) and keeps it; the oldest goes when the log is full.
  std::uint64_t append(MissionEvent event);

  struct Page {
    std::vector<MissionEvent> events;  // numbered from `from` on (or the oldest held), in order
    std::uint64_t skipped = 0;         // events from `from` on that the log no longer holds
    std::uint64_t next = 0;            // the number to ask for next
  };
  // At most `max` events numbered `from` or later.
  [[nodiscard]] Page read(std::uint64_t from, std::size_t max) const;
  // The number the next event will get (1 while the log is empty).
  [[nodiscard]] std::uint64_t nextNumber() const;

 private:
  struct State {
    std::deque<MissionEvent> events;
    std::uint64_t next_number = 1;
  };
  std::size_t capacity_;
  Synchronized<State> state_;
};

}  // namespace cvislam::server

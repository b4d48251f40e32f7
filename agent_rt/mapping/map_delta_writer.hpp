// The map delta for the link to the server (messages/messages.hpp: MapDeltaMessage). While mapping processes a
// keyframe, the local map reports its structural changes here and they go straight into the delta; afterwards
// finish() adds the keyframe in full, the points made with it, and the states and positions of everything in
// the local map. A keyframe may have two deltas (before and after its local BA): only the first carries it whole.
#pragma once

#include <cstdint>
#include <vector>

#include "agent_rt/map/local_map.hpp"
#include "agent_rt/map/map_events.hpp"
#include "agent_rt/messages/messages.hpp"

namespace cvislam::agent {

// A keyframe's state as the messages carry it.
KeyframeStateMsg toStateMsg(const KeyframeData& keyframe);

class MapDeltaWriter final : public MapEventSink {
 public:
  MapDeltaWriter();  // reserves its scratch once

  // Events recorded from now on go into `delta` (beyond its capacity they are counted as lost).
  void start(MapDeltaMessage& delta);
  void record(const MapEvent& event) override;

  // The map's world frame after the keyframe.
  struct MapFrame {
    std::uint32_t map_id = 0;
    std::uint32_t epoch = 0;
    bool ready = false;                 // final (IMU initialised; vision only: started): the link may send it
    std::uint32_t keyframe_map_id = 0;  // the map the keyframe was inserted into
  };
  // What the delta says of the keyframe just processed: its first delta carries it in full, after its local BA or
  // (when the link sends it sooner) before; a second delta, after the BA, only its state.
  enum class KeyframePart : std::uint8_t { kAfterLocalBa, kBeforeLocalBa, kStateOnly };
  // Writes the rest of the delta started with start().
  void finish(const LocalMap& map, const KeyframeMessage& keyframe, const MapFrame& frame,
              KeyframePart part = KeyframePart::kAfterLocalBa);

 private:
  MapDeltaMessage* delta_ = nullptr;
  std::vector<MapPointId> created_;  // scratch: points made with this keyframe
};

}  // namespace cvislam::agent

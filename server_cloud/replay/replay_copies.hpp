// Copies of a recorded agent for cvislam_replay --copies: one recording makes a mission of many agents flying the
// same place at once, the hardest case for recognition, fusion and global BA.
//
// Copy k of recorded agent a flies under agent id a + k * id_stride (copy 0 is the recording itself), in a world
// frame of its own: the recorded world turned about gravity (z) by k * yaw_step_rad and moved by k *
// step_m. A visual-inertial world frame is fixed only up to yaw and position, so each copy is what another agent
// would have sent flying the same path from another start, and the server must find the transform between the
// copies' maps, not be handed the identity. The batches name everything by counter within the stream's agent
// (keyframes, points, observations), so a copy's batches change only in their poses, velocities and positions.
#pragma once

#include <array>
#include <cstdint>

#include "common/core/ids.hpp"

namespace cvislam::v1 {
class MapBatch;
}

namespace cvislam::server::replay {

struct CopyOptions {
  int copies = 1;             // 1: the recording alone
  AgentId id_stride = 0;      // the agent ids of one copy: recorded id + k * id_stride; >= largest id + 1
  double yaw_step_rad = 0.6;  // copy k's world: turned by k times this about z
  std::array<double, 3> step_m{4.0, -3.0, 0.0};  // ... and moved by k times this
};

// The id copy k gives recorded agent `agent`.
[[nodiscard]] AgentId copyAgentId(AgentId agent, int k, const CopyOptions& options);

// Moves every pose, velocity and position of `batch` from the recorded world frame into copy k's (k = 0: unchanged):
// keyframes' states, their updates, new points and point updates, and the live pose.
void moveToCopyWorld(v1::MapBatch& batch, int k, const CopyOptions& options);

}  // namespace cvislam::server::replay

// Loop closure inside one map (CVI-SLAM IV-A, as in ORB-SLAM's essential graph): a 4-DoF pose graph (yaw about
// gravity and position per keyframe; roll and pitch, which the IMU observes, are held) over
//   - the spanning tree: each agent's IMU chain, and for keyframes without an IMU link their strongest older
//     covisible neighbour,
//   - the strong covisibility edges (at least `strong_covisibility` shared points),
//   - every loop edge closed in this map so far (the new one included),
// with the relative poses the map holds now as measurements, except the loop edges: those carry what place
// recognition measured until a GBA of the map is applied, and the map's relative pose from then on
// (BackendWorker::refreshLoopEdges). The oldest keyframe is held (the gauge). Map points then move with their reference
// keyframes (applyCorrections), and global BA follows.
#pragma once

#include <optional>
#include <vector>

#include "common/core/ids.hpp"
#include "common/core/result.hpp"
#include "common/geometry/lie.hpp"
#include "server_cloud/backend/global_ba.hpp"
#include "server_cloud/stack/map_content.hpp"

namespace cvislam::server::backend {

struct PoseGraphOptions {
  int strong_covisibility = 100;
  int max_iterations = 30;
  // Relative to the other edges. A verified loop (dozens of inliers) is far more precise than the relative poses
  // of a drifted stretch; with equal weights the graph would split the error between the loop and that stretch.
  double loop_weight = 10.0;
  double yaw_weight = 10.0;  // residual units per radian, against metres
  int threads = 2;

  [[nodiscard]] Status validate() const;
};

// A loop edge: keyframe b's body pose in keyframe a's body frame, as measured.
struct LoopEdge {
  KeyframeId a;
  KeyframeId b;
  geometry::SE3d T_a_b;
};

struct PoseGraphSummary {
  int keyframes = 0;
  int tree_edges = 0;
  int covisibility_edges = 0;
  int loop_edges = 0;
  int iterations = 0;
  double initial_cost = 0.0;
  double final_cost = 0.0;
};

// What the solve needs, copied from the map (under its read lock).
struct PoseGraph {
  struct Node {
    KeyframeId id;
    std::int64_t t_ns = 0;
    geometry::SE3d T_w_s;  // the edges' relative poses are taken from these
    // Held at this pose in the solve (keyframes that a windowed BA has just placed, or the part of a merged map
    // that stays where it is).
    std::optional<geometry::SE3d> held_at;
  };
  struct Edge {
    int a = 0;
    int b = 0;
    geometry::SE3d T_a_b;
    double weight = 1.0;
  };
  std::vector<Node> nodes;
  std::vector<Edge> edges;
  PoseGraphSummary summary;
};

// Loop edges whose keyframes are gone are left out.
PoseGraph buildPoseGraph(const MapContent& map, const std::vector<LoopEdge>& loops, const PoseGraphOptions& options);

// Optimises and returns the correction of every node that moved (no velocity or bias: applyCorrections rotates
// velocities). Held nodes fix the gauge; with none, the oldest node is held.
Result<std::vector<KeyframeCorrection>> solvePoseGraph(PoseGraph& graph, const PoseGraphOptions& options);

}  // namespace cvislam::server::backend

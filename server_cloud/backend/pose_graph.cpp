#include "server_cloud/backend/pose_graph.hpp"

#include <algorithm>
#include <cmath>
#include <unordered_map>
#include <unordered_set>

#include <ceres/ceres.h>
#include <ceres/rotation.h>

#include "server_cloud/backend/map_fusion.hpp"

namespace cvislam::server::backend {

namespace {

using geometry::SE3d;

// A turn by `yaw` about the world's vertical.
template <typename T>
Eigen::Matrix<T, 3, 3> aboutGravity(const T& yaw) {
  using std::cos;
  using std::sin;
  Eigen::Matrix<T, 3, 3> Rz;
  Rz << cos(yaw), -sin(yaw), T(0), sin(yaw), cos(yaw), T(0), T(0), T(0), T(1);
  return Rz;
}

template <typename T>
T wrapAngle(const T& a) {
  using std::atan2;
  using std::cos;
  using std::sin;
  return atan2(sin(a), cos(a));
}

// Each node's unknowns are a turn about gravity from its start attitude, R = Rz(turn) R_start (roll and pitch held
// as they are), and its position. r = w [R_a^T (p_b - p_a) - t_ab ; yaw_weight (turn_b - turn_a - turn_ab)].
struct FourDofEdge {
  Eigen::Vector3d t_ab;
  double turn_ab;
  Eigen::Matrix3d R_start_a;
  double weight;
  double yaw_weight;

  template <typename T>
  bool operator()(const T* turn_a, const T* p_a, const T* turn_b, const T* p_b, T* residual) const {
    const Eigen::Matrix<T, 3, 3> R_a = aboutGravity(turn_a[0]) * R_start_a.cast<T>();
    const Eigen::Matrix<T, 3, 1> d(p_b[0] - p_a[0], p_b[1] - p_a[1], p_b[2] - p_a[2]);
    const Eigen::Matrix<T, 3, 1> t = R_a.transpose() * d;
    for (int k = 0; k < 3; ++k) residual[k] = T(weight) * (t[k] - T(t_ab[k]));
    residual[3] = T(weight * yaw_weight) * wrapAngle(turn_b[0] - turn_a[0] - T(turn_ab));
    return true;
  }
};

}  // namespace

Status PoseGraphOptions::validate() const {
  if (strong_covisibility < 1) return Error{ErrorCode::kInvalidArgument, "pose_graph.strong_covisibility must be >= 1"};
  if (max_iterations < 1) return Error{ErrorCode::kInvalidArgument, "pose_graph.max_iterations must be >= 1"};
  if (!(loop_weight > 0.0) || !(yaw_weight > 0.0)) {
    return Error{ErrorCode::kInvalidArgument, "pose_graph weights must be positive"};
  }
  if (threads < 1) return Error{ErrorCode::kInvalidArgument, "pose_graph.threads must be >= 1"};
  return Status::Ok();
}

PoseGraph buildPoseGraph(const MapContent& map, const std::vector<LoopEdge>& loops, const PoseGraphOptions& options) {
  PoseGraph graph;
  std::unordered_map<KeyframeId, int> index;
  for (const auto& [id, kf] : map.keyframes()) graph.nodes.push_back({id, kf.t_ns, kf.T_w_s, std::nullopt});
  std::sort(graph.nodes.begin(), graph.nodes.end(),
            [](const PoseGraph::Node& a, const PoseGraph::Node& b) { return a.id < b.id; });
  for (std::size_t i = 0; i < graph.nodes.size(); ++i) index.emplace(graph.nodes[i].id, static_cast<int>(i));
  graph.summary.keyframes = static_cast<int>(graph.nodes.size());

  std::unordered_set<std::uint64_t> linked;
  const auto key = [](int a, int b) {
    return (static_cast<std::uint64_t>(std::min(a, b)) << 32U) | static_cast<std::uint32_t>(std::max(a, b));
  };
  const auto add = [&](int a, int b, double weight) -> bool {
    if (a == b || !linked.insert(key(a, b)).second) return false;
    const SE3d T_a_b =
        graph.nodes[static_cast<std::size_t>(a)].T_w_s.inverse() * graph.nodes[static_cast<std::size_t>(b)].T_w_s;
    graph.edges.push_back({a, b, T_a_b, weight});
    return true;
  };
  for (const PoseGraph::Node& node : graph.nodes) {
    const ServerKeyframe& kf = *map.keyframe(node.id);
    const int b = index.at(node.id);
    bool has_parent = false;
    if (kf.imu_from) {
      if (const auto it = index.find(*kf.imu_from); it != index.end()) {
        has_parent = true;
        if (add(it->second, b, 1.0)) ++graph.summary.tree_edges;
      }
    }
    // The strongest older covisible neighbour is the parent where there is no IMU link; strong edges always.
    int best_shared = 0;
    int parent = -1;
    for (const auto& [other, shared] : map.covisible(node.id)) {
      const auto it = index.find(other);
      if (it == index.end()) continue;
      if (shared >= options.strong_covisibility && add(it->second, b, 1.0)) ++graph.summary.covisibility_edges;
      const PoseGraph::Node& o = graph.nodes[static_cast<std::size_t>(it->second)];
      if (o.t_ns < node.t_ns && shared > best_shared) {
        best_shared = shared;
        parent = it->second;
      }
    }
    if (!has_parent && parent >= 0 && add(parent, b, 1.0)) ++graph.summary.tree_edges;
  }
  for (const LoopEdge& loop : loops) {
    const auto a = index.find(loop.a);
    const auto b = index.find(loop.b);
    if (a == index.end() || b == index.end()) continue;
    graph.edges.push_back({a->second, b->second, loop.T_a_b, options.loop_weight});
    ++graph.summary.loop_edges;
  }
  return graph;
}

Result<std::vector<KeyframeCorrection>> solvePoseGraph(PoseGraph& graph, const PoseGraphOptions& options) {
  if (Status s = options.validate(); !s.ok()) return s.error();
  const std::size_t n = graph.nodes.size();
  std::vector<double> turn(n, 0.0);
  std::vector<Eigen::Vector3d> p(n);
  std::vector<Eigen::Matrix3d> R_start(n);
  for (std::size_t i = 0; i < n; ++i) {
    const SE3d& start = graph.nodes[i].held_at ? *graph.nodes[i].held_at : graph.nodes[i].T_w_s;
    R_start[i] = start.rotationMatrix();
    p[i] = start.translation();
  }
  ceres::Problem problem;
  for (const PoseGraph::Edge& e : graph.edges) {
    const auto a = static_cast<std::size_t>(e.a);
    const auto b = static_cast<std::size_t>(e.b);
    // The edge's turn is the yaw of R_start_a R_ab R_start_b^T, a world-frame rotation close to one about gravity,
    // whose yaw is well defined. The yaw of a sensor's own attitude is not: an IMU mounted with an axis near the
    // vertical (EuRoC's x-axis points up) is near the Euler angles' singularity, where the heading of that axis
    // swings by degrees for a tenth of a degree of tilt, and a loop measured 0.05 deg off turned its map by 1.8 deg.
    const Eigen::Matrix3d R_turn = R_start[a] * e.T_a_b.rotationMatrix() * R_start[b].transpose();
    FourDofEdge edge{e.T_a_b.translation(), yawOf(R_turn), R_start[a], e.weight, options.yaw_weight};
    problem.AddResidualBlock(new ceres::AutoDiffCostFunction<FourDofEdge, 4, 1, 3, 1, 3>(new FourDofEdge(edge)),
                             nullptr, &turn[a], p[a].data(), &turn[b], p[b].data());
  }
  std::vector<KeyframeCorrection> out;
  if (graph.edges.empty()) return out;
  std::vector<std::uint8_t> held(n, 0);
  for (std::size_t i = 0; i < n; ++i) held[i] = graph.nodes[i].held_at ? 1 : 0;
  if (std::find(held.begin(), held.end(), 1) == held.end()) {
    std::size_t oldest = 0;
    for (std::size_t i = 1; i < n; ++i) {
      if (graph.nodes[i].t_ns < graph.nodes[oldest].t_ns) oldest = i;
    }
    held[oldest] = 1;
  }
  for (std::size_t i = 0; i < n; ++i) {
    if (held[i] == 0 || !problem.HasParameterBlock(&turn[i])) continue;
    problem.SetParameterBlockConstant(&turn[i]);
    problem.SetParameterBlockConstant(p[i].data());
  }
  ceres::Solver::Options solver;
  solver.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  solver.max_num_iterations = options.max_iterations;
  solver.num_threads = options.threads;
  ceres::Solver::Summary summary;
  ceres::Solve(solver, &problem, &summary);
  if (!summary.IsSolutionUsable()) return Error{ErrorCode::kDegenerate, "pose graph failed: " + summary.message};
  graph.summary.iterations = static_cast<int>(summary.iterations.size()) - 1;
  graph.summary.initial_cost = summary.initial_cost;
  graph.summary.final_cost = summary.final_cost;
  out.reserve(n);
  for (std::size_t i = 0; i < n; ++i) {
    if (held[i] != 0) continue;
    const SE3d T_after(geometry::SO3d(Eigen::Matrix3d(aboutGravity(turn[i]) * R_start[i])), p[i]);
    out.push_back({graph.nodes[i].id, graph.nodes[i].T_w_s, T_after, std::nullopt});
  }
  return out;
}

}  // namespace cvislam::server::backend

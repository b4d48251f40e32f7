// A Levenberg-Marquardt solver made for the server's global BA: keyframe states (poses, velocities, biases)
// against 3-dof world points, where every factor that touches a point is a reprojection from one keyframe pose.
//
// Why not Ceres' SPARSE_SCHUR, which it replaces by default: on a 1000-keyframe lap about 40 % of Ceres' time was
// its per-residual machinery (residual-block preparation, ambient Jacobians lifted through the manifold, the
// reduced matrix's per-cell locks), and every Solve() rebuilt its program. This solver knows the structure:
// - the reduced keyframe system's sparsity is worked out once, and CHOLMOD's symbolic analysis with it;
// - reprojection factors give their pose Jacobian in the tangent space directly;
// - each point's 3x3 block and its couplings to the poses that see it are formed, and the point eliminated, in
//   one pass over its observations, split over threads by points (each thread into its own copy of the reduced
//   matrix, summed after);
// - a step rejected by the trust region reuses the linearisation and only eliminates again with the new damping.
//
// Step control follows Ceres' Levenberg-Marquardt, so that both reach the same optimum by the same path: damping
// by the diagonal (clamped to [1e-6, 1e32]) over the trust radius, the radius grown or shrunk by the step's
// gain ratio, a step accepted when the ratio is above 1e-3, convergence when an accepted step lowers the cost by
// less than function_tolerance of it. Robust loss: Cauchy, with residuals and Jacobians scaled by sqrt(rho'), as
// Ceres does for a loss whose second derivative is negative.
#pragma once

#include <atomic>
#include <chrono>
#include <memory>
#include <optional>
#include <vector>

#include <Eigen/Core>

namespace ceres {
class CostFunction;
}  // namespace ceres

namespace cvislam::factors {
class WorldPointReprojectionFactor;
}  // namespace cvislam::factors

namespace cvislam::server::backend {

struct SchurSolverOptions {
  int max_iterations = 15;  // steps, accepted or not (as Ceres counts them)
  double function_tolerance = 1e-4;
  double max_time_s = 120.0;
  // No step is started that would end past this, judged by how long the step before it took; the first step is
  // taken whatever the time, so a solve always moves. Unset: no deadline.
  std::optional<std::chrono::steady_clock::time_point> deadline;
  int threads = 2;
  const std::atomic<bool>* cancel = nullptr;  // polled after every step
};

struct SchurSolverSummary {
  int iterations = 0;
  double initial_cost = 0.0;
  double final_cost = 0.0;
  bool cancelled = false;         // the state is the last accepted one
  bool deadline_reached = false;  // stopped before converging, at the deadline
  // Where the time went.
  double setup_s = 0.0;          // the structure: observations by point, the reduced system's pattern, its analysis
  double linearize_s = 0.0;      // residuals and Jacobians at the accepted states
  double evaluate_s = 0.0;       // the cost of trial states
  double linear_solver_s = 0.0;  // point elimination, factorisation, back-substitution
  // The cost after each accepted step, with the seconds since solve() began: how fast the solve converged, so
  // that a time limit can be judged by what it would have left on the table.
  struct Step {
    double t_s = 0.0;
    double cost = 0.0;
  };
  std::vector<Step> accepted;
};

// The problem. Parameter blocks are the caller's memory (updated in place by solve()); factors are owned.
class SchurProblem {
 public:
  SchurProblem();
  ~SchurProblem();
  SchurProblem(const SchurProblem&) = delete;
  SchurProblem& operator=(const SchurProblem&) = delete;

  // Keyframe-side blocks: a pose [p_w_s, q_w_s xyzw] (PoseManifold, tangent [dp, dphi]), or a Euclidean vector
  // (velocity, biases). Returns the block's index.
  int addPose(double* pose);
  int addVector(double* values, int size);
  // A 3-dof world point. Returns the point's index.
  int addPoint(double* p_w);
  // Held blocks are constants of the problem. A held point's observations still constrain their poses.
  void setKeyframeBlockHeld(int block, bool held);
  void setPointHeld(int point, bool held);

  // A reprojection of `point` from `pose` with a Cauchy loss of `cauchy_scale` (on whitened residuals).
  void addReprojection(std::unique_ptr<factors::WorldPointReprojectionFactor> factor, int pose, int point,
                       double cauchy_scale);
  // A factor between keyframe-side blocks only (IMU, bias random walk, priors), without a loss. Pose blocks are
  // given Ceres' ambient Jacobians (7 columns), lifted with PoseManifold's PlusJacobian.
  void addKeyframeFactor(std::unique_ptr<ceres::CostFunction> factor, std::vector<int> blocks);

  // Half the sum of the robustified squared residuals at the current states; false when a factor cannot be
  // evaluated (a point behind its camera).
  [[nodiscard]] bool cost(double& out, int threads = 1);
  // The gradient of cost() in the tangent space of every free block, as the solver assembles it: keyframe blocks
  // in index order (poses 6, vectors their size), then points (3 each). For tests against numeric differences.
  [[nodiscard]] Eigen::VectorXd gradient();

  SchurSolverSummary solve(const SchurSolverOptions& options);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace cvislam::server::backend

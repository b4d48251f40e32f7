// Trajectory evaluation: associate an estimate with ground truth, align it, and measure its error.
//
// Protocol (DESIGN.md, "Evaluation protocol"): ground truth is interpolated at the estimate's timestamps
// (linear in position, slerp in rotation); estimates outside the ground-truth time span are dropped and
// counted. ATE is the RMSE of position errors after aligning the estimate to the ground truth with
//   posyaw  4-DoF (position + yaw): the right one for visual-inertial estimates, whose roll and pitch
//           are observable through gravity;
//   se3     rotation + translation (Umeyama);
//   sim3    with scale (Umeyama): the scale factor says how far the estimate's scale is off.
// RPE compares relative motion over path-length segments.
//
// Several agents (evaluateJoint) are scored as CVI-SLAM's Table II does: each estimate is associated with
// its own ground truth (all ground truths in one world frame), then ONE transform per alignment is fitted
// over all associated poses together, and the ATE is taken over all of them ("joint"). While the maps are
// still separate, each estimate can instead keep its own transform, and the joint figure pools the errors
// ("each").
//
// The `nearest` association reproduces evo and rpg_trajectory_evaluation (see test/common/eval), so that
// numbers are comparable with published ones.
#pragma once

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "common/core/result.hpp"
#include "common/dataset/types.hpp"
#include "common/geometry/lie.hpp"

namespace cvislam::eval {

enum class AssociationMode {
  kInterpolate,  // ground truth interpolated at each estimate timestamp
  kNearest,      // each estimate pose takes the nearest ground-truth pose (evo's and rpg's protocol)
};

struct AssociationOptions {
  AssociationMode mode = AssociationMode::kInterpolate;
  // nearest: the largest |t_est - t_gt| accepted. interpolate: the estimate must lie this close to a
  // ground-truth sample (so that gaps in the ground truth are not bridged). Defaults when < 0: 20 ms
  // (nearest, as rpg) and 100 ms (interpolate).
  std::int64_t max_diff_ns = -1;
  // Added to estimate timestamps before association (a known clock offset between the two).
  std::int64_t estimate_offset_ns = 0;

  [[nodiscard]] std::int64_t effectiveMaxDiffNs() const;
  [[nodiscard]] Status validate() const;
};

Result<AssociationMode> parseAssociationMode(std::string_view name);  // "interpolate" | "nearest"
std::string_view toString(AssociationMode mode);

// Estimate poses paired with ground-truth poses at the same instants.
struct AssociatedPoses {
  std::vector<std::int64_t> t_ns;            // estimate timestamps (after the offset)
  std::vector<geometry::SE3d> estimate;      // T_w'_b of the estimate, in its own world frame w'
  std::vector<geometry::SE3d> ground_truth;  // T_w_b of the ground truth
  std::size_t estimate_poses = 0;            // poses in the estimate file
  std::size_t outside_span = 0;              // dropped: outside the ground-truth time span
  std::size_t unmatched = 0;                 // dropped: no ground truth within max_diff

  [[nodiscard]] std::size_t size() const { return t_ns.size(); }
};

// Fails when fewer than 3 poses associate, saying which time spans were compared.
Result<AssociatedPoses> associate(const dataset::Trajectory& estimate, const dataset::Trajectory& ground_truth,
                                  const AssociationOptions& options);

enum class Alignment { kNone, kPosYaw, kSE3, kSim3 };
Result<Alignment> parseAlignment(std::string_view name);  // "none" | "posyaw" | "se3" | "sim3"
std::string_view toString(Alignment alignment);

// Statistics of a set of non-negative errors. std is the population standard deviation, median the
// mean of the two middle values for an even count (as numpy).
struct ErrorStats {
  std::size_t count = 0;
  double rmse = 0.0;
  double mean = 0.0;
  double median = 0.0;
  double std = 0.0;
  double min = 0.0;
  double max = 0.0;
};
ErrorStats computeStats(std::vector<double> values);

// Absolute trajectory error under one alignment.
struct AbsoluteError {
  Alignment alignment = Alignment::kSE3;
  geometry::Sim3d S_gt_est;  // maps the estimate's world into the ground truth's
  ErrorStats translation_m;
  ErrorStats rotation_deg;
  // rpg_trajectory_evaluation's per-pose "scale error": | |p_est_aligned| / |p_gt| - 1 | * 100, a ratio of
  // distances from the world origin (so it depends on where the origin is). Reported only so that figures
  // can be compared with that tool; use the Sim3 scale for the scale error.
  ErrorStats rpg_scale_error_percent;
  std::vector<double> translation_errors_m;      // per associated pose
  std::vector<double> rotation_errors_deg;       // per associated pose
  std::vector<double> rpg_scale_errors_percent;  // per associated pose whose ground truth is off the origin
};

// Fits the alignment to the poses, then measures the errors under it.
Result<AbsoluteError> absoluteError(const AssociatedPoses& poses, Alignment alignment);

// The errors of `poses` under a given transform (fitted elsewhere, e.g. to several estimates at once).
AbsoluteError absoluteErrorUnder(const AssociatedPoses& poses, Alignment alignment, const geometry::Sim3d& S_gt_est);

enum class RpePairing {
  kAllStarts,    // every pose starts a segment that ends where the ground-truth path reaches the distance
  kConsecutive,  // back-to-back segments along the estimate's path (evo's default for path deltas)
};

struct RpeOptions {
  std::vector<double> distances_m;  // segment lengths; empty: no RPE
  RpePairing pairing = RpePairing::kAllStarts;
};

struct RelativeError {
  double distance_m = 0.0;
  ErrorStats translation_m;
  ErrorStats translation_percent;  // translation error / path length of the segment
  ErrorStats rotation_deg;
};

// Relative pose error over path-length segments. Segments that the trajectory is too short for are left out;
// a distance with no segment at all yields an entry with count 0.
std::vector<RelativeError> relativeError(const AssociatedPoses& poses, const RpeOptions& options);

struct EvaluationOptions {
  AssociationOptions association;
  RpeOptions rpe;
};

struct Evaluation {
  AssociatedPoses poses;
  std::vector<AbsoluteError> ate;             // posyaw, se3, sim3 (those that could be computed)
  std::optional<double> sim3_scale;           // the scale factor applied to the estimate by the Sim3 alignment
  std::optional<double> scale_error_percent;  // (1 / sim3_scale - 1) * 100: > 0 when the estimate is too large
  std::vector<RelativeError> rpe;
  double ground_truth_path_m = 0.0;  // path length of the associated ground truth
  double duration_s = 0.0;           // time spanned by the associated poses
  std::vector<std::string> notes;    // alignments that failed (degenerate motion) and why

  [[nodiscard]] const AbsoluteError* find(Alignment alignment) const;
};

Result<Evaluation> evaluate(const dataset::Trajectory& estimate, const dataset::Trajectory& ground_truth,
                            const EvaluationOptions& options);

// How several estimates are aligned to their ground truths.
enum class JointAlignment {
  kJoint,  // one transform per alignment, fitted over the poses of all estimates together (CVI-SLAM, Table II)
  kEach,   // each estimate its own transform; the joint figure pools the errors of all poses
};
Result<JointAlignment> parseJointAlignment(std::string_view name);  // "joint" | "each"
std::string_view toString(JointAlignment mode);

// One agent's estimate and its ground truth; `name` says which in messages.
struct TrajectoryPair {
  std::string name;
  const dataset::Trajectory* estimate = nullptr;
  const dataset::Trajectory* ground_truth = nullptr;
};

struct JointEvaluation {
  JointAlignment mode = JointAlignment::kJoint;
  // One per pair, in order, each with its association, RPE and path. Their `ate` (and Sim3 scale) are under
  // the joint transforms (kJoint) or under their own (kEach).
  std::vector<Evaluation> estimates;
  // The joint figure per alignment. kJoint: all poses under the one transform, `S_gt_est`. kEach: the errors
  // of all poses, each under its own estimate's transform, pooled (the RMSE is the square root of the
  // pose-weighted mean of the estimates' mean squares); `S_gt_est` is the identity and means nothing.
  std::vector<AbsoluteError> ate;
  std::optional<double> sim3_scale;           // kJoint only: the joint Sim3's scale factor
  std::optional<double> scale_error_percent;  // kJoint only: (1 / sim3_scale - 1) * 100
  std::size_t poses = 0;                      // associated poses of all estimates
  double ground_truth_path_m = 0.0;           // sum of the estimates' ground-truth paths
  std::vector<std::string> notes;             // alignments that could not be computed and why

  [[nodiscard]] const AbsoluteError* find(Alignment alignment) const;
};

// Associates each pair on its own (the options apply to each), then aligns as `mode` says. Fails, naming the
// pair, when a pair cannot be associated; an alignment that fails (degenerate motion) is a note.
Result<JointEvaluation> evaluateJoint(std::span<const TrajectoryPair> pairs, const EvaluationOptions& options,
                                      JointAlignment mode);

// Length of the polyline through the positions.
double pathLength(const std::vector<geometry::SE3d>& poses);

}  // namespace cvislam::eval

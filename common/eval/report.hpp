// Human- and machine-readable reports of a trajectory evaluation: a table, JSON, and an SVG top view.
#pragma once

#include <span>
#include <string>

#include "common/dataset/types.hpp"
#include "common/eval/trajectory_eval.hpp"

namespace cvislam::eval {

struct ReportLabels {
  std::string estimate;      // what was evaluated (a file name)
  std::string ground_truth;  // against what
  std::string rpe_pairing;   // "all-starts" or "consecutive"
  std::string label;         // the agent's name when several estimates are scored together
  // Poses marked as made before the estimator's initialisation (and left out unless asked for).
  std::size_t before_initialisation = 0;
  bool before_initialisation_scored = false;
};

// A fixed-width table for the terminal.
std::string formatTable(const Evaluation& evaluation, const ReportLabels& labels);

// JSON with "poses", "posyaw"/"se3"/"sim3" objects (rmse, mean, median, max, min, std, rotation and the
// alignment transform), "scale", "scale_error_percent", "rpe", the association counts and "before_initialisation"
// (poses marked as from before the estimator's initialisation; "before_initialisation_scored": whether they were). With
// `per_pose`, also the timestamps, per-pose translation errors under each alignment, the associated
// ground-truth positions ("groundtruth_xyz_m") and the SE3-aligned estimate positions
// ("estimate_se3_aligned_xyz_m"), each an array of [x, y, z].
std::string toJson(const Evaluation& evaluation, const ReportLabels& labels, bool per_pose);

// Top view (x-y) of the ground truth and of the estimate after `alignment`, with a scale bar.
// `ground_truth` is drawn in full; the estimate only where it was associated.
std::string topViewSvg(const Evaluation& evaluation, Alignment alignment, const dataset::Trajectory& ground_truth,
                       const ReportLabels& labels);

// Several estimates scored together (evaluateJoint); `labels` has one entry per estimate, in order.
//
// The table: each estimate's association, then per alignment one line per estimate and a "joint" line; the
// header says whether the joint line used one transform ("joint") or pooled the estimates' own ("each").
std::string formatJointTable(const JointEvaluation& joint, std::span<const ReportLabels> labels);

// {"tool", "align": "joint"|"each", "estimates": [ {"label", "path_m", and the fields of toJson}, ... ],
//  "joint": {"poses", "path_m", "posyaw", "se3", "sim3", "scale", "scale_error_percent", "notes"}}.
// Each estimate's alignment objects are under the joint transform ("joint") or its own ("each"); so are its
// "scale" and "scale_error_percent" (under "joint", the joint Sim3's). The joint alignment objects have a
// "transform_gt_est" under "joint" only, and "scale" and "scale_error_percent" are null under "each".
std::string toJointJson(const JointEvaluation& joint, std::span<const ReportLabels> labels, bool per_pose);

// Top view (x-y) of every ground truth (grey, in full) and every estimate after `alignment` (joint or its
// own, as evaluated), one colour each, with a legend. `ground_truths` is in the order of the estimates.
std::string jointTopViewSvg(const JointEvaluation& joint, Alignment alignment,
                            std::span<const dataset::Trajectory> ground_truths, std::span<const ReportLabels> labels);

}  // namespace cvislam::eval

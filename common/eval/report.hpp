// Human- and machine-readable reports of a trajectory evaluation: a table, JSON, and an SVG top view.
#pragma once

#include <string>

#include "common/dataset/types.hpp"
#include "common/eval/trajectory_eval.hpp"

namespace cvislam::eval {

struct ReportLabels {
  std::string estimate;      // what was evaluated (a file name)
  std::string ground_truth;  // against what
  std::string rpe_pairing;   // "all-starts" or "consecutive"
};

// A fixed-width table for the terminal.
std::string formatTable(const Evaluation& evaluation, const ReportLabels& labels);

// JSON with "poses", "posyaw"/"se3"/"sim3" objects (rmse, mean, median, max, min, std, rotation and the
// alignment transform), "scale", "scale_error_percent", "rpe" and the association counts. With
// `per_pose`, also the timestamps and per-pose translation errors under each alignment.
std::string toJson(const Evaluation& evaluation, const ReportLabels& labels, bool per_pose);

// Top view (x-y) of the ground truth and of the estimate after `alignment`, with a scale bar.
// `ground_truth` is drawn in full; the estimate only where it was associated.
std::string topViewSvg(const Evaluation& evaluation, Alignment alignment, const dataset::Trajectory& ground_truth,
                       const ReportLabels& labels);

}  // namespace cvislam::eval

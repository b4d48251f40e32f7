// cvislam_eval: evaluate a trajectory estimate against EuRoC ground truth.
//
//   cvislam_eval --estimate FILE --groundtruth PATH [--associate interpolate|nearest] [--max-diff SECONDS]
//                [--json OUT] [--plot OUT.svg] [--rpe METERS,...] ...
//
// Several agents at once (CVI-SLAM's Table II): --estimate and --groundtruth given in pairs, all ground truths
// in one world frame, aligned with one transform (--align joint, the default) or each on its own (--align
// each), with --label naming them.
//
// Exit status: 0 evaluated, 1 the inputs could not be evaluated (the message says why), 2 bad command line.
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <set>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "common/core/text.hpp"
#include "common/dataset/trajectory_io.hpp"
#include "common/eval/report.hpp"
#include "common/eval/trajectory_eval.hpp"

namespace {

using cvislam::Status;

Status writeFile(const std::string& path, const std::string& contents) {
  std::ofstream out(path, std::ios::binary);
  out << contents;
  out.close();
  if (!out) return cvislam::Error{cvislam::ErrorCode::kIoError, path + ": cannot write"};
  return Status::Ok();
}

void printFindings(const char* what, const cvislam::Diagnostics& diagnostics) {
  if (diagnostics.empty()) return;
  std::cerr << what << ": " << diagnostics.warningCount() << " row(s) with findings\n";
  diagnostics.print(std::cerr, 5);
}

// The estimates' file stems; where stems repeat, the parent folder's name and the stem; where even those
// repeat, a number after them.
std::vector<std::string> defaultLabels(const std::vector<std::string>& estimate_paths) {
  std::vector<std::string> labels;
  std::multiset<std::string> stems;
  for (const std::string& path : estimate_paths) stems.insert(std::filesystem::path(path).stem().string());
  for (const std::string& path : estimate_paths) {
    const std::filesystem::path p(path);
    std::string label = p.stem().string();
    if (stems.count(label) > 1) {
      const std::string parent = std::filesystem::absolute(p).lexically_normal().parent_path().filename().string();
      if (!parent.empty()) label = parent + "/" + label;
    }
    labels.push_back(label);
  }
  std::multiset<std::string> seen(labels.begin(), labels.end());
  std::map<std::string, int> next;
  for (std::string& label : labels) {
    if (seen.count(label) > 1) label += "#" + std::to_string(++next[label]);
  }
  return labels;
}

}  // namespace

static int run(int argc, char** argv) {
  CLI::App app{
      "Evaluate a trajectory estimate against ground truth: ATE after position+yaw, SE3 and Sim3 alignment, the "
      "scale error, and RPE over path-length segments.\n"
      "Estimates: TUM ('t[s] x y z qx qy qz qw') or EuRoC CSV ('t[ns],x,y,z,qw,qx,qy,qz'), detected from the "
      "content. Ground truth: a EuRoC sequence folder (or its mav0), a state_groundtruth_estimate0 data.csv, or a "
      "TUM file.",
      "cvislam_eval"};
  std::vector<std::string> estimate_paths;
  std::vector<std::string> ground_truth_paths;
  std::vector<std::string> labels_given;
  std::string align_mode;
  std::string association = "interpolate";
  double max_diff_s = -1.0;
  double offset_s = 0.0;
  std::string json_path;
  std::string plot_path;
  std::string plot_alignment = "posyaw";
  std::string estimate_format = "auto";
  std::vector<double> rpe_distances;
  std::string rpe_pairing = "all-starts";
  bool strict = false;
  bool per_pose = false;
  bool quiet = false;

  app.add_option("--estimate", estimate_paths,
                 "Estimated trajectory (TUM or EuRoC CSV). Give it once per agent, each with its --groundtruth, to "
                 "score several agents together")
      ->required()
      ->allow_extra_args(false);
  app.add_option("--groundtruth", ground_truth_paths,
                 "Ground truth: EuRoC sequence folder, data.csv, or TUM file; one per --estimate, in the same order, "
                 "all in one world frame")
      ->required()
      ->allow_extra_args(false);
  app.add_option("--align", align_mode,
                 "With several estimates: joint: one transform per alignment over all their poses (default); each: "
                 "every estimate its own, and the joint figure pools the errors")
      ->check(CLI::IsMember({"joint", "each"}));
  app.add_option("--label", labels_given,
                 "With several estimates: their names, one per --estimate (default: the file stem; the parent "
                 "folder and stem where stems repeat)")
      ->allow_extra_args(false);
  app.add_option("--associate", association,
                 "interpolate: ground truth interpolated at each estimate time (default); nearest: the nearest "
                 "ground-truth pose, as evo and rpg_trajectory_evaluation do")
      ->check(CLI::IsMember({"interpolate", "nearest"}));
  app.add_option("--max-diff", max_diff_s,
                 "Largest time difference in seconds to a ground-truth pose (default: 0.02 for nearest, 0.1 for "
                 "interpolate)")
      ->check(CLI::Range(0.0, 10.0));
  app.add_option("--offset", offset_s, "Seconds added to the estimate's timestamps before association");
  app.add_option("--estimate-format", estimate_format, "auto, tum or euroc")
      ->check(CLI::IsMember({"auto", "tum", "euroc"}));
  app.add_option("--json", json_path, "Write the results as JSON to this file");
  app.add_option("--plot", plot_path, "Write a top view of the ground truth(s) and estimate(s) as SVG to this file");
  app.add_option("--plot-alignment", plot_alignment, "Alignment of the estimate in the plot")
      ->check(CLI::IsMember({"posyaw", "se3", "sim3", "none"}));
  app.add_option("--rpe", rpe_distances, "RPE segment lengths in metres, e.g. --rpe 1,5,10")
      ->delimiter(',')
      ->check(CLI::PositiveNumber);
  app.add_option("--rpe-pairing", rpe_pairing,
                 "all-starts: a segment from every pose (default); consecutive: back-to-back segments along the "
                 "estimate's path, as evo does")
      ->check(CLI::IsMember({"all-starts", "consecutive"}));
  app.add_flag("--strict", strict, "Refuse files with any malformed row instead of skipping the row");
  app.add_flag("--per-pose", per_pose,
               "Add timestamps, per-pose errors, ground-truth positions and SE3-aligned estimate positions to the "
               "JSON");
  app.add_flag("-q,--quiet", quiet, "Do not print the table");
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // --help and --version exit 0; any other command-line error exits 2 after CLI11 prints it.
    return app.exit(e) == 0 ? 0 : 2;
  }
  if (estimate_paths.size() != ground_truth_paths.size()) {
    std::cerr << "cvislam_eval: --estimate given " << estimate_paths.size() << " time(s) but --groundtruth "
              << ground_truth_paths.size() << " time(s); give one --groundtruth per --estimate, in the same order\n";
    return 2;
  }
  if (!labels_given.empty() && labels_given.size() != estimate_paths.size()) {
    std::cerr << "cvislam_eval: --label given " << labels_given.size() << " time(s) for " << estimate_paths.size()
              << " estimate(s); give one per --estimate or none\n";
    return 2;
  }
  if (std::set<std::string>(labels_given.begin(), labels_given.end()).size() != labels_given.size()) {
    std::cerr << "cvislam_eval: --label: every estimate needs a different label\n";
    return 2;
  }

  cvislam::eval::EvaluationOptions options;
  options.association.mode = association == "nearest" ? cvislam::eval::AssociationMode::kNearest
                                                      : cvislam::eval::AssociationMode::kInterpolate;
  if (max_diff_s >= 0.0) options.association.max_diff_ns = static_cast<std::int64_t>(std::llround(max_diff_s * 1e9));
  options.association.estimate_offset_ns = static_cast<std::int64_t>(std::llround(offset_s * 1e9));
  options.rpe.distances_m = rpe_distances;
  options.rpe.pairing =
      rpe_pairing == "consecutive" ? cvislam::eval::RpePairing::kConsecutive : cvislam::eval::RpePairing::kAllStarts;

  cvislam::dataset::TrajectoryReadOptions read_estimate;
  read_estimate.format = cvislam::dataset::parseTrajectoryFormat(estimate_format).value();
  read_estimate.strict = strict;
  cvislam::dataset::TrajectoryReadOptions read_gt;
  read_gt.strict = strict;
  const bool several = estimate_paths.size() > 1;
  const std::vector<std::string> labels_used = labels_given.empty() ? defaultLabels(estimate_paths) : labels_given;
  std::vector<cvislam::dataset::Trajectory> estimates;
  std::vector<cvislam::dataset::Trajectory> ground_truths;
  std::vector<cvislam::eval::ReportLabels> labels;
  for (std::size_t i = 0; i < estimate_paths.size(); ++i) {
    cvislam::Diagnostics estimate_findings;
    auto estimate = cvislam::dataset::readTrajectory(estimate_paths[i], read_estimate, estimate_findings);
    if (!estimate) {
      std::cerr << "cvislam_eval: cannot read the estimate: " << estimate.error().message() << "\n";
      return 1;
    }
    cvislam::Diagnostics gt_findings;
    auto ground_truth = cvislam::dataset::readTrajectory(ground_truth_paths[i], read_gt, gt_findings);
    if (!ground_truth) {
      std::cerr << "cvislam_eval: cannot read the ground truth: " << ground_truth.error().message() << "\n";
      return 1;
    }
    const std::string suffix = several ? " " + labels_used[i] : "";
    printFindings(("estimate" + suffix).c_str(), estimate_findings);
    printFindings(("ground truth" + suffix).c_str(), gt_findings);
    estimates.push_back(std::move(*estimate));
    ground_truths.push_back(std::move(*ground_truth));
    labels.push_back({std::filesystem::path(estimate_paths[i]).filename().string(),
                      std::filesystem::path(ground_truth_paths[i]).filename().string(), rpe_pairing, labels_used[i]});
  }
  const std::string association_line =
      "association:  " + association + ", max difference " +
      cvislam::text::formatDouble(1e-9 * static_cast<double>(options.association.effectiveMaxDiffNs())) + " s\n";
  const auto alignment = cvislam::eval::parseAlignment(plot_alignment).value();

  std::string table;
  std::string json;
  std::string svg;
  if (!several) {
    auto evaluation = cvislam::eval::evaluate(estimates.front(), ground_truths.front(), options);
    if (!evaluation) {
      std::cerr << "cvislam_eval: " << evaluation.error().message() << "\n";
      return 1;
    }
    if (!quiet) table = cvislam::eval::formatTable(*evaluation, labels.front());
    if (!json_path.empty()) json = cvislam::eval::toJson(*evaluation, labels.front(), per_pose);
    if (!plot_path.empty()) {
      svg = cvislam::eval::topViewSvg(*evaluation, alignment, ground_truths.front(), labels.front());
    }
  } else {
    std::vector<cvislam::eval::TrajectoryPair> pairs;
    for (std::size_t i = 0; i < estimates.size(); ++i) {
      pairs.push_back({"'" + labels_used[i] + "' (" + estimate_paths[i] + " against " + ground_truth_paths[i] + ")",
                       &estimates[i], &ground_truths[i]});
    }
    const auto mode =
        align_mode == "each" ? cvislam::eval::JointAlignment::kEach : cvislam::eval::JointAlignment::kJoint;
    auto joint = cvislam::eval::evaluateJoint(pairs, options, mode);
    if (!joint) {
      std::cerr << "cvislam_eval: " << joint.error().message() << "\n";
      return 1;
    }
    if (!quiet) table = cvislam::eval::formatJointTable(*joint, labels);
    if (!json_path.empty()) json = cvislam::eval::toJointJson(*joint, labels, per_pose);
    if (!plot_path.empty()) svg = cvislam::eval::jointTopViewSvg(*joint, alignment, ground_truths, labels);
  }
  if (!quiet) std::cout << association_line << table;
  if (!json_path.empty()) {
    if (Status st = writeFile(json_path, json); !st) {
      std::cerr << "cvislam_eval: " << st.error().message() << "\n";
      return 1;
    }
  }
  if (!plot_path.empty()) {
    if (Status st = writeFile(plot_path, svg); !st) {
      std::cerr << "cvislam_eval: " << st.error().message() << "\n";
      return 1;
    }
  }
  return 0;
}

int main(int argc, char** argv) {
  try {
    return run(argc, argv);
  } catch (const std::exception& e) {  // a bug, or the system out of memory: say so instead of aborting
    std::cerr << "cvislam_eval: internal error: " << e.what() << "\n";
    return 1;
  }
}

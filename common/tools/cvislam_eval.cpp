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
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <utility>
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

struct CommandLine {
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
  bool include_before_init = false;
  bool per_pose = false;
  bool quiet = false;
};

void addOptions(CLI::App& app, CommandLine& cl) {
  app.add_option("--estimate", cl.estimate_paths,
                 "Estimated trajectory (TUM or EuRoC CSV). Give it once per agent, each with its --groundtruth, to "
                 "score several agents together")
      ->required()
      ->allow_extra_args(false);
  app.add_option("--groundtruth", cl.ground_truth_paths,
                 "Ground truth: EuRoC sequence folder, data.csv, or TUM file; one per --estimate, in the same order, "
                 "all in one world frame")
      ->required()
      ->allow_extra_args(false);
  app.add_option("--align", cl.align_mode,
                 "With several estimates: joint: one transform per alignment over all their poses (default); each: "
                 "every estimate its own, and the joint figure pools the errors")
      ->check(CLI::IsMember({"joint", "each"}));
  app.add_option("--label", cl.labels_given,
                 "With several estimates: their names, one per --estimate (default: the file stem; the parent "
                 "folder and stem where stems repeat)")
      ->allow_extra_args(false);
  app.add_option("--associate", cl.association,
                 "interpolate: ground truth interpolated at each estimate time (default); nearest: the nearest "
                 "ground-truth pose, as evo and rpg_trajectory_evaluation do")
      ->check(CLI::IsMember({"interpolate", "nearest"}));
  app.add_option("--max-diff", cl.max_diff_s,
                 "Largest time difference in seconds to a ground-truth pose (default: 0.02 for nearest, 0.1 for "
                 "interpolate)")
      ->check(CLI::Range(0.0, 10.0));
  app.add_option("--offset", cl.offset_s, "Seconds added to the estimate's timestamps before association");
  app.add_option("--estimate-format", cl.estimate_format, "auto, tum or euroc")
      ->check(CLI::IsMember({"auto", "tum", "euroc"}));
  app.add_option("--json", cl.json_path, "Write the results as JSON to this file");
  app.add_option("--plot", cl.plot_path, "Write a top view of the ground truth(s) and estimate(s) as SVG to this file");
  app.add_option("--plot-alignment", cl.plot_alignment, "Alignment of the estimate in the plot")
      ->check(CLI::IsMember({"posyaw", "se3", "sim3", "none"}));
  app.add_option("--rpe", cl.rpe_distances, "RPE segment lengths in metres, e.g. --rpe 1,5,10")
      ->delimiter(',')
      ->check(CLI::PositiveNumber);
  app.add_option("--rpe-pairing", cl.rpe_pairing,
                 "all-starts: a segment from every pose (default); consecutive: back-to-back segments along the "
                 "estimate's path, as evo does")
      ->check(CLI::IsMember({"all-starts", "consecutive"}));
  app.add_flag("--strict", cl.strict, "Refuse files with any malformed row instead of skipping the row");
  app.add_flag("--include-before-init", cl.include_before_init,
               "Also score the estimate's poses from before its initialisation (rows marked '# before_init': not yet "
               "in a final world frame, up to scale in mono); by default they are left out and counted");
  app.add_flag("--per-pose", cl.per_pose,
               "Add timestamps, per-pose errors, ground-truth positions and SE3-aligned estimate positions to the "
               "JSON");
  app.add_flag("-q,--quiet", cl.quiet, "Do not print the table");
}

// The repeated options must pair up: one ground truth and at most one label per estimate. False after saying
// what to fix.
bool pairsHold(const CommandLine& cl) {
  if (cl.estimate_paths.size() != cl.ground_truth_paths.size()) {
    std::cerr << "cvislam_eval: --estimate given " << cl.estimate_paths.size() << " time(s) but --groundtruth "
              << cl.ground_truth_paths.size() << " time(s); give one --groundtruth per --estimate, in the same order\n";
    return false;
  }
  if (!cl.labels_given.empty() && cl.labels_given.size() != cl.estimate_paths.size()) {
    std::cerr << "cvislam_eval: --label given " << cl.labels_given.size() << " time(s) for " << cl.estimate_paths.size()
              << " estimate(s); give one per --estimate or none\n";
    return false;
  }
  if (std::set<std::string>(cl.labels_given.begin(), cl.labels_given.end()).size() != cl.labels_given.size()) {
    std::cerr << "cvislam_eval: --label: every estimate needs a different label\n";
    return false;
  }
  return true;
}

cvislam::eval::EvaluationOptions evaluationOptions(const CommandLine& cl) {
  cvislam::eval::EvaluationOptions options;
  options.association.mode = cl.association == "nearest" ? cvislam::eval::AssociationMode::kNearest
                                                         : cvislam::eval::AssociationMode::kInterpolate;
  if (cl.max_diff_s >= 0.0) {
    options.association.max_diff_ns = static_cast<std::int64_t>(std::llround(cl.max_diff_s * 1e9));
  }
  options.association.estimate_offset_ns = static_cast<std::int64_t>(std::llround(cl.offset_s * 1e9));
  options.rpe.distances_m = cl.rpe_distances;
  options.rpe.pairing =
      cl.rpe_pairing == "consecutive" ? cvislam::eval::RpePairing::kConsecutive : cvislam::eval::RpePairing::kAllStarts;
  return options;
}

struct Inputs {
  std::vector<std::string> labels;  // as given, or made from the file names
  std::vector<cvislam::dataset::Trajectory> estimates;
  std::vector<cvislam::dataset::Trajectory> ground_truths;
  std::vector<cvislam::eval::ReportLabels> report_labels;
};

// Poses from before the estimator's initialisation are scored only when asked: they are not in the frame (nor,
// in mono, the scale) that the rest is. Returns how many there were (left out unless `include`).
std::size_t leaveOutBeforeInitialisation(cvislam::dataset::Trajectory& estimate, bool include) {
  const auto before = [](const cvislam::dataset::StampedPose& p) { return p.before_initialisation; };
  const auto count = static_cast<std::size_t>(std::count_if(estimate.begin(), estimate.end(), before));
  if (!include) estimate.erase(std::remove_if(estimate.begin(), estimate.end(), before), estimate.end());
  return count;
}

// Every estimate with its ground truth, printing what was skipped in each; nothing after saying which file
// could not be read.
std::optional<Inputs> readInputs(const CommandLine& cl) {
  cvislam::dataset::TrajectoryReadOptions read_estimate;
  read_estimate.format = cvislam::dataset::parseTrajectoryFormat(cl.estimate_format).value();
  read_estimate.strict = cl.strict;
  cvislam::dataset::TrajectoryReadOptions read_gt;
  read_gt.strict = cl.strict;
  const bool several = cl.estimate_paths.size() > 1;
  Inputs in;
  in.labels = cl.labels_given.empty() ? defaultLabels(cl.estimate_paths) : cl.labels_given;
  for (std::size_t i = 0; i < cl.estimate_paths.size(); ++i) {
    cvislam::Diagnostics estimate_findings;
    auto estimate = cvislam::dataset::readTrajectory(cl.estimate_paths[i], read_estimate, estimate_findings);
    if (!estimate) {
      std::cerr << "cvislam_eval: cannot read the estimate: " << estimate.error().message() << "\n";
      return std::nullopt;
    }
    cvislam::Diagnostics gt_findings;
    auto ground_truth = cvislam::dataset::readTrajectory(cl.ground_truth_paths[i], read_gt, gt_findings);
    if (!ground_truth) {
      std::cerr << "cvislam_eval: cannot read the ground truth: " << ground_truth.error().message() << "\n";
      return std::nullopt;
    }
    const std::size_t before_init = leaveOutBeforeInitialisation(*estimate, cl.include_before_init);
    if (estimate->empty()) {
      std::cerr << "cvislam_eval: " << cl.estimate_paths[i] << ": every pose is from before the estimator's "
                << "initialisation (" << before_init << " marked '# before_init'); --include-before-init scores them\n";
      return std::nullopt;
    }
    const std::string suffix = several ? " " + in.labels[i] : "";
    printFindings(("estimate" + suffix).c_str(), estimate_findings);
    printFindings(("ground truth" + suffix).c_str(), gt_findings);
    in.estimates.push_back(std::move(*estimate));
    in.ground_truths.push_back(std::move(*ground_truth));
    in.report_labels.push_back({std::filesystem::path(cl.estimate_paths[i]).filename().string(),
                                std::filesystem::path(cl.ground_truth_paths[i]).filename().string(), cl.rpe_pairing,
                                in.labels[i], before_init, cl.include_before_init});
  }
  return in;
}

// What the run writes: the table (unless quiet), the JSON and the SVG (when asked for).
struct Outputs {
  std::string table;
  std::string json;
  std::string svg;
};

cvislam::Result<Outputs> evaluateOne(const CommandLine& cl, const Inputs& in,
                                     const cvislam::eval::EvaluationOptions& options) {
  auto evaluation = cvislam::eval::evaluate(in.estimates.front(), in.ground_truths.front(), options);
  if (!evaluation) return evaluation.error();
  Outputs out;
  if (!cl.quiet) out.table = cvislam::eval::formatTable(*evaluation, in.report_labels.front());
  if (!cl.json_path.empty()) out.json = cvislam::eval::toJson(*evaluation, in.report_labels.front(), cl.per_pose);
  if (!cl.plot_path.empty()) {
    out.svg = cvislam::eval::topViewSvg(*evaluation, cvislam::eval::parseAlignment(cl.plot_alignment).value(),
                                        in.ground_truths.front(), in.report_labels.front());
  }
  return out;
}

cvislam::Result<Outputs> evaluateSeveral(const CommandLine& cl, const Inputs& in,
                                         const cvislam::eval::EvaluationOptions& options) {
  std::vector<cvislam::eval::TrajectoryPair> pairs;
  for (std::size_t i = 0; i < in.estimates.size(); ++i) {
    pairs.push_back({"'" + in.labels[i] + "' (" + cl.estimate_paths[i] + " against " + cl.ground_truth_paths[i] + ")",
                     &in.estimates[i], &in.ground_truths[i]});
  }
  const auto mode =
      cl.align_mode == "each" ? cvislam::eval::JointAlignment::kEach : cvislam::eval::JointAlignment::kJoint;
  auto joint = cvislam::eval::evaluateJoint(pairs, options, mode);
  if (!joint) return joint.error();
  Outputs out;
  if (!cl.quiet) out.table = cvislam::eval::formatJointTable(*joint, in.report_labels);
  if (!cl.json_path.empty()) out.json = cvislam::eval::toJointJson(*joint, in.report_labels, cl.per_pose);
  if (!cl.plot_path.empty()) {
    out.svg = cvislam::eval::jointTopViewSvg(*joint, cvislam::eval::parseAlignment(cl.plot_alignment).value(),
                                             in.ground_truths, in.report_labels);
  }
  return out;
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
  CommandLine cl;
  addOptions(app, cl);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // --help and --version exit 0; any other command-line error exits 2 after CLI11 prints it.
    return app.exit(e) == 0 ? 0 : 2;
  }
  if (!pairsHold(cl)) return 2;

  const cvislam::eval::EvaluationOptions options = evaluationOptions(cl);
  const std::optional<Inputs> in = readInputs(cl);
  if (!in) return 1;
  auto out = in->estimates.size() > 1 ? evaluateSeveral(cl, *in, options) : evaluateOne(cl, *in, options);
  if (!out) {
    std::cerr << "cvislam_eval: " << out.error().message() << "\n";
    return 1;
  }
  if (!cl.quiet) {
    std::cout << "association:  " << cl.association << ", max difference "
              << cvislam::text::formatDouble(1e-9 * static_cast<double>(options.association.effectiveMaxDiffNs()))
              << " s\n"
              << out->table;
  }
  for (const auto& [path, contents] : {std::pair{&cl.json_path, &out->json}, std::pair{&cl.plot_path, &out->svg}}) {
    if (path->empty()) continue;
    if (Status st = writeFile(*path, *contents); !st) {
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

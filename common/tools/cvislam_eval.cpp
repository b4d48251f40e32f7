// cvislam_eval: evaluate a trajectory estimate against EuRoC ground truth.
//
//   cvislam_eval --estimate FILE --groundtruth PATH [--associate interpolate|nearest] [--max-diff SECONDS]
//                [--json OUT] [--plot OUT.svg] [--rpe METERS,...] ...
//
// Exit status: 0 evaluated, 1 the inputs could not be evaluated (the message says why), 2 bad command line.
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
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

}  // namespace

static int run(int argc, char** argv) {
  CLI::App app{
      "Evaluate a trajectory estimate against ground truth: ATE after position+yaw, SE3 and Sim3 alignment, the "
      "scale error, and RPE over path-length segments.\n"
      "Estimates: TUM ('t[s] x y z qx qy qz qw') or EuRoC CSV ('t[ns],x,y,z,qw,qx,qy,qz'), detected from the "
      "content. Ground truth: a EuRoC sequence folder (or its mav0), a state_groundtruth_estimate0 data.csv, or a "
      "TUM file.",
      "cvislam_eval"};
  std::string estimate_path;
  std::string ground_truth_path;
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

  app.add_option("--estimate", estimate_path, "Estimated trajectory (TUM or EuRoC CSV)")->required();
  app.add_option("--groundtruth", ground_truth_path, "Ground truth: EuRoC sequence folder, data.csv, or TUM file")
      ->required();
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
  app.add_option("--plot", plot_path, "Write a top view of both trajectories as SVG to this file");
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
  app.add_flag("--per-pose", per_pose, "Add timestamps and per-pose errors to the JSON");
  app.add_flag("-q,--quiet", quiet, "Do not print the table");
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // --help and --version exit 0; any other command-line error exits 2 after CLI11 prints it.
    return app.exit(e) == 0 ? 0 : 2;
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
  cvislam::Diagnostics estimate_findings;
  auto estimate = cvislam::dataset::readTrajectory(estimate_path, read_estimate, estimate_findings);
  if (!estimate) {
    std::cerr << "cvislam_eval: cannot read the estimate: " << estimate.error().message() << "\n";
    return 1;
  }
  cvislam::dataset::TrajectoryReadOptions read_gt;
  read_gt.strict = strict;
  cvislam::Diagnostics gt_findings;
  auto ground_truth = cvislam::dataset::readTrajectory(ground_truth_path, read_gt, gt_findings);
  if (!ground_truth) {
    std::cerr << "cvislam_eval: cannot read the ground truth: " << ground_truth.error().message() << "\n";
    return 1;
  }
  printFindings("estimate", estimate_findings);
  printFindings("ground truth", gt_findings);

  auto evaluation = cvislam::eval::evaluate(*estimate, *ground_truth, options);
  if (!evaluation) {
    std::cerr << "cvislam_eval: " << evaluation.error().message() << "\n";
    return 1;
  }
  const cvislam::eval::ReportLabels labels{std::filesystem::path(estimate_path).filename().string(),
                                           std::filesystem::path(ground_truth_path).filename().string(), rpe_pairing};
  if (!quiet) {
    std::cout << "association:  " << association << ", max difference "
              << cvislam::text::formatDouble(1e-9 * static_cast<double>(options.association.effectiveMaxDiffNs()))
              << " s\n"
              << cvislam::eval::formatTable(*evaluation, labels);
  }
  if (!json_path.empty()) {
    if (Status st = writeFile(json_path, cvislam::eval::toJson(*evaluation, labels, per_pose)); !st) {
      std::cerr << "cvislam_eval: " << st.error().message() << "\n";
      return 1;
    }
  }
  if (!plot_path.empty()) {
    const auto alignment = cvislam::eval::parseAlignment(plot_alignment).value();
    if (Status st = writeFile(plot_path, cvislam::eval::topViewSvg(*evaluation, alignment, *ground_truth, labels));
        !st) {
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

#include "common/eval/report.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <string>

#include <fmt/format.h>
#include <nlohmann/json.hpp>

#include "common/core/text.hpp"

namespace cvislam::eval {
namespace {

nlohmann::json statsJson(const ErrorStats& s) {
  return {{"count", s.count}, {"rmse", s.rmse}, {"mean", s.mean}, {"median", s.median},
          {"std", s.std},     {"min", s.min},   {"max", s.max}};
}

// 1, 2 or 5 times a power of ten, near `target`.
double niceLength(double target) {
  if (!(target > 0.0)) return 1.0;
  const double base = std::pow(10.0, std::floor(std::log10(target)));
  for (double m : {5.0, 2.0, 1.0}) {
    if (m * base <= target) return m * base;
  }
  return base;
}

std::string escapeXml(const std::string& s) {
  std::string out;
  for (char c : s) {
    switch (c) {
      case '&':
        out += "&amp;";
        break;
      case '<':
        out += "&lt;";
        break;
      case '>':
        out += "&gt;";
        break;
      case '"':
        out += "&quot;";
        break;
      default:
        out += c;
    }
  }
  return out;
}

// The line on poses from before the estimator's initialisation, when it marked any.
std::string beforeInitialisationLine(const ReportLabels& labels) {
  if (labels.before_initialisation == 0) return {};
  return fmt::format("before init:  {} poses marked as estimated before the initialisation: {}\n",
                     labels.before_initialisation,
                     labels.before_initialisation_scored ? "scored (--include-before-init)" : "left out");
}

}  // namespace

std::string formatTable(const Evaluation& ev, const ReportLabels& labels) {
  const AssociatedPoses& p = ev.poses;
  std::string out;
  out += fmt::format("estimate:     {}\nground truth: {}\n", labels.estimate, labels.ground_truth);
  out += fmt::format("poses:        {} of {} associated ({} outside the ground-truth time span, {} without a match)\n",
                     p.size(), p.estimate_poses, p.outside_span, p.unmatched);
  out += beforeInitialisationLine(labels);
  out += fmt::format("span:         {:.1f} s, ground-truth path {:.2f} m\n\n", ev.duration_s, ev.ground_truth_path_m);
  out += fmt::format("{:<8} {:>11} {:>9} {:>9} {:>9} {:>13}\n", "align", "ATE rmse[m]", "mean", "median", "max",
                     "rot rmse[deg]");
  for (const AbsoluteError& e : ev.ate) {
    out += fmt::format("{:<8} {:>11.4f} {:>9.4f} {:>9.4f} {:>9.4f} {:>13.3f}\n", toString(e.alignment),
                       e.translation_m.rmse, e.translation_m.mean, e.translation_m.median, e.translation_m.max,
                       e.rotation_deg.rmse);
  }
  if (ev.sim3_scale) {
    out += fmt::format("\nscale:        {:.5f} (Sim3 factor applied to the estimate); scale error {:+.2f} %\n",
                       *ev.sim3_scale, *ev.scale_error_percent);
  }
  if (!ev.rpe.empty()) {
    out += fmt::format("\nRPE ({} segments)\n{:>10} {:>7} {:>13} {:>10} {:>13}\n", labels.rpe_pairing, "dist[m]",
                       "pairs", "trans rmse[m]", "trans[%]", "rot rmse[deg]");
    for (const RelativeError& r : ev.rpe) {
      out += fmt::format("{:>10.2f} {:>7} {:>13.4f} {:>10.3f} {:>13.3f}\n", r.distance_m, r.translation_m.count,
                         r.translation_m.rmse, r.translation_percent.rmse, r.rotation_deg.rmse);
    }
  }
  for (const std::string& note : ev.notes) out += "note: " + note + "\n";
  return out;
}

namespace {

nlohmann::json transformJson(const geometry::Sim3d& S) {
  const Eigen::Quaterniond& q = S.so3().quaternion();
  return {{"scale", S.scale()},
          {"translation", {S.translation().x(), S.translation().y(), S.translation().z()}},
          {"quaternion_wxyz", {q.w(), q.x(), q.y(), q.z()}}};
}

nlohmann::json absoluteErrorJson(const AbsoluteError& e, bool with_transform, bool per_pose) {
  nlohmann::json a = statsJson(e.translation_m);
  a["rotation_deg"] = statsJson(e.rotation_deg);
  a["rpg_scale_error_percent"] = statsJson(e.rpg_scale_error_percent);
  if (with_transform) a["transform_gt_est"] = transformJson(e.S_gt_est);
  if (per_pose) a["translation_errors_m"] = e.translation_errors_m;
  return a;
}

nlohmann::json optionalJson(const std::optional<double>& value) {
  return value ? nlohmann::json(*value) : nlohmann::json(nullptr);
}

nlohmann::json xyzJson(const Eigen::Vector3d& p) {
  return {p.x(), p.y(), p.z()};
}

// The fields of the single-estimate JSON, without "tool".
nlohmann::json evaluationJson(const Evaluation& ev, const ReportLabels& labels, bool per_pose) {
  nlohmann::json j;
  j["estimate"] = labels.estimate;
  j["groundtruth"] = labels.ground_truth;
  j["poses"] = ev.poses.size();
  j["estimate_poses"] = ev.poses.estimate_poses;
  j["before_initialisation"] = labels.before_initialisation;
  j["before_initialisation_scored"] = labels.before_initialisation_scored;
  j["outside_groundtruth_span"] = ev.poses.outside_span;
  j["unmatched"] = ev.poses.unmatched;
  j["duration_s"] = ev.duration_s;
  j["groundtruth_path_m"] = ev.ground_truth_path_m;
  for (const AbsoluteError& e : ev.ate) {
    j[std::string(toString(e.alignment))] = absoluteErrorJson(e, true, per_pose);
  }
  j["scale"] = optionalJson(ev.sim3_scale);
  j["scale_error_percent"] = optionalJson(ev.scale_error_percent);
  nlohmann::json rpe = nlohmann::json::array();
  for (const RelativeError& r : ev.rpe) {
    rpe.push_back({{"distance_m", r.distance_m},
                   {"pairing", labels.rpe_pairing},
                   {"translation_m", statsJson(r.translation_m)},
                   {"translation_percent", statsJson(r.translation_percent)},
                   {"rotation_deg", statsJson(r.rotation_deg)}});
  }
  j["rpe"] = rpe;
  j["notes"] = ev.notes;
  if (per_pose) {
    std::vector<std::string> stamps;
    stamps.reserve(ev.poses.size());
    for (std::int64_t t : ev.poses.t_ns) stamps.push_back(text::formatNsAsSeconds(t));
    j["timestamps_s"] = stamps;
    nlohmann::json gt = nlohmann::json::array();
    for (const auto& T : ev.poses.ground_truth) gt.push_back(xyzJson(T.translation()));
    j["groundtruth_xyz_m"] = gt;
    if (const AbsoluteError* se3 = ev.find(Alignment::kSE3); se3 != nullptr) {
      nlohmann::json aligned = nlohmann::json::array();
      for (const auto& T : ev.poses.estimate) aligned.push_back(xyzJson(se3->S_gt_est * T.translation()));
      j["estimate_se3_aligned_xyz_m"] = aligned;
    }
  }
  return j;
}

}  // namespace

std::string toJson(const Evaluation& ev, const ReportLabels& labels, bool per_pose) {
  nlohmann::json j = evaluationJson(ev, labels, per_pose);
  j["tool"] = "cvislam_eval";
  return j.dump(1) + "\n";
}

namespace {

struct Polyline {
  std::vector<Eigen::Vector2d> points;
  std::string colour;
  double stroke = 1.0;
};

struct LegendEntry {
  std::string colour;
  std::string text;
};

// An SVG top view: the ground truths first (each with a start marker), then the estimates, a legend with one
// row per entry below the title, a scale bar and a caption. The plot area keeps its size; the picture grows
// with the legend.
std::string drawTopView(const std::string& title, const std::vector<Polyline>& ground_truths,
                        const std::vector<Polyline>& estimates, const std::vector<LegendEntry>& legend) {
  Eigen::Vector2d lo = ground_truths.front().points.front();
  Eigen::Vector2d hi = lo;
  for (const auto* lines : {&ground_truths, &estimates}) {
    for (const Polyline& line : *lines) {
      for (const auto& p : line.points) {
        lo = lo.cwiseMin(p);
        hi = hi.cwiseMax(p);
      }
    }
  }
  const double legend_px = 18.0 * static_cast<double>(legend.size()) + 4.0;
  const double width_px = 800.0;
  const double height_px = 640.0 - 40.0 + legend_px;
  const double margin = 50.0;
  const Eigen::Vector2d extent = (hi - lo).cwiseMax(Eigen::Vector2d(1e-3, 1e-3));
  const double px_per_m =
      std::min((width_px - 2 * margin) / extent.x(), (height_px - 2 * margin - legend_px) / extent.y());
  // World x to the right, world y up.
  const auto to_px = [&](const Eigen::Vector2d& p) {
    return Eigen::Vector2d(margin + (p.x() - lo.x()) * px_per_m, height_px - margin - (p.y() - lo.y()) * px_per_m);
  };
  const auto polyline = [&](const Polyline& line) {
    std::string s =
        fmt::format(R"(<polyline fill="none" stroke="{}" stroke-width="{}" points=")", line.colour, line.stroke);
    for (const auto& p : line.points) {
      const Eigen::Vector2d q = to_px(p);
      s += fmt::format("{:.1f},{:.1f} ", q.x(), q.y());
    }
    return s + "\"/>\n";
  };
  std::string svg = fmt::format(
      R"(<svg xmlns="http://www.w3.org/2000/svg" width="{0}" height="{1}" viewBox="0 0 {0} {1}" font-family="sans-serif" font-size="13">)"
      "\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n",
      width_px, height_px);
  svg += fmt::format("<text x=\"{}\" y=\"22\">{}</text>\n", margin, escapeXml(title));
  for (const Polyline& line : ground_truths) svg += polyline(line);
  for (const Polyline& line : estimates) svg += polyline(line);
  for (const Polyline& line : ground_truths) {
    const Eigen::Vector2d start = to_px(line.points.front());
    svg += fmt::format(R"(<circle cx="{:.1f}" cy="{:.1f}" r="4" fill="#2ca02c"/>)", start.x(), start.y()) + "\n";
  }
  // Legend and scale bar.
  for (std::size_t k = 0; k < legend.size(); ++k) {
    const double y = 40.0 + 18.0 * static_cast<double>(k);
    svg += fmt::format(
        R"(<line x1="{0}" y1="{3}" x2="{1}" y2="{3}" stroke="{4}" stroke-width="2"/><text x="{2}" y="{5}">{6}</text>)"
        "\n",
        margin, margin + 30, margin + 36, y, legend[k].colour, y + 4, escapeXml(legend[k].text));
  }
  const double bar_m = niceLength(0.2 * (width_px - 2 * margin) / px_per_m);
  const double bar_px = bar_m * px_per_m;
  svg += fmt::format(
      R"(<line x1="{0}" y1="{1}" x2="{2}" y2="{1}" stroke="black" stroke-width="3"/><text x="{0}" y="{3}">{4} m</text>)"
      "\n",
      width_px - margin - bar_px, height_px - 20, width_px - margin, height_px - 26, text::formatDouble(bar_m));
  svg += fmt::format("<text x=\"{}\" y=\"{}\">top view (x right, y up)</text>\n", margin, height_px - 20);
  return svg + "</svg>\n";
}

Polyline groundTruthLine(const dataset::Trajectory& ground_truth, const char* colour) {
  Polyline line{{}, colour, 1.5};
  line.points.reserve(ground_truth.size());
  for (const auto& pose : ground_truth) line.points.emplace_back(pose.T_w_b.translation().head<2>());
  return line;
}

Polyline estimateLine(const Evaluation& ev, const geometry::Sim3d& S, std::string colour) {
  Polyline line{{}, std::move(colour), 1.2};
  line.points.reserve(ev.poses.size());
  for (const auto& T : ev.poses.estimate) line.points.emplace_back((S * T.translation()).head<2>());
  return line;
}

// Distinct colours: Tableau's, without its grey (the ground truth's), then hues a golden angle apart.
std::string seriesColour(std::size_t k) {
  static constexpr const char* kPalette[] = {"#d62728", "#1f77b4", "#ff7f0e", "#9467bd", "#8c564b",
                                             "#e377c2", "#17becf", "#bcbd22", "#2ca02c"};
  constexpr std::size_t kCount = sizeof(kPalette) / sizeof(kPalette[0]);
  if (k < kCount) return kPalette[k];
  return fmt::format("hsl({:.0f},70%,40%)", std::fmod(137.508 * static_cast<double>(k - kCount), 360.0));
}

}  // namespace

std::string topViewSvg(const Evaluation& ev, Alignment alignment, const dataset::Trajectory& ground_truth,
                       const ReportLabels& labels) {
  const AbsoluteError* ate = ev.find(alignment);
  const geometry::Sim3d S = ate != nullptr ? ate->S_gt_est : geometry::Sim3d();
  const std::string title =
      ate != nullptr ? fmt::format("{} vs {} - ATE {} {:.3f} m ({} poses)", labels.estimate, labels.ground_truth,
                                   toString(alignment), ate->translation_m.rmse, ev.poses.size())
                     : labels.estimate + " vs " + labels.ground_truth;
  return drawTopView(
      title, {groundTruthLine(ground_truth, "#444444")}, {estimateLine(ev, S, "#d62728")},
      {{"#444444", "ground truth"}, {"#d62728", fmt::format("estimate ({}-aligned)", toString(alignment))}});
}

std::string formatJointTable(const JointEvaluation& joint, std::span<const ReportLabels> labels) {
  const std::size_t n = joint.estimates.size();
  std::size_t width = 8;
  for (const ReportLabels& l : labels) width = std::max(width, l.label.size());
  std::string out;
  if (joint.mode == JointAlignment::kJoint) {
    out += fmt::format("alignment:    joint: one transform per alignment, fitted to all {} estimates together\n", n);
  } else {
    out += "alignment:    each: every estimate aligned on its own\n";
  }
  for (std::size_t i = 0; i < n; ++i) {
    const Evaluation& ev = joint.estimates[i];
    const AssociatedPoses& p = ev.poses;
    out += fmt::format("\n[{}]\nestimate:     {}\nground truth: {}\n", labels[i].label, labels[i].estimate,
                       labels[i].ground_truth);
    out +=
        fmt::format("poses:        {} of {} associated ({} outside the ground-truth time span, {} without a match)\n",
                    p.size(), p.estimate_poses, p.outside_span, p.unmatched);
    out += beforeInitialisationLine(labels[i]);
    out += fmt::format("span:         {:.1f} s, ground-truth path {:.2f} m\n", ev.duration_s, ev.ground_truth_path_m);
  }
  if (joint.mode == JointAlignment::kJoint) {
    out += fmt::format("\nATE; joint line: all {} poses under one transform\n", joint.poses);
  } else {
    out += fmt::format("\nATE; joint line: RMSE pooled over all {} poses, each under its own estimate's transform\n",
                       joint.poses);
  }
  out += fmt::format("{:<8} {:<{}} {:>7} {:>11} {:>9} {:>9} {:>9} {:>13}\n", "align", "estimate", width, "poses",
                     "ATE rmse[m]", "mean", "median", "max", "rot rmse[deg]");
  const auto line = [&](Alignment alignment, const std::string& name, std::size_t poses, const AbsoluteError* e) {
    if (e == nullptr) {
      return fmt::format("{:<8} {:<{}} {:>7} {:>11}\n", toString(alignment), name, width, poses, "failed");
    }
    return fmt::format("{:<8} {:<{}} {:>7} {:>11.4f} {:>9.4f} {:>9.4f} {:>9.4f} {:>13.3f}\n", toString(alignment), name,
                       width, poses, e->translation_m.rmse, e->translation_m.mean, e->translation_m.median,
                       e->translation_m.max, e->rotation_deg.rmse);
  };
  for (Alignment alignment : {Alignment::kPosYaw, Alignment::kSE3, Alignment::kSim3}) {
    const AbsoluteError* pooled = joint.find(alignment);
    if (joint.mode == JointAlignment::kJoint && pooled == nullptr) continue;  // the notes say why
    for (std::size_t i = 0; i < n; ++i) {
      out += line(alignment, labels[i].label, joint.estimates[i].poses.size(), joint.estimates[i].find(alignment));
    }
    out += line(alignment, "joint", joint.poses, pooled);
  }
  if (joint.mode == JointAlignment::kJoint) {
    if (joint.sim3_scale) {
      out +=
          fmt::format("\nscale:        {:.5f} (joint Sim3 factor applied to every estimate); scale error {:+.2f} %\n",
                      *joint.sim3_scale, *joint.scale_error_percent);
    }
  } else {
    out += "\n";
    for (std::size_t i = 0; i < n; ++i) {
      const Evaluation& ev = joint.estimates[i];
      if (!ev.sim3_scale) continue;
      out += fmt::format("scale:        {:<{}} {:.5f} (its own Sim3 factor); scale error {:+.2f} %\n", labels[i].label,
                         width, *ev.sim3_scale, *ev.scale_error_percent);
    }
  }
  if (!joint.estimates.front().rpe.empty()) {
    out += fmt::format("\nRPE ({} segments)\n{:<{}} {:>10} {:>7} {:>13} {:>10} {:>13}\n", labels.front().rpe_pairing,
                       "estimate", width, "dist[m]", "pairs", "trans rmse[m]", "trans[%]", "rot rmse[deg]");
    for (std::size_t i = 0; i < n; ++i) {
      for (const RelativeError& r : joint.estimates[i].rpe) {
        out +=
            fmt::format("{:<{}} {:>10.2f} {:>7} {:>13.4f} {:>10.3f} {:>13.3f}\n", labels[i].label, width, r.distance_m,
                        r.translation_m.count, r.translation_m.rmse, r.translation_percent.rmse, r.rotation_deg.rmse);
      }
    }
  }
  for (const std::string& note : joint.notes) out += "note: " + note + "\n";
  for (std::size_t i = 0; i < n; ++i) {
    for (const std::string& note : joint.estimates[i].notes) out += "note: " + labels[i].label + ": " + note + "\n";
  }
  return out;
}

std::string toJointJson(const JointEvaluation& joint, std::span<const ReportLabels> labels, bool per_pose) {
  nlohmann::json j;
  j["tool"] = "cvislam_eval";
  j["align"] = toString(joint.mode);
  nlohmann::json estimates = nlohmann::json::array();
  for (std::size_t i = 0; i < joint.estimates.size(); ++i) {
    nlohmann::json e = evaluationJson(joint.estimates[i], labels[i], per_pose);
    e["label"] = labels[i].label;
    e["path_m"] = joint.estimates[i].ground_truth_path_m;
    estimates.push_back(std::move(e));
  }
  j["estimates"] = estimates;
  nlohmann::json pooled;
  pooled["poses"] = joint.poses;
  pooled["path_m"] = joint.ground_truth_path_m;
  for (const AbsoluteError& e : joint.ate) {
    pooled[std::string(toString(e.alignment))] = absoluteErrorJson(e, joint.mode == JointAlignment::kJoint, false);
  }
  pooled["scale"] = optionalJson(joint.sim3_scale);
  pooled["scale_error_percent"] = optionalJson(joint.scale_error_percent);
  pooled["notes"] = joint.notes;
  j["joint"] = pooled;
  return j.dump(1) + "\n";
}

std::string jointTopViewSvg(const JointEvaluation& joint, Alignment alignment,
                            std::span<const dataset::Trajectory> ground_truths, std::span<const ReportLabels> labels) {
  constexpr const char* kGrey = "#9e9e9e";
  std::vector<Polyline> gt_lines;
  std::vector<Polyline> est_lines;
  std::vector<LegendEntry> legend = {{kGrey, "ground truth"}};
  for (std::size_t i = 0; i < joint.estimates.size(); ++i) {
    const Evaluation& ev = joint.estimates[i];
    gt_lines.push_back(groundTruthLine(ground_truths[i], kGrey));
    const AbsoluteError* ate = ev.find(alignment);
    const std::string colour = seriesColour(i);
    est_lines.push_back(estimateLine(ev, ate != nullptr ? ate->S_gt_est : geometry::Sim3d(), colour));
    if (alignment == Alignment::kNone) {
      legend.push_back({colour, labels[i].label + " (not aligned)"});
    } else if (ate == nullptr) {
      legend.push_back(
          {colour, labels[i].label + " (not aligned: the " + std::string(toString(alignment)) + " alignment failed)"});
    } else {
      legend.push_back({colour, fmt::format("{} ({}-aligned, ATE {:.3f} m, {} poses)", labels[i].label,
                                            toString(alignment), ate->translation_m.rmse, ev.poses.size())});
    }
  }
  const AbsoluteError* pooled = joint.find(alignment);
  std::string title = fmt::format("{} estimates, {} alignment", joint.estimates.size(), toString(joint.mode));
  if (pooled != nullptr && alignment != Alignment::kNone) {
    title += fmt::format(" - joint ATE {} {:.3f} m ({} poses)", toString(alignment), pooled->translation_m.rmse,
                         joint.poses);
  }
  return drawTopView(title, gt_lines, est_lines, legend);
}

}  // namespace cvislam::eval

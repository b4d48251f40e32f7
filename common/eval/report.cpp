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

}  // namespace

std::string formatTable(const Evaluation& ev, const ReportLabels& labels) {
  const AssociatedPoses& p = ev.poses;
  std::string out;
  out += fmt::format("estimate:     {}\nground truth: {}\n", labels.estimate, labels.ground_truth);
  out += fmt::format("poses:        {} of {} associated ({} outside the ground-truth time span, {} without a match)\n",
                     p.size(), p.estimate_poses, p.outside_span, p.unmatched);
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

std::string toJson(const Evaluation& ev, const ReportLabels& labels, bool per_pose) {
  nlohmann::json j;
  j["tool"] = "cvislam_eval";
  j["estimate"] = labels.estimate;
  j["groundtruth"] = labels.ground_truth;
  j["poses"] = ev.poses.size();
  j["estimate_poses"] = ev.poses.estimate_poses;
  j["outside_groundtruth_span"] = ev.poses.outside_span;
  j["unmatched"] = ev.poses.unmatched;
  j["duration_s"] = ev.duration_s;
  j["groundtruth_path_m"] = ev.ground_truth_path_m;
  for (const AbsoluteError& e : ev.ate) {
    nlohmann::json a = statsJson(e.translation_m);
    a["rotation_deg"] = statsJson(e.rotation_deg);
    a["rpg_scale_error_percent"] = statsJson(e.rpg_scale_error_percent);
    const Eigen::Quaterniond& q = e.S_gt_est.so3().quaternion();
    a["transform_gt_est"] = {
        {"scale", e.S_gt_est.scale()},
        {"translation", {e.S_gt_est.translation().x(), e.S_gt_est.translation().y(), e.S_gt_est.translation().z()}},
        {"quaternion_wxyz", {q.w(), q.x(), q.y(), q.z()}}};
    if (per_pose) a["translation_errors_m"] = e.translation_errors_m;
    j[std::string(toString(e.alignment))] = a;
  }
  j["scale"] = ev.sim3_scale ? nlohmann::json(*ev.sim3_scale) : nlohmann::json(nullptr);
  j["scale_error_percent"] = ev.scale_error_percent ? nlohmann::json(*ev.scale_error_percent) : nlohmann::json(nullptr);
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
  }
  return j.dump(1) + "\n";
}

std::string topViewSvg(const Evaluation& ev, Alignment alignment, const dataset::Trajectory& ground_truth,
                       const ReportLabels& labels) {
  const AbsoluteError* ate = ev.find(alignment);
  const geometry::Sim3d S = ate != nullptr ? ate->S_gt_est : geometry::Sim3d();
  std::vector<Eigen::Vector2d> gt;
  std::vector<Eigen::Vector2d> est;
  gt.reserve(ground_truth.size());
  for (const auto& pose : ground_truth) gt.emplace_back(pose.T_w_b.translation().head<2>());
  for (const auto& T : ev.poses.estimate) est.emplace_back((S * T.translation()).head<2>());

  Eigen::Vector2d lo = gt.front();
  Eigen::Vector2d hi = gt.front();
  for (const auto* points : {&gt, &est}) {
    for (const auto& p : *points) {
      lo = lo.cwiseMin(p);
      hi = hi.cwiseMax(p);
    }
  }
  const double width_px = 800.0;
  const double height_px = 640.0;
  const double margin = 50.0;
  const Eigen::Vector2d extent = (hi - lo).cwiseMax(Eigen::Vector2d(1e-3, 1e-3));
  const double px_per_m = std::min((width_px - 2 * margin) / extent.x(), (height_px - 2 * margin - 40) / extent.y());
  // World x to the right, world y up.
  const auto to_px = [&](const Eigen::Vector2d& p) {
    return Eigen::Vector2d(margin + (p.x() - lo.x()) * px_per_m, height_px - margin - (p.y() - lo.y()) * px_per_m);
  };
  const auto polyline = [&](const std::vector<Eigen::Vector2d>& points, const char* colour, double stroke) {
    std::string s = fmt::format(R"(<polyline fill="none" stroke="{}" stroke-width="{}" points=")", colour, stroke);
    for (const auto& p : points) {
      const Eigen::Vector2d q = to_px(p);
      s += fmt::format("{:.1f},{:.1f} ", q.x(), q.y());
    }
    return s + "\"/>\n";
  };
  std::string svg = fmt::format(
      R"(<svg xmlns="http://www.w3.org/2000/svg" width="{0}" height="{1}" viewBox="0 0 {0} {1}" font-family="sans-serif" font-size="13">)"
      "\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n",
      width_px, height_px);
  const std::string title =
      ate != nullptr ? fmt::format("{} vs {} - ATE {} {:.3f} m ({} poses)", labels.estimate, labels.ground_truth,
                                   toString(alignment), ate->translation_m.rmse, ev.poses.size())
                     : labels.estimate + " vs " + labels.ground_truth;
  svg += fmt::format("<text x=\"{}\" y=\"22\">{}</text>\n", margin, escapeXml(title));
  svg += polyline(gt, "#444444", 1.5);
  svg += polyline(est, "#d62728", 1.2);
  const Eigen::Vector2d start = to_px(gt.front());
  svg += fmt::format(R"(<circle cx="{:.1f}" cy="{:.1f}" r="4" fill="#2ca02c"/>)", start.x(), start.y()) + "\n";
  // Legend and scale bar.
  svg += fmt::format(
      R"(<line x1="{0}" y1="40" x2="{1}" y2="40" stroke="#444444" stroke-width="2"/><text x="{2}" y="44">ground truth</text>)"
      "\n",
      margin, margin + 30, margin + 36);
  svg += fmt::format(
      R"(<line x1="{0}" y1="58" x2="{1}" y2="58" stroke="#d62728" stroke-width="2"/><text x="{2}" y="62">estimate ({3}-aligned)</text>)"
      "\n",
      margin, margin + 30, margin + 36, toString(alignment));
  const double bar_m = niceLength(0.2 * (width_px - 2 * margin) / px_per_m);
  const double bar_px = bar_m * px_per_m;
  svg += fmt::format(
      R"(<line x1="{0}" y1="{1}" x2="{2}" y2="{1}" stroke="black" stroke-width="3"/><text x="{0}" y="{3}">{4} m</text>)"
      "\n",
      width_px - margin - bar_px, height_px - 20, width_px - margin, height_px - 26, text::formatDouble(bar_m));
  svg += fmt::format("<text x=\"{}\" y=\"{}\">top view (x right, y up)</text>\n", margin, height_px - 20);
  return svg + "</svg>\n";
}

}  // namespace cvislam::eval

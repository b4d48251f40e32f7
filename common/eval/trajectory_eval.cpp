#include "common/eval/trajectory_eval.hpp"

#include <algorithm>
#include <cmath>
#include <numeric>

#include "common/core/text.hpp"
#include "common/geometry/alignment.hpp"

namespace cvislam::eval {
namespace {

constexpr double kRadToDeg = 180.0 / 3.14159265358979323846;
constexpr std::int64_t kDefaultNearestMaxDiffNs = 20'000'000;       // rpg_trajectory_evaluation's 20 ms
constexpr std::int64_t kDefaultInterpolateMaxDiffNs = 100'000'000;  // do not bridge ground-truth gaps > 0.2 s

std::string spanText(const dataset::Trajectory& t) {
  return text::formatNsAsSeconds(t.front().t_ns) + " .. " + text::formatNsAsSeconds(t.back().t_ns) + " s";
}

geometry::SE3d interpolate(const geometry::SE3d& a, const geometry::SE3d& b, double alpha) {
  const Eigen::Vector3d p = (1.0 - alpha) * a.translation() + alpha * b.translation();
  return geometry::SE3d(a.quaternion().slerp(alpha, b.quaternion()), p);  // slerp takes the short arc
}

std::vector<Eigen::Vector3d> positions(const std::vector<geometry::SE3d>& poses) {
  std::vector<Eigen::Vector3d> out;
  out.reserve(poses.size());
  for (const auto& T : poses) out.push_back(T.translation());
  return out;
}

}  // namespace

std::int64_t AssociationOptions::effectiveMaxDiffNs() const {
  if (max_diff_ns >= 0) return max_diff_ns;
  return mode == AssociationMode::kNearest ? kDefaultNearestMaxDiffNs : kDefaultInterpolateMaxDiffNs;
}

Status AssociationOptions::validate() const {
  if (max_diff_ns > 10'000'000'000LL) {
    return Error{ErrorCode::kInvalidArgument, "association max_diff must be at most 10 s"};
  }
  return Status::Ok();
}

Result<AssociationMode> parseAssociationMode(std::string_view name) {
  if (name == "interpolate") return AssociationMode::kInterpolate;
  if (name == "nearest") return AssociationMode::kNearest;
  return Error{ErrorCode::kInvalidArgument, "unknown association '" + std::string(name) + "' (interpolate, nearest)"};
}

std::string_view toString(AssociationMode mode) {
  return mode == AssociationMode::kNearest ? "nearest" : "interpolate";
}

Result<Alignment> parseAlignment(std::string_view name) {
  if (name == "none") return Alignment::kNone;
  if (name == "posyaw") return Alignment::kPosYaw;
  if (name == "se3") return Alignment::kSE3;
  if (name == "sim3") return Alignment::kSim3;
  return Error{ErrorCode::kInvalidArgument, "unknown alignment '" + std::string(name) + "' (none, posyaw, se3, sim3)"};
}

std::string_view toString(Alignment alignment) {
  switch (alignment) {
    case Alignment::kNone:
      return "none";
    case Alignment::kPosYaw:
      return "posyaw";
    case Alignment::kSE3:
      return "se3";
    case Alignment::kSim3:
      return "sim3";
  }
  return "unknown";
}

Result<AssociatedPoses> associate(const dataset::Trajectory& estimate, const dataset::Trajectory& ground_truth,
                                  const AssociationOptions& options) {
  if (Status st = options.validate(); !st) return st.error();
  if (estimate.empty()) return Error{ErrorCode::kInvalidArgument, "the estimate has no poses"};
  if (ground_truth.size() < 2) return Error{ErrorCode::kInvalidArgument, "the ground truth needs at least 2 poses"};
  const std::int64_t max_diff = options.effectiveMaxDiffNs();
  AssociatedPoses out;
  out.estimate_poses = estimate.size();
  const std::int64_t gt_first = ground_truth.front().t_ns;
  const std::int64_t gt_last = ground_truth.back().t_ns;
  const auto gt_begin = ground_truth.begin();
  const auto gt_end = ground_truth.end();

  for (const dataset::StampedPose& est : estimate) {
    const std::int64_t t = est.t_ns + options.estimate_offset_ns;
    // First ground-truth pose at or after t.
    const auto after = std::lower_bound(
        gt_begin, gt_end, t, [](const dataset::StampedPose& p, std::int64_t value) { return p.t_ns < value; });
    if (options.mode == AssociationMode::kNearest) {
      auto best = after;
      if (after == gt_end || (after != gt_begin && t - std::prev(after)->t_ns <= after->t_ns - t)) {
        best = std::prev(after);  // ties go to the earlier pose, as numpy's argmin
      }
      if (std::llabs(best->t_ns - t) > max_diff) {
        ++((t < gt_first || t > gt_last) ? out.outside_span : out.unmatched);
        continue;
      }
      out.t_ns.push_back(t);
      out.estimate.push_back(est.T_w_b);
      out.ground_truth.push_back(best->T_w_b);
      continue;
    }
    if (t < gt_first || t > gt_last) {
      ++out.outside_span;
      continue;
    }
    if (after->t_ns == t) {
      out.t_ns.push_back(t);
      out.estimate.push_back(est.T_w_b);
      out.ground_truth.push_back(after->T_w_b);
      continue;
    }
    const auto before = std::prev(after);
    if (std::min(t - before->t_ns, after->t_ns - t) > max_diff) {
      ++out.unmatched;  // inside a gap of the ground truth
      continue;
    }
    const double alpha = static_cast<double>(t - before->t_ns) / static_cast<double>(after->t_ns - before->t_ns);
    out.t_ns.push_back(t);
    out.estimate.push_back(est.T_w_b);
    out.ground_truth.push_back(interpolate(before->T_w_b, after->T_w_b, alpha));
  }
  if (out.size() < 3) {
    return Error{ErrorCode::kDataError,
                 "only " + std::to_string(out.size()) + " of " + std::to_string(estimate.size()) +
                     " estimate poses could be associated with the ground truth (estimate " + spanText(estimate) +
                     ", ground truth " + spanText(ground_truth) + ", max difference " +
                     text::formatNsAsSeconds(max_diff) +
                     " s); check that both use the same clock and that timestamps are in the expected unit"};
  }
  return out;
}

ErrorStats computeStats(std::vector<double> values) {
  ErrorStats s;
  s.count = values.size();
  if (values.empty()) return s;
  const double n = static_cast<double>(values.size());
  double sum = 0.0;
  double sum_sq = 0.0;
  for (double v : values) {
    sum += v;
    sum_sq += v * v;
  }
  s.mean = sum / n;
  s.rmse = std::sqrt(sum_sq / n);
  double var = 0.0;
  for (double v : values) var += (v - s.mean) * (v - s.mean);
  s.std = std::sqrt(var / n);
  const auto [lo, hi] = std::minmax_element(values.begin(), values.end());
  s.min = *lo;
  s.max = *hi;
  const std::size_t mid = values.size() / 2;
  std::nth_element(values.begin(), values.begin() + static_cast<std::ptrdiff_t>(mid), values.end());
  const double upper = values[mid];
  if (values.size() % 2 == 1) {
    s.median = upper;
  } else {
    const double lower = *std::max_element(values.begin(), values.begin() + static_cast<std::ptrdiff_t>(mid));
    s.median = 0.5 * (lower + upper);
  }
  return s;
}

Result<AbsoluteError> absoluteError(const AssociatedPoses& poses, Alignment alignment) {
  const std::vector<Eigen::Vector3d> p_est = positions(poses.estimate);
  const std::vector<Eigen::Vector3d> p_gt = positions(poses.ground_truth);
  geometry::Sim3d S_gt_est;
  switch (alignment) {
    case Alignment::kNone:
      break;
    case Alignment::kPosYaw: {
      auto T = geometry::alignPositionYaw(p_est, p_gt);
      if (!T) return T.error();
      S_gt_est = geometry::Sim3d(*T);
      break;
    }
    case Alignment::kSE3: {
      auto T = geometry::alignSE3(p_est, p_gt);
      if (!T) return T.error();
      S_gt_est = geometry::Sim3d(*T);
      break;
    }
    case Alignment::kSim3: {
      auto S = geometry::alignSim3(p_est, p_gt);
      if (!S) return S.error();
      S_gt_est = *S;
      break;
    }
  }
  return absoluteErrorUnder(poses, alignment, S_gt_est);
}

AbsoluteError absoluteErrorUnder(const AssociatedPoses& poses, Alignment alignment, const geometry::Sim3d& S_gt_est) {
  AbsoluteError out;
  out.alignment = alignment;
  out.S_gt_est = S_gt_est;
  out.translation_errors_m.reserve(poses.size());
  out.rotation_errors_deg.reserve(poses.size());
  for (std::size_t i = 0; i < poses.size(); ++i) {
    const Eigen::Vector3d& p_gt = poses.ground_truth[i].translation();
    const Eigen::Vector3d p_aligned = S_gt_est * poses.estimate[i].translation();
    out.translation_errors_m.push_back((p_gt - p_aligned).norm());
    const geometry::SO3d R_err = poses.ground_truth[i].so3().inverse() * S_gt_est.so3() * poses.estimate[i].so3();
    out.rotation_errors_deg.push_back(R_err.log().norm() * kRadToDeg);
    if (p_gt.norm() > 0.0) {
      out.rpg_scale_errors_percent.push_back(std::abs(p_aligned.norm() / p_gt.norm() - 1.0) * 100.0);
    }
  }
  out.translation_m = computeStats(out.translation_errors_m);
  out.rotation_deg = computeStats(out.rotation_errors_deg);
  out.rpg_scale_error_percent = computeStats(out.rpg_scale_errors_percent);
  return out;
}

double pathLength(const std::vector<geometry::SE3d>& poses) {
  double length = 0.0;
  for (std::size_t i = 1; i < poses.size(); ++i) length += (poses[i].translation() - poses[i - 1].translation()).norm();
  return length;
}

std::vector<RelativeError> relativeError(const AssociatedPoses& poses, const RpeOptions& options) {
  std::vector<RelativeError> out;
  const std::size_t n = poses.size();
  // Cumulative path length along the ground truth and along the estimate.
  std::vector<double> path_gt(n, 0.0);
  std::vector<double> path_est(n, 0.0);
  for (std::size_t i = 1; i < n; ++i) {
    path_gt[i] =
        path_gt[i - 1] + (poses.ground_truth[i].translation() - poses.ground_truth[i - 1].translation()).norm();
    path_est[i] = path_est[i - 1] + (poses.estimate[i].translation() - poses.estimate[i - 1].translation()).norm();
  }
  for (double distance : options.distances_m) {
    std::vector<std::pair<std::size_t, std::size_t>> pairs;
    if (options.pairing == RpePairing::kAllStarts) {
      for (std::size_t i = 0; i < n; ++i) {
        const auto it =
            std::lower_bound(path_gt.begin() + static_cast<std::ptrdiff_t>(i), path_gt.end(), path_gt[i] + distance);
        if (it == path_gt.end()) break;  // later starts cannot reach the distance either
        pairs.emplace_back(i, static_cast<std::size_t>(it - path_gt.begin()));
      }
    } else {
      // Segment ends where the estimate's path since the previous end first reaches the distance.
      std::vector<std::size_t> ends;
      double since_last = 0.0;
      for (std::size_t i = 1; i < n; ++i) {
        since_last += path_est[i] - path_est[i - 1];
        if (since_last >= distance) {
          ends.push_back(i);
          since_last = 0.0;
        }
      }
      for (std::size_t k = 1; k < ends.size(); ++k) pairs.emplace_back(ends[k - 1], ends[k]);
    }
    std::vector<double> trans;
    std::vector<double> percent;
    std::vector<double> rot;
    for (const auto& [i, j] : pairs) {
      const geometry::SE3d delta_gt = poses.ground_truth[i].inverse() * poses.ground_truth[j];
      const geometry::SE3d delta_est = poses.estimate[i].inverse() * poses.estimate[j];
      const geometry::SE3d E = delta_gt.inverse() * delta_est;
      trans.push_back(E.translation().norm());
      const double segment = path_gt[j] - path_gt[i];
      if (segment > 0.0) percent.push_back(100.0 * trans.back() / segment);
      rot.push_back(E.so3().log().norm() * kRadToDeg);
    }
    RelativeError rpe;
    rpe.distance_m = distance;
    rpe.translation_m = computeStats(std::move(trans));
    rpe.translation_percent = computeStats(std::move(percent));
    rpe.rotation_deg = computeStats(std::move(rot));
    out.push_back(rpe);
  }
  return out;
}

const AbsoluteError* Evaluation::find(Alignment alignment) const {
  for (const AbsoluteError& e : ate) {
    if (e.alignment == alignment) return &e;
  }
  return nullptr;
}

namespace {

constexpr Alignment kReportedAlignments[] = {Alignment::kPosYaw, Alignment::kSE3, Alignment::kSim3};

// Association, RPE, path and duration: all of an evaluation but the ATE.
Result<Evaluation> evaluateUnaligned(const dataset::Trajectory& estimate, const dataset::Trajectory& ground_truth,
                                     const EvaluationOptions& options) {
  for (double d : options.rpe.distances_m) {
    if (!(d > 0.0)) return Error{ErrorCode::kInvalidArgument, "RPE distances must be > 0 m"};
  }
  auto associated = associate(estimate, ground_truth, options.association);
  if (!associated) return associated.error();
  Evaluation ev;
  ev.poses = std::move(*associated);
  ev.rpe = relativeError(ev.poses, options.rpe);
  ev.ground_truth_path_m = pathLength(ev.poses.ground_truth);
  ev.duration_s = 1e-9 * static_cast<double>(ev.poses.t_ns.back() - ev.poses.t_ns.front());
  return ev;
}

void setSim3Scale(const geometry::Sim3d& S_gt_est, std::optional<double>& scale,
                  std::optional<double>& scale_error_percent) {
  scale = S_gt_est.scale();
  scale_error_percent = (1.0 / S_gt_est.scale() - 1.0) * 100.0;
}

// Each alignment fitted to the evaluation's own poses.
void alignOnItsOwn(Evaluation& ev) {
  for (Alignment alignment : kReportedAlignments) {
    auto ate = absoluteError(ev.poses, alignment);
    if (!ate) {
      ev.notes.push_back(std::string(toString(alignment)) + " alignment failed: " + ate.error().message());
      continue;
    }
    if (alignment == Alignment::kSim3) setSim3Scale(ate->S_gt_est, ev.sim3_scale, ev.scale_error_percent);
    ev.ate.push_back(std::move(*ate));
  }
}

template <typename T>
void append(std::vector<T>& to, const std::vector<T>& from) {
  to.insert(to.end(), from.begin(), from.end());
}

// One transform per alignment over the poses of all estimates; each estimate measured under it.
void alignJointly(JointEvaluation& joint) {
  AssociatedPoses all;
  for (const Evaluation& ev : joint.estimates) {
    append(all.t_ns, ev.poses.t_ns);
    append(all.estimate, ev.poses.estimate);
    append(all.ground_truth, ev.poses.ground_truth);
  }
  for (Alignment alignment : kReportedAlignments) {
    auto ate = absoluteError(all, alignment);
    if (!ate) {
      joint.notes.push_back("joint " + std::string(toString(alignment)) +
                            " alignment failed: " + ate.error().message());
      continue;
    }
    for (Evaluation& ev : joint.estimates) {
      ev.ate.push_back(absoluteErrorUnder(ev.poses, alignment, ate->S_gt_est));
      if (alignment == Alignment::kSim3) setSim3Scale(ate->S_gt_est, ev.sim3_scale, ev.scale_error_percent);
    }
    if (alignment == Alignment::kSim3) setSim3Scale(ate->S_gt_est, joint.sim3_scale, joint.scale_error_percent);
    joint.ate.push_back(std::move(*ate));
  }
}

// Each estimate its own transform; the joint figure pools the per-pose errors of all.
void alignEachAndPool(JointEvaluation& joint, std::span<const TrajectoryPair> pairs) {
  for (Evaluation& ev : joint.estimates) alignOnItsOwn(ev);
  for (Alignment alignment : kReportedAlignments) {
    AbsoluteError pooled;
    pooled.alignment = alignment;
    std::string failed;
    for (std::size_t i = 0; i < joint.estimates.size(); ++i) {
      const AbsoluteError* own = joint.estimates[i].find(alignment);
      if (own == nullptr) {
        failed += (failed.empty() ? "" : ", ") + pairs[i].name;
        continue;
      }
      append(pooled.translation_errors_m, own->translation_errors_m);
      append(pooled.rotation_errors_deg, own->rotation_errors_deg);
      append(pooled.rpg_scale_errors_percent, own->rpg_scale_errors_percent);
    }
    if (!failed.empty()) {
      joint.notes.push_back("no pooled " + std::string(toString(alignment)) + " figure: the " +
                            std::string(toString(alignment)) + " alignment of " + failed + " failed");
      continue;
    }
    pooled.translation_m = computeStats(pooled.translation_errors_m);
    pooled.rotation_deg = computeStats(pooled.rotation_errors_deg);
    pooled.rpg_scale_error_percent = computeStats(pooled.rpg_scale_errors_percent);
    joint.ate.push_back(std::move(pooled));
  }
}

}  // namespace

Result<Evaluation> evaluate(const dataset::Trajectory& estimate, const dataset::Trajectory& ground_truth,
                            const EvaluationOptions& options) {
  auto ev = evaluateUnaligned(estimate, ground_truth, options);
  if (!ev) return ev.error();
  alignOnItsOwn(*ev);
  return ev;
}

Result<JointAlignment> parseJointAlignment(std::string_view name) {
  if (name == "joint") return JointAlignment::kJoint;
  if (name == "each") return JointAlignment::kEach;
  return Error{ErrorCode::kInvalidArgument, "unknown joint alignment '" + std::string(name) + "' (joint, each)"};
}

std::string_view toString(JointAlignment mode) {
  return mode == JointAlignment::kEach ? "each" : "joint";
}

const AbsoluteError* JointEvaluation::find(Alignment alignment) const {
  for (const AbsoluteError& e : ate) {
    if (e.alignment == alignment) return &e;
  }
  return nullptr;
}

Result<JointEvaluation> evaluateJoint(std::span<const TrajectoryPair> pairs, const EvaluationOptions& options,
                                      JointAlignment mode) {
  if (pairs.empty()) return Error{ErrorCode::kInvalidArgument, "no estimate to evaluate"};
  JointEvaluation joint;
  joint.mode = mode;
  for (const TrajectoryPair& pair : pairs) {
    if (pair.estimate == nullptr || pair.ground_truth == nullptr) {
      return Error{ErrorCode::kInvalidArgument, "estimate " + pair.name + ": no trajectory given"};
    }
    auto ev = evaluateUnaligned(*pair.estimate, *pair.ground_truth, options);
    if (!ev) return Error{ev.error().code(), "estimate " + pair.name + ": " + ev.error().message()};
    joint.poses += ev->poses.size();
    joint.ground_truth_path_m += ev->ground_truth_path_m;
    joint.estimates.push_back(std::move(*ev));
  }
  if (mode == JointAlignment::kJoint) {
    alignJointly(joint);
  } else {
    alignEachAndPool(joint, pairs);
  }
  return joint;
}

}  // namespace cvislam::eval

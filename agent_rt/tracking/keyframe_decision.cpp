#include "agent_rt/tracking/keyframe_decision.hpp"

#include <algorithm>
#include <bitset>
#include <string>

namespace cvislam::agent {

namespace {
constexpr int kMaxCells = 4096;
}  // namespace

Status KeyframeDecisionOptions::validate() const {
  const auto bad = [](const std::string& what) {
    return Error{ErrorCode::kInvalidArgument, "keyframe decision options: " + what};
  };
  if (max_frames_between < 1) return bad("max_frames_between must be >= 1");
  if (!(max_interval_s >= 0.0))
    return bad("max_interval_s (tracking.max_keyframe_interval_s) must be >= 0 (0: no cap)");
  if (!(min_coverage_ratio >= 0.0 && min_coverage_ratio <= 1.0)) return bad("min_coverage_ratio must be in [0, 1]");
  if (min_tracked_points < 0) return bad("min_tracked_points must be >= 0");
  if (grid_columns < 1 || grid_rows < 1 || grid_columns * grid_rows > kMaxCells) {
    return bad("grid_columns x grid_rows must be 1 to 4096 cells");
  }
  return Status::Ok();
}

const char* toString(KeyframeReason reason) {
  switch (reason) {
    case KeyframeReason::kNone:
      return "none";
    case KeyframeReason::kFrameCount:
      return "frames since the last keyframe";
    case KeyframeReason::kInterval:
      return "time since the last keyframe";
    case KeyframeReason::kCoverage:
      return "tracked keypoint coverage dropped";
    case KeyframeReason::kFewTrackedPoints:
      return "few tracked map points";
  }
  return "unknown";
}

double gridCoverage(std::span<const Eigen::Vector2f> points_px, int width, int height, int columns, int rows) {
  if (width <= 0 || height <= 0 || columns < 1 || rows < 1 || columns * rows > kMaxCells) return 0.0;
  std::bitset<kMaxCells> covered;
  for (const Eigen::Vector2f& p : points_px) {
    if (!(p.x() >= 0.0F && p.y() >= 0.0F && p.x() < static_cast<float>(width) && p.y() < static_cast<float>(height))) {
      continue;
    }
    const int cx =
        std::min(columns - 1, static_cast<int>(p.x() * static_cast<float>(columns) / static_cast<float>(width)));
    const int cy = std::min(rows - 1, static_cast<int>(p.y() * static_cast<float>(rows) / static_cast<float>(height)));
    covered.set(static_cast<std::size_t>(cy) * static_cast<std::size_t>(columns) + static_cast<std::size_t>(cx));
  }
  return static_cast<double>(covered.count()) / static_cast<double>(columns * rows);
}

KeyframeReason decideKeyframe(const TrackingState& state, const KeyframeDecisionOptions& options) {
  if (state.tracked_points < options.min_tracked_points) return KeyframeReason::kFewTrackedPoints;
  if (state.keyframe_coverage > 0.0 && state.coverage < options.min_coverage_ratio * state.keyframe_coverage) {
    return KeyframeReason::kCoverage;
  }
  if (state.frames_since_keyframe > options.max_frames_between) return KeyframeReason::kFrameCount;
  if (options.max_interval_s > 0.0 && state.interval_s >= options.max_interval_s) return KeyframeReason::kInterval;
  return KeyframeReason::kNone;
}

}  // namespace cvislam::agent

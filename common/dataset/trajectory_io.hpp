// Trajectory files: TUM ("t[s] x y z qx qy qz qw", blank-separated) and EuRoC CSV ("t[ns],x,y,z,qw,qx,qy,qz"
// plus optional velocity and biases). Also reads a EuRoC sequence folder's ground truth.
//
// Poses made before the estimator's initialisation (StampedPose::before_initialisation) are written as comment
// lines, the row behind kBeforeInitialisationMark: tools that read TUM (evo, rpg_trajectory_evaluation) skip them,
// and a TUM file read here gives them back marked. A column would have broken those tools, which want 8 fields.
#pragma once

#include <filesystem>
#include <string_view>

#include "common/core/diagnostics.hpp"
#include "common/core/result.hpp"
#include "common/dataset/types.hpp"

namespace cvislam::dataset {

enum class TrajectoryFormat {
  kAuto,  // reading: a folder is EuRoC ground truth; a file is EuRoC CSV if its rows use commas, else TUM
  kTum,
  kEurocCsv,
};

Result<TrajectoryFormat> parseTrajectoryFormat(std::string_view name);  // "auto", "tum", "euroc"
std::string_view toString(TrajectoryFormat format);

inline constexpr std::string_view kBeforeInitialisationMark = "# before_init ";

struct TrajectoryReadOptions {
  TrajectoryFormat format = TrajectoryFormat::kAuto;
  bool strict = false;  // a bad row is an error instead of a skipped row with a warning
};

// Reads a trajectory file, or the ground truth of a EuRoC sequence folder (SEQ or SEQ/mav0).
// Fails when nothing usable is left.
Result<Trajectory> readTrajectory(const std::filesystem::path& path, const TrajectoryReadOptions& options,
                                  Diagnostics& diagnostics);

// Writes with full precision: timestamps exactly (nanoseconds), values as shortest round-trip decimals.
// kAuto picks EuRoC CSV for a ".csv" name and TUM otherwise.
Status writeTrajectory(const std::filesystem::path& path, const Trajectory& trajectory,
                       TrajectoryFormat format = TrajectoryFormat::kAuto);

}  // namespace cvislam::dataset

// Trajectory files: TUM ("t[s] x y z qx qy qz qw", blank-separated) and EuRoC CSV ("t[ns],x,y,z,qw,qx,qy,qz"
// plus optional velocity and biases). Also reads a EuRoC sequence folder's ground truth.
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

#include "common/dataset/trajectory_io.hpp"

#include <algorithm>
#include <fstream>
#include <string>

#include "common/core/text.hpp"
#include "common/dataset/csv.hpp"
#include "common/dataset/euroc.hpp"
#include "common/dataset/pose_fields.hpp"

namespace cvislam::dataset {
namespace {

std::string parseTumRow(const std::vector<std::string_view>& f, StampedPose& row) {
  const auto t_ns = text::parseSecondsAsNs(f[0]);
  if (!t_ns) return "field 1 ('" + std::string(f[0]) + "') is not a timestamp in seconds";
  row.t_ns = *t_ns;
  std::string problem;
  parsePositionQuaternionXyzw(f, 1, row.T_w_b, problem);
  return problem;
}

// The first data row decides: commas mean EuRoC CSV, blanks mean TUM.
Result<TrajectoryFormat> sniffFormat(const std::filesystem::path& path) {
  auto reader = text::LineReader::open(path);
  if (!reader) return reader.error();
  std::string_view line;
  while (reader->next(line)) {
    std::string_view content = text::trim(line);
    // A file of nothing but rows from before the initialisation is still a trajectory (of an estimator that never
    // initialised): it is read, and what is scored decides what to do with them.
    if (content.starts_with(kBeforeInitialisationMark)) content = content.substr(kBeforeInitialisationMark.size());
    if (content.empty() || content.front() == '#') continue;
    return content.find(',') != std::string_view::npos ? TrajectoryFormat::kEurocCsv : TrajectoryFormat::kTum;
  }
  return Error{ErrorCode::kDataError, path.string() + ": no trajectory rows (the file is empty or all comments)"};
}

}  // namespace

Result<TrajectoryFormat> parseTrajectoryFormat(std::string_view name) {
  if (name == "auto") return TrajectoryFormat::kAuto;
  if (name == "tum") return TrajectoryFormat::kTum;
  if (name == "euroc" || name == "csv") return TrajectoryFormat::kEurocCsv;
  return Error{ErrorCode::kInvalidArgument, "unknown trajectory format '" + std::string(name) + "' (auto, tum, euroc)"};
}

std::string_view toString(TrajectoryFormat format) {
  switch (format) {
    case TrajectoryFormat::kAuto:
      return "auto";
    case TrajectoryFormat::kTum:
      return "tum";
    case TrajectoryFormat::kEurocCsv:
      return "euroc";
  }
  return "unknown";
}

Result<Trajectory> readTrajectory(const std::filesystem::path& path, const TrajectoryReadOptions& options,
                                  Diagnostics& diagnostics) {
  std::filesystem::path file = path;
  TrajectoryFormat format = options.format;
  std::error_code ec;
  if (std::filesystem::is_directory(path, ec)) {
    auto mav0 = findMav0(path);
    if (!mav0) return mav0.error();
    file = *mav0 / "state_groundtruth_estimate0" / "data.csv";
    if (!std::filesystem::exists(file, ec)) {
      return Error{ErrorCode::kNotFound, path.string() + ": the sequence has no ground truth (" + file.string() + ")"};
    }
    format = TrajectoryFormat::kEurocCsv;
  }
  if (format == TrajectoryFormat::kAuto) {
    auto sniffed = sniffFormat(file);
    if (!sniffed) return sniffed.error();
    format = *sniffed;
  }
  Trajectory trajectory;
  if (format == TrajectoryFormat::kEurocCsv) {
    auto states = readGroundTruthCsv(file, options.strict, diagnostics, /*as_trajectory=*/true);
    if (!states) return states.error();
    trajectory.reserve(states->size());
    for (const GroundTruthState& s : *states) trajectory.push_back({s.t_ns, s.T_w_b});
  } else {
    const CsvFormat tum{false,
                        8,
                        8,
                        "timestamp [s], x, y, z, qx, qy, qz, qw",
                        /*keep_repeated_timestamps=*/true,
                        kBeforeInitialisationMark};
    auto rows = readTimestampedRows<StampedPose>(file, tum, &parseTumRow, options.strict, diagnostics);
    if (!rows) return rows.error();
    trajectory = std::move(*rows);
  }
  if (trajectory.empty()) {
    return Error{ErrorCode::kDataError,
                 file.string() + ": no usable " + std::string(toString(format)) + " trajectory rows"};
  }
  return trajectory;
}

Status writeTrajectory(const std::filesystem::path& path, const Trajectory& trajectory, TrajectoryFormat format) {
  if (format == TrajectoryFormat::kAuto) {
    format = path.extension() == ".csv" ? TrajectoryFormat::kEurocCsv : TrajectoryFormat::kTum;
  }
  std::error_code ec;
  if (path.has_parent_path()) std::filesystem::create_directories(path.parent_path(), ec);
  std::ofstream out(path, std::ios::binary);
  if (!out) return Error{ErrorCode::kIoError, path.string() + ": cannot open for writing"};
  const bool tum = format == TrajectoryFormat::kTum;
  out << (tum ? "# timestamp[s] tx ty tz qx qy qz qw\n"
              : "#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []\n");
  const bool any_marked = std::any_of(trajectory.begin(), trajectory.end(),
                                      [](const StampedPose& pose) { return pose.before_initialisation; });
  if (any_marked) {
    out << "# rows after '" << text::trim(kBeforeInitialisationMark)
        << "' were estimated before the initialisation (world frame not final; mono: up to scale): not scored\n";
  }
  const char sep = tum ? ' ' : ',';
  for (const StampedPose& pose : trajectory) {
    const Eigen::Vector3d& p = pose.T_w_b.translation();
    const Eigen::Quaterniond& q = pose.T_w_b.quaternion();
    std::string line = pose.before_initialisation ? std::string(kBeforeInitialisationMark) : std::string();
    line += tum ? text::formatNsAsSeconds(pose.t_ns) : std::to_string(pose.t_ns);
    const double values_tum[] = {p.x(), p.y(), p.z(), q.x(), q.y(), q.z(), q.w()};
    const double values_euroc[] = {p.x(), p.y(), p.z(), q.w(), q.x(), q.y(), q.z()};
    for (double v : tum ? values_tum : values_euroc) {
      line += sep;
      line += text::formatDouble(v);
    }
    line += '\n';
    out << line;
  }
  out.close();
  if (!out) return Error{ErrorCode::kIoError, path.string() + ": write failed (disk full?)"};
  return Status::Ok();
}

}  // namespace cvislam::dataset

// Reading timestamped rows from the CSV and whitespace-separated text files of EuRoC and TUM, with the
// project's policy for defects (see common/core/diagnostics.hpp): a bad row is reported with its file and
// line and skipped; in strict mode the first bad row is an error.
#pragma once

#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>
#include <vector>

#include "common/core/diagnostics.hpp"
#include "common/core/result.hpp"
#include "common/core/text.hpp"

namespace cvislam::dataset {

struct CsvFormat {
  bool comma = true;           // false: fields separated by blanks or tabs (TUM)
  std::size_t min_fields = 1;  // fewer fields is a truncated or malformed row
  std::size_t max_fields = 0;  // 0: no upper bound
  std::string description;     // e.g. "timestamp [ns], w_x, w_y, w_z, a_x, a_y, a_z"
  // Sensor streams need strictly increasing time. Trajectory files may repeat a timestamp (estimators do
  // emit two poses for one frame); such rows are kept and reported.
  bool keep_repeated_timestamps = false;
  // Comment lines that start with this hold a row all the same: read, with `row.before_initialisation` set
  // (empty: every comment line is skipped).
  std::string_view marked_prefix = {};
};

// Parses the fields of one row into `row`; returns an empty string on success, else the problem.
template <typename Row>
using CsvRowParser = std::string (*)(const std::vector<std::string_view>& fields, Row& row);

// Reads every row; `row.t_ns` must increase strictly from row to row. Comment lines start with '#'.
template <typename Row>
Result<std::vector<Row>> readTimestampedRows(const std::filesystem::path& path, const CsvFormat& format,
                                             CsvRowParser<Row> parse, bool strict, Diagnostics& diagnostics) {
  auto reader = text::LineReader::open(path);
  if (!reader) return reader.error();
  std::vector<Row> rows;
  std::vector<std::string_view> fields;
  std::string_view line;
  const std::string file = path.string();
  while (reader->next(line)) {
    std::string_view content = text::trim(line);
    const bool marked = !format.marked_prefix.empty() && content.starts_with(format.marked_prefix);
    if (marked) content = text::trim(content.substr(format.marked_prefix.size()));
    if (!marked && (content.empty() || content.front() == '#')) continue;
    const std::int64_t line_number = reader->lineNumber();
    std::string problem;
    text::splitFields(content, format.comma, fields);
    if (fields.size() < format.min_fields || (format.max_fields > 0 && fields.size() > format.max_fields)) {
      problem = "expected " + std::to_string(format.min_fields) +
                (format.max_fields > format.min_fields ? " to " + std::to_string(format.max_fields) : std::string()) +
                " fields (" + format.description + "), found " + std::to_string(fields.size()) +
                (fields.size() < format.min_fields ? " (truncated line?)" : "");
    }
    Row row{};
    if constexpr (requires { row.csv_line; }) row.csv_line = line_number;  // rows that remember their line
    if constexpr (requires { row.before_initialisation; }) row.before_initialisation = marked;
    if (problem.empty()) problem = parse(fields, row);
    if (problem.empty() && !rows.empty() && row.t_ns <= rows.back().t_ns) {
      if (row.t_ns == rows.back().t_ns && format.keep_repeated_timestamps) {
        diagnostics.warn(file, line_number,
                         "timestamp " + std::to_string(row.t_ns) + " ns repeats the previous row's; row kept");
      } else {
        problem = "timestamp " + std::to_string(row.t_ns) + " ns is not after the previous row's (" +
                  std::to_string(rows.back().t_ns) + " ns); timestamps must increase";
      }
    }
    if (!problem.empty()) {
      if (strict) return Error{ErrorCode::kDataError, file + ":" + std::to_string(line_number) + ": " + problem};
      diagnostics.warn(file, line_number, problem + "; row skipped");
      continue;
    }
    rows.push_back(std::move(row));
  }
  return rows;
}

// "field 3 ('abc') is not a number" style helper for parsers: parses fields[i] as a double.
bool parseFieldDouble(const std::vector<std::string_view>& fields, std::size_t i, double& out, std::string& problem);
bool parseFieldNs(const std::vector<std::string_view>& fields, std::size_t i, std::int64_t& out, std::string& problem);

}  // namespace cvislam::dataset

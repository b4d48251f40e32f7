// Diagnostics: a list of located findings about input data (file, line, message).
//
// Readers of real data meet real defects (an image listed but missing, a truncated last line). Policy:
// a defect that leaves the rest of the input usable is recorded here as a warning and reading carries on;
// a defect that makes the input unusable is returned as an Error. A caller that wants zero tolerance
// (CI, a calibration pipeline) turns warnings into errors with `strict` options on the reader.
#pragma once

#include <cstdint>
#include <ostream>
#include <string>
#include <vector>

namespace cvislam {

struct Finding {
  enum class Severity { kWarning, kError };
  Severity severity = Severity::kWarning;
  std::string file;       // path as given to the reader; empty if not tied to a file
  std::int64_t line = 0;  // 1-based line number, 0 if not tied to a line
  std::string message;

  // "path/data.csv:12: warning: non-numeric field 3 ('abc')"
  [[nodiscard]] std::string toString() const;
};

class Diagnostics {
 public:
  void warn(std::string file, std::int64_t line, std::string message);
  void error(std::string file, std::int64_t line, std::string message);

  [[nodiscard]] const std::vector<Finding>& findings() const noexcept { return findings_; }
  [[nodiscard]] std::size_t warningCount() const noexcept;
  [[nodiscard]] std::size_t errorCount() const noexcept;
  [[nodiscard]] bool empty() const noexcept { return findings_.empty(); }

  // Prints at most `max_lines` findings and a summary line for the rest.
  void print(std::ostream& os, std::size_t max_lines = 20) const;

  void append(const Diagnostics& other);

 private:
  std::vector<Finding> findings_;
};

}  // namespace cvislam

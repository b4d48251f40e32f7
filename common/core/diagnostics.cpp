#include "common/core/diagnostics.hpp"

#include <algorithm>

namespace cvislam {

std::string Finding::toString() const {
  std::string out;
  if (!file.empty()) {
    out += file;
    if (line > 0) {
      out += ':';
      out += std::to_string(line);
    }
    out += ": ";
  }
  out += severity == Severity::kError ? "error: " : "warning: ";
  out += message;
  return out;
}

void Diagnostics::warn(std::string file, std::int64_t line, std::string message) {
  findings_.push_back({Finding::Severity::kWarning, std::move(file), line, std::move(message)});
}

void Diagnostics::error(std::string file, std::int64_t line, std::string message) {
  findings_.push_back({Finding::Severity::kError, std::move(file), line, std::move(message)});
}

std::size_t Diagnostics::warningCount() const noexcept {
  return static_cast<std::size_t>(std::count_if(
      findings_.begin(), findings_.end(), [](const Finding& f) { return f.severity == Finding::Severity::kWarning; }));
}

std::size_t Diagnostics::errorCount() const noexcept {
  return findings_.size() - warningCount();
}

void Diagnostics::print(std::ostream& os, std::size_t max_lines) const {
  const std::size_t shown = std::min(max_lines, findings_.size());
  for (std::size_t i = 0; i < shown; ++i) {
    os << "  " << findings_[i].toString() << '\n';
  }
  if (findings_.size() > shown) {
    os << "  ... and " << (findings_.size() - shown) << " more finding(s)\n";
  }
}

void Diagnostics::append(const Diagnostics& other) {
  findings_.insert(findings_.end(), other.findings_.begin(), other.findings_.end());
}

}  // namespace cvislam

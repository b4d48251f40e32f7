// Exact, locale-independent parsing of the numbers found in dataset and trajectory files.
#pragma once

#include <cstdint>
#include <filesystem>
#include <fstream>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "common/core/result.hpp"

namespace cvislam::text {

// Whether `s` is a usable credential or metadata value: non-empty printable ASCII without spaces (gRPC aborts the
// process on a metadata value it cannot send, so clients check before sending).
bool isPrintableToken(std::string_view s) noexcept;

// A whole file's bytes; the error (kNotFound) names `what` and the file ("cannot read the tokens file /x").
Result<std::string> readTextFile(const std::filesystem::path& path, std::string_view what);
// The same for a PEM file (certificates, keys), which must hold a "-----BEGIN " block (kParseError otherwise).
Result<std::string> readPemFile(const std::filesystem::path& path, std::string_view what);

// A signed decimal integer, the whole field ("1403715273262142976"). Rejects signs-only, blanks, junk.
std::optional<std::int64_t> parseInt64(std::string_view field) noexcept;

// A finite double ("9.08", "-1.7e-05"). Rejects NaN, infinities, blanks and trailing junk.
std::optional<double> parseDouble(std::string_view field) noexcept;

// Seconds written in decimal or scientific notation ("1403715273.262142976", "1.403636579763555527e+09")
// to integer nanoseconds, rounded half away from zero. Exact: it never goes through a double, which at
// 1.4e9 s resolves only ~240 ns.
std::optional<std::int64_t> parseSecondsAsNs(std::string_view field) noexcept;

// Integer nanoseconds as seconds with nine decimals ("1403715273.262142976"); exact inverse of the above.
std::string formatNsAsSeconds(std::int64_t t_ns);

// The shortest decimal text that reads back as exactly `value` ("0.1", "1.6968e-05"). Deterministic.
std::string formatDouble(double value);

// Splits on commas (trimming blanks around fields) or, when `comma` is false, on runs of blanks/tabs.
void splitFields(std::string_view line, bool comma, std::vector<std::string_view>& fields);

std::string_view trim(std::string_view s) noexcept;

// Reads a text file line by line, with 1-based line numbers and without '\r' (files written on Windows).
class LineReader {
 public:
  static Result<LineReader> open(const std::filesystem::path& path);

  // Returns false at the end of the file. `line` stays valid until the next call.
  bool next(std::string_view& line);
  [[nodiscard]] std::int64_t lineNumber() const noexcept { return line_number_; }
  [[nodiscard]] const std::string& path() const noexcept { return path_; }

 private:
  LineReader(std::string path, std::ifstream stream) : path_(std::move(path)), stream_(std::move(stream)) {}

  std::string path_;
  std::ifstream stream_;
  std::string buffer_;
  std::int64_t line_number_ = 0;
};

}  // namespace cvislam::text

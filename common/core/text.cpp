#include "common/core/text.hpp"

#include <charconv>
#include <cmath>
#include <cstdio>
#include <iterator>
#include <limits>

namespace cvislam::text {

bool isPrintableToken(std::string_view s) noexcept {
  if (s.empty()) return false;
  for (const char c : s) {
    if (c <= ' ' || c > '~') return false;
  }
  return true;
}

Result<std::string> readTextFile(const std::filesystem::path& path, std::string_view what) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return Error{ErrorCode::kNotFound, "cannot read the " + std::string(what) + " " + path.string()};
  return std::string(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
}

Result<std::string> readPemFile(const std::filesystem::path& path, std::string_view what) {
  auto pem = readTextFile(path, what);
  if (pem && pem->find("-----BEGIN ") == std::string::npos) {
    return Error{ErrorCode::kParseError, "the " + std::string(what) + " " + path.string() + " is not a PEM file"};
  }
  return pem;
}

std::string_view trim(std::string_view s) noexcept {
  const auto is_blank = [](char c) { return c == ' ' || c == '\t' || c == '\r' || c == '\n'; };
  while (!s.empty() && is_blank(s.front())) s.remove_prefix(1);
  while (!s.empty() && is_blank(s.back())) s.remove_suffix(1);
  return s;
}

std::optional<std::int64_t> parseInt64(std::string_view field) noexcept {
  field = trim(field);
  if (!field.empty() && field.front() == '+') field.remove_prefix(1);
  if (field.empty()) return std::nullopt;
  std::int64_t value = 0;
  const auto [end, ec] = std::from_chars(field.data(), field.data() + field.size(), value);
  if (ec != std::errc() || end != field.data() + field.size()) return std::nullopt;
  return value;
}

std::optional<double> parseDouble(std::string_view field) noexcept {
  field = trim(field);
  if (!field.empty() && field.front() == '+') field.remove_prefix(1);
  if (field.empty()) return std::nullopt;
  double value = 0.0;
  const auto [end, ec] = std::from_chars(field.data(), field.data() + field.size(), value);
  if (ec != std::errc() || end != field.data() + field.size() || !std::isfinite(value)) return std::nullopt;
  return value;
}

std::optional<std::int64_t> parseSecondsAsNs(std::string_view field) noexcept {
  field = trim(field);
  if (field.empty()) return std::nullopt;
  bool negative = false;
  if (field.front() == '-' || field.front() == '+') {
    negative = field.front() == '-';
    field.remove_prefix(1);
  }
  // value = mantissa * 10^exp10, with the mantissa an integer made of the significant digits.
  using Wide = unsigned __int128;
  constexpr int kMaxDigits = 36;  // 10^36 < 2^128
  Wide mantissa = 0;
  int digits = 0;
  int exp10 = 0;
  bool seen_digit = false;
  bool seen_point = false;
  bool round_up_dropped = false;  // first dropped digit >= 5 (digits beyond kMaxDigits)
  bool dropped_any = false;
  std::size_t i = 0;
  for (; i < field.size(); ++i) {
    const char c = field[i];
    if (c == '.') {
      if (seen_point) return std::nullopt;
      seen_point = true;
      continue;
    }
    if (c < '0' || c > '9') break;
    seen_digit = true;
    if (digits < kMaxDigits) {
      if (mantissa != 0 || c != '0') {
        mantissa = mantissa * 10 + static_cast<unsigned>(c - '0');
        ++digits;
      }
      if (seen_point) --exp10;
    } else {
      if (!dropped_any) round_up_dropped = c >= '5';
      dropped_any = true;
      if (!seen_point) ++exp10;
    }
  }
  if (!seen_digit) return std::nullopt;
  if (round_up_dropped) mantissa += 1;
  if (i < field.size()) {
    if (field[i] != 'e' && field[i] != 'E') return std::nullopt;
    const auto exponent = parseInt64(field.substr(i + 1));
    if (!exponent || *exponent > 100 || *exponent < -100) return std::nullopt;
    exp10 += static_cast<int>(*exponent);
  }
  int shift = exp10 + 9;  // to nanoseconds
  constexpr Wide kLimit = static_cast<Wide>(std::numeric_limits<std::int64_t>::max());
  if (shift >= 0) {
    for (; shift > 0; --shift) {
      if (mantissa > kLimit) return std::nullopt;
      mantissa *= 10;
    }
  } else {
    for (; shift < -1 && mantissa != 0; ++shift) mantissa /= 10;
    if (shift == -1) mantissa = (mantissa + 5) / 10;  // round half away from zero on the last digit
  }
  if (mantissa > kLimit) return std::nullopt;
  const auto magnitude = static_cast<std::int64_t>(mantissa);
  return negative ? -magnitude : magnitude;
}

std::string formatNsAsSeconds(std::int64_t t_ns) {
  const bool negative = t_ns < 0;
  const auto magnitude = negative ? -static_cast<unsigned long long>(t_ns) : static_cast<unsigned long long>(t_ns);
  char buffer[48];
  std::snprintf(buffer, sizeof(buffer), "%s%llu.%09llu", negative ? "-" : "", magnitude / 1000000000ULL,
                magnitude % 1000000000ULL);
  return buffer;
}

std::string formatDouble(double value) {
  char buffer[32];
  const auto [end, ec] = std::to_chars(buffer, buffer + sizeof(buffer), value);
  return ec == std::errc() ? std::string(buffer, end) : std::string("nan");
}

void splitFields(std::string_view line, bool comma, std::vector<std::string_view>& fields) {
  fields.clear();
  if (comma) {
    std::size_t start = 0;
    while (true) {
      const std::size_t end = line.find(',', start);
      fields.push_back(trim(line.substr(start, end == std::string_view::npos ? std::string_view::npos : end - start)));
      if (end == std::string_view::npos) break;
      start = end + 1;
    }
    return;
  }
  std::size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && (line[i] == ' ' || line[i] == '\t' || line[i] == '\r')) ++i;
    const std::size_t start = i;
    while (i < line.size() && line[i] != ' ' && line[i] != '\t' && line[i] != '\r') ++i;
    if (i > start) fields.push_back(line.substr(start, i - start));
  }
}

Result<LineReader> LineReader::open(const std::filesystem::path& path) {
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) {
    return Error{ErrorCode::kNotFound, path.string() + ": file does not exist"};
  }
  if (std::filesystem::is_directory(path, ec)) {
    return Error{ErrorCode::kInvalidArgument, path.string() + ": is a folder, expected a file"};
  }
  std::ifstream stream(path, std::ios::binary);
  if (!stream) {
    return Error{ErrorCode::kIoError, path.string() + ": cannot open for reading"};
  }
  return LineReader(path.string(), std::move(stream));
}

bool LineReader::next(std::string_view& line) {
  if (!std::getline(stream_, buffer_)) return false;
  ++line_number_;
  if (!buffer_.empty() && buffer_.back() == '\r') buffer_.pop_back();
  line = buffer_;
  return true;
}

}  // namespace cvislam::text

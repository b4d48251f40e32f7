#include "common/ros2/cdr.hpp"

#include <bit>
#include <cstdio>

namespace cvislam::ros2 {

// memcpy of host-order values is the whole encoding: little-endian hosts only (x86-64 and arm64 both are).
static_assert(std::endian::native == std::endian::little, "the CDR codecs assume a little-endian host");

Result<CdrReader> CdrReader::open(std::span<const std::uint8_t> message, std::string_view type) {
  const std::string what = "cdr: " + std::string(type) + ": ";
  if (message.size() < kEncapsulationBytes) {
    return Error(ErrorCode::kParseError,
                 what + std::to_string(message.size()) + " bytes, shorter than the encapsulation header");
  }
  // The representation identifier, big endian: 0x0001 CDR_LE. The option bytes that follow are not interpreted.
  const unsigned kind = (unsigned{message[0]} << 8U) | message[1];
  switch (kind) {
    case 0x0001:
      return CdrReader(message, type);
    case 0x0000:
      return Error(ErrorCode::kParseError, what + "big-endian CDR (encapsulation 00 00) is not supported");
    case 0x0002:
    case 0x0003:
      return Error(ErrorCode::kParseError, what + "parameter-list CDR (PL_CDR) is not supported");
    default: {
      char hex[8];
      std::snprintf(hex, sizeof hex, "%02x %02x", message[0], message[1]);
      return Error(ErrorCode::kParseError,
                   what + "encapsulation " + hex + " is not supported (only 00 01, CDR little endian)");
    }
  }
}

void CdrReader::align(std::size_t n) {
  if (failed_) return;
  const std::size_t past = (position_ - kEncapsulationBytes) % n;
  if (past != 0) position_ += n - past;
}

std::span<const std::uint8_t> CdrReader::take(std::uint64_t n, const char* field) {
  if (failed_) return {};
  if (position_ > message_.size() || n > message_.size() - position_) {
    fail(field, "needs " + std::to_string(n) + " bytes at byte " + std::to_string(position_) + " but the message has " +
                    std::to_string(message_.size()));
    return {};
  }
  const auto out = message_.subspan(position_, static_cast<std::size_t>(n));
  position_ += static_cast<std::size_t>(n);
  return out;
}

void CdrReader::fail(const char* field, std::string what) {
  if (failed_) return;
  failed_ = true;
  failure_ = "cdr: " + std::string(type_) + ": field '" + field + "' " + std::move(what);
}

std::string_view CdrReader::string(const char* field) {
  const std::size_t at = position_;
  const auto length = primitive<std::uint32_t>(field);
  const auto bytes = take(length, field);
  if (failed_ || length == 0) return {};  // some writers send an empty string as length 0
  if (bytes.back() != 0) {
    fail(field, "(a string at byte " + std::to_string(at) + ") does not end with a NUL");
    return {};
  }
  return {reinterpret_cast<const char*>(bytes.data()), bytes.size() - 1};
}

std::span<const std::uint8_t> CdrReader::byteSequence(const char* field) {
  const auto count = primitive<std::uint32_t>(field);
  return take(count, field);
}

void CdrReader::doubles(std::span<double> out, const char* field) {
  align(sizeof(double));
  const auto bytes = take(out.size() * sizeof(double), field);
  if (!bytes.empty()) std::memcpy(out.data(), bytes.data(), bytes.size());
}

Status CdrReader::finish() const {
  if (failed_) return Error(ErrorCode::kParseError, failure_);
  const std::size_t rest = position_ < message_.size() ? message_.size() - position_ : 0;
  if (rest > 3) {
    return Error(ErrorCode::kParseError, "cdr: " + std::string(type_) + ": " + std::to_string(rest) +
                                             " bytes follow the last field (at byte " + std::to_string(position_) +
                                             ")");
  }
  return {};
}

CdrWriter::CdrWriter(std::vector<std::uint8_t>& out) : out_(out) {
  out_.assign({0x00, 0x01, 0x00, 0x00});
}

void CdrWriter::align(std::size_t n) {
  const std::size_t past = (out_.size() - kEncapsulationBytes) % n;
  if (past != 0) out_.resize(out_.size() + n - past, 0);
}

void CdrWriter::string(std::string_view s) {
  primitive(static_cast<std::uint32_t>(s.size() + 1));
  out_.insert(out_.end(), s.begin(), s.end());
  out_.push_back(0);
}

void CdrWriter::byteSequence(std::span<const std::uint8_t> bytes) {
  primitive(static_cast<std::uint32_t>(bytes.size()));
  out_.insert(out_.end(), bytes.begin(), bytes.end());
}

void CdrWriter::doubles(std::span<const double> values) {
  align(sizeof(double));
  const std::size_t at = out_.size();
  out_.resize(at + values.size_bytes());
  std::memcpy(out_.data() + at, values.data(), values.size_bytes());
}

}  // namespace cvislam::ros2

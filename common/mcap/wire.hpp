// MCAP's field encoding, both ways: little-endian integers, String = u32 byte length + bytes, Bytes with a u32 or
// u64 length, Map and Array = u32 byte length + entries. Used by the reader and the writer only.
#pragma once

#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "common/mcap/records.hpp"

namespace cvislam::mcap::wire {

// Reads fields from a record's content. A read past the end fails the cursor: it remembers the first field that did
// not fit and every later read returns zero or empty, so a parser reads all its fields and checks ok() once.
class Cursor {
 public:
  explicit Cursor(std::span<const std::uint8_t> bytes) : bytes_(bytes) {}

  std::uint8_t u8(const char* field) { return static_cast<std::uint8_t>(little(1, field)); }
  std::uint16_t u16(const char* field) { return static_cast<std::uint16_t>(little(2, field)); }
  std::uint32_t u32(const char* field) { return static_cast<std::uint32_t>(little(4, field)); }
  std::uint64_t u64(const char* field) { return little(8, field); }

  std::span<const std::uint8_t> take(std::uint64_t n, const char* field) {
    if (!ok() || n > remaining()) {
      fail(field);
      return {};
    }
    const auto out = bytes_.subspan(position_, static_cast<std::size_t>(n));
    position_ += static_cast<std::size_t>(n);
    return out;
  }
  std::string_view string(const char* field) {
    const auto bytes = take(u32(field), field);
    return {reinterpret_cast<const char*>(bytes.data()), bytes.size()};
  }
  std::span<const std::uint8_t> bytes32(const char* field) { return take(u32(field), field); }
  std::span<const std::uint8_t> bytes64(const char* field) { return take(u64(field), field); }
  // Everything not read yet (a Message's data).
  std::span<const std::uint8_t> rest() { return take(remaining(), "rest"); }

  // Fails the cursor from outside (a nested structure that did not parse).
  void fail(const char* field) {
    if (failed_field_ == nullptr) failed_field_ = field;
    position_ = bytes_.size();
  }

  [[nodiscard]] bool ok() const { return failed_field_ == nullptr; }
  [[nodiscard]] const char* failedField() const { return failed_field_; }
  [[nodiscard]] std::size_t position() const { return position_; }
  [[nodiscard]] std::size_t remaining() const { return bytes_.size() - position_; }

 private:
  std::uint64_t little(std::size_t n, const char* field) {
    if (!ok() || n > remaining()) {
      fail(field);
      return 0;
    }
    std::uint64_t v = 0;
    for (std::size_t i = 0; i < n; ++i) v |= std::uint64_t{bytes_[position_ + i]} << (8 * i);
    position_ += n;
    return v;
  }

  std::span<const std::uint8_t> bytes_;
  std::size_t position_ = 0;
  const char* failed_field_ = nullptr;
};

// Appends fields to a byte buffer.
class Encoder {
 public:
  explicit Encoder(std::vector<std::uint8_t>& out) : out_(out) {}

  void u8(std::uint8_t v) { out_.push_back(v); }
  void u16(std::uint16_t v) { little(v, 2); }
  void u32(std::uint32_t v) { little(v, 4); }
  void u64(std::uint64_t v) { little(v, 8); }
  void raw(std::span<const std::uint8_t> bytes) { out_.insert(out_.end(), bytes.begin(), bytes.end()); }
  void raw(std::string_view bytes) {
    raw(std::span<const std::uint8_t>(reinterpret_cast<const std::uint8_t*>(bytes.data()), bytes.size()));
  }
  // Callers keep strings, maps and Bytes32 below 4 GiB (the writer checks what users pass).
  void string(std::string_view s) {
    u32(static_cast<std::uint32_t>(s.size()));
    raw(s);
  }
  void bytes64(std::span<const std::uint8_t> bytes) {
    u64(bytes.size());
    raw(bytes);
  }
  void stringMap(const std::map<std::string, std::string>& map) {
    const std::size_t length_at = beginLength32();
    for (const auto& [key, value] : map) {
      string(key);
      string(value);
    }
    endLength32(length_at);
  }
  void u16Map(const std::map<std::uint16_t, std::uint64_t>& map) {
    const std::size_t length_at = beginLength32();
    for (const auto& [key, value] : map) {
      u16(key);
      u64(value);
    }
    endLength32(length_at);
  }

  // A record: the opcode, a length patched by endRecord(), then the content appended in between.
  std::size_t beginRecord(Opcode op) {
    u8(static_cast<std::uint8_t>(op));
    const std::size_t at = out_.size();
    u64(0);
    return at;
  }
  // `bytes_after`: content the caller writes separately after this buffer (a chunk's compressed records).
  void endRecord(std::size_t length_at, std::uint64_t bytes_after = 0) {
    patch(length_at, out_.size() - length_at - 8 + bytes_after, 8);
  }
  std::size_t beginLength32() {
    const std::size_t at = out_.size();
    u32(0);
    return at;
  }
  void endLength32(std::size_t length_at) { patch(length_at, out_.size() - length_at - 4, 4); }

 private:
  void little(std::uint64_t v, std::size_t n) {
    for (std::size_t i = 0; i < n; ++i) out_.push_back(static_cast<std::uint8_t>(v >> (8 * i)));
  }
  void patch(std::size_t at, std::uint64_t v, std::size_t n) {
    for (std::size_t i = 0; i < n; ++i) out_[at + i] = static_cast<std::uint8_t>(v >> (8 * i));
  }

  std::vector<std::uint8_t>& out_;
};

}  // namespace cvislam::mcap::wire

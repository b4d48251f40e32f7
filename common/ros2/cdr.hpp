// ROS 2's message serialization: OMG CDR (XCDR version 1, plain, little endian) as rmw writes it and rosbag2
// stores it. A message is a 4-byte encapsulation header (00 01 = CDR little endian, then two option bytes), then the
// fields in .msg order with nested messages inlined. Every primitive is aligned to its own size (1, 2, 4, 8),
// counted from the byte after the encapsulation header. string = u32 length including the terminating NUL, the
// bytes and the NUL; T[] = u32 element count, then the elements; T[N] = N elements, no count.
#pragma once

#include <cstdint>
#include <cstring>
#include <span>
#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

#include "common/core/result.hpp"

namespace cvislam::ros2 {

inline constexpr std::size_t kEncapsulationBytes = 4;

// Reads fields with bounds checks. A read that does not fit fails the reader: it remembers the field and its
// position, and every later read returns zero or empty, so a decoder reads everything and calls finish() once.
class CdrReader {
 public:
  // Checks the encapsulation header. `type` names the message in errors (e.g. "sensor_msgs/msg/Image"). Big-endian
  // CDR and the parameter-list / XCDR2 kinds are refused with an error that names them.
  static Result<CdrReader> open(std::span<const std::uint8_t> message, std::string_view type);

  template <typename T>
  T primitive(const char* field) {
    static_assert(std::is_arithmetic_v<T>);
    align(sizeof(T));
    const auto bytes = take(sizeof(T), field);
    T v{};
    if (!bytes.empty()) std::memcpy(&v, bytes.data(), sizeof(T));
    return v;
  }
  // A string: a view into the message, without its NUL.
  std::string_view string(const char* field);
  // uint8[]: a view into the message.
  std::span<const std::uint8_t> byteSequence(const char* field);
  // float64[N] into `out` (N = out.size()).
  void doubles(std::span<double> out, const char* field);

  // OK when every field fitted and nothing but up to 3 bytes of padding follows (rmw may pad a message to a
  // multiple of 4); the error names the type, the field and the byte.
  [[nodiscard]] Status finish() const;

 private:
  CdrReader(std::span<const std::uint8_t> message, std::string_view type) : message_(message), type_(type) {}
  void align(std::size_t n);
  std::span<const std::uint8_t> take(std::uint64_t n, const char* field);
  void fail(const char* field, std::string what);

  std::span<const std::uint8_t> message_;
  std::string_view type_;
  std::size_t position_ = kEncapsulationBytes;
  bool failed_ = false;
  std::string failure_;
};

// Writes a message into a buffer it replaces, encapsulation header first.
class CdrWriter {
 public:
  explicit CdrWriter(std::vector<std::uint8_t>& out);

  template <typename T>
  void primitive(T v) {
    static_assert(std::is_arithmetic_v<T>);
    align(sizeof(T));
    const std::size_t at = out_.size();
    out_.resize(at + sizeof(T));
    std::memcpy(out_.data() + at, &v, sizeof(T));
  }
  // Callers keep strings and sequences below 4 GiB (the message encoders check).
  void string(std::string_view s);
  void byteSequence(std::span<const std::uint8_t> bytes);
  void doubles(std::span<const double> values);

 private:
  void align(std::size_t n);

  std::vector<std::uint8_t>& out_;
};

}  // namespace cvislam::ros2

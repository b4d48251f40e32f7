// The contract of a fuzz target (test/fuzz): libFuzzer's entry point, plus the seed inputs the target makes for
// itself (valid messages built with the test helpers, so no generated corpus is committed). A target is linked
// either with libFuzzer (clang, -fsanitize=fuzzer: test/fuzz/run_fuzz.sh) or with fuzz_driver.cpp, a small
// seeded mutator that CTest runs for a fixed number of inputs in every build.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include <google/protobuf/stubs/logging.h>

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size);

namespace cvislam::fuzz {

// Valid inputs that reach deep into the target: the starting corpus.
std::vector<std::string> seeds();

// Splits an input into framed parts: each is a 2-byte little-endian length and that many bytes (the last one
// takes what is left when its length runs past the end). Lets one input carry a sequence of messages.
inline std::vector<std::string> frames(const std::uint8_t* data, std::size_t size, std::size_t max_frames) {
  std::vector<std::string> out;
  std::size_t at = 0;
  while (at + 2 <= size && out.size() < max_frames) {
    const std::size_t length = static_cast<std::size_t>(data[at]) | (static_cast<std::size_t>(data[at + 1]) << 8U);
    at += 2;
    const std::size_t n = length < size - at ? length : size - at;
    out.emplace_back(reinterpret_cast<const char*>(data + at), n);
    at += n;
  }
  return out;
}

// Protobuf logs every string field that is not UTF-8; hostile input is expected here, so keep the output readable.
[[maybe_unused]] inline const bool kQuietProtobuf = [] {
  google::protobuf::SetLogHandler(nullptr);
  return true;
}();

inline std::string frame(const std::string& part) {
  std::string out;
  out.push_back(static_cast<char>(part.size() & 0xFFU));
  out.push_back(static_cast<char>((part.size() >> 8U) & 0xFFU));
  return out + part;
}

}  // namespace cvislam::fuzz

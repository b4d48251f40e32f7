// Where an MCAP reader's bytes come from: a file read with pread through a read-ahead window, or a buffer in memory.
// Internal to the reader.
#pragma once

#include <cstdint>
#include <filesystem>
#include <memory>
#include <span>
#include <vector>

#include "common/core/result.hpp"

namespace cvislam::mcap {

class Source {
 public:
  virtual ~Source() = default;
  [[nodiscard]] virtual std::uint64_t size() const = 0;
  // Fills `out` from `offset`; the caller has checked that the range lies inside size().
  virtual Status read(std::uint64_t offset, std::span<std::uint8_t> out) = 0;
};

std::unique_ptr<Source> memorySource(std::vector<std::uint8_t> bytes);
// Errors: kNotFound when the file does not exist, kIoError when it cannot be opened or is not a regular file.
Result<std::unique_ptr<Source>> openFileSource(const std::filesystem::path& path);

}  // namespace cvislam::mcap

// A decoder for the one PNG layout a camera dataset holds in bulk: 8-bit grey, not interlaced (EuRoC's and the
// simulator's images). It reads the file, inflates the image data with libdeflate and undoes the row filters
// straight into the caller's buffer, reusing its own buffers from file to file: once they have grown to the
// largest file seen it allocates nothing. Anything else (colour, 16-bit, interlaced, JPEG, PGM) it hands back
// undecoded: the loader (image.hpp) then names the format and how to convert it.
//
// The frame loader is a quarter to a third of the agent's CPU on one core (docs/agent.md, "On a small board"); most of
// it was libpng's inflate and OpenCV's buffers around it.
#pragma once

#include <cstdint>
#include <filesystem>
#include <span>
#include <string>
#include <vector>

#include "common/core/result.hpp"

struct libdeflate_decompressor;

namespace cvislam::dataset {

class GrayPngDecoder {
 public:
  GrayPngDecoder();
  ~GrayPngDecoder();
  GrayPngDecoder(const GrayPngDecoder&) = delete;
  GrayPngDecoder& operator=(const GrayPngDecoder&) = delete;

  // true: decoded into `pixels` (exactly width*height bytes, stride == width). false: not an 8-bit grey,
  // non-interlaced PNG; nothing was written and the caller decodes it another way. An error names the file and
  // what is wrong with it (missing, truncated, a bad checksum, corrupt image data, a size other than
  // width x height).
  Result<bool> decodeInto(const std::filesystem::path& path, int width, int height, std::span<std::uint8_t> pixels);

  // The same from bytes already in memory (the file's whole contents); `name` is used in errors.
  Result<bool> decodeInto(std::span<const std::uint8_t> file, const std::string& name, int width, int height,
                          std::span<std::uint8_t> pixels);

 private:
  libdeflate_decompressor* inflater_ = nullptr;
  std::vector<std::uint8_t> file_;      // the file's bytes
  std::vector<std::uint8_t> deflated_;  // the IDAT chunks' contents, joined
  std::vector<std::uint8_t> filtered_;  // one filter byte and width pixels per row
  std::vector<std::uint8_t> zero_row_;  // the row of zeros PNG puts above the first row
};

}  // namespace cvislam::dataset

// CRC-32 and chunk (de)compression for the reader and the writer. zstd, LZ4 and zlib stay behind this header:
// their own headers are included in codec.cpp only.
#pragma once

#include <cstdint>
#include <memory>
#include <span>
#include <string_view>
#include <vector>

#include "common/core/result.hpp"
#include "common/mcap/records.hpp"

namespace cvislam::mcap::codec {

// The CRC-32 MCAP uses (zlib's: IEEE polynomial, reflected, initial and final xor 0xFFFFFFFF). Start with 0 and feed
// the bytes in any number of pieces.
std::uint32_t crc32(std::uint32_t crc, std::span<const std::uint8_t> bytes);

// Decompresses chunk records. Holds the decoder contexts, so that a reader allocates them once.
class Decompressor {
 public:
  Decompressor();
  ~Decompressor();
  Decompressor(Decompressor&&) noexcept;
  Decompressor& operator=(Decompressor&&) noexcept;

  // Fills `out` exactly from `in`, compressed with `compression` ("zstd" or "lz4"; "" is a copy). An error says
  // what went wrong without context: the caller names the chunk. Never writes past `out` and never allocates more
  // than the decoders' own bounded state, whatever `in` holds.
  Status decompress(std::string_view compression, std::span<const std::uint8_t> in, std::span<std::uint8_t> out);

 private:
  struct Contexts;
  std::unique_ptr<Contexts> contexts_;
};

// Compresses chunk records for the writer.
class Compressor {
 public:
  Compressor();
  ~Compressor();
  Compressor(Compressor&&) noexcept;
  Compressor& operator=(Compressor&&) noexcept;

  // Replaces `out` with `in` compressed; `zstd_level` is used for kZstd only.
  Status compress(Compression compression, int zstd_level, std::span<const std::uint8_t> in,
                  std::vector<std::uint8_t>& out);

 private:
  struct Contexts;
  std::unique_ptr<Contexts> contexts_;
};

}  // namespace cvislam::mcap::codec

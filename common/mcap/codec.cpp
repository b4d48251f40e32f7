#include "common/mcap/codec.hpp"

#include <lz4frame.h>
#include <zlib.h>
#include <zstd.h>

#include <algorithm>
#include <string>

namespace cvislam::mcap::codec {

std::uint32_t crc32(std::uint32_t crc, std::span<const std::uint8_t> bytes) {
  // zlib takes a uInt length: feed pieces of at most 1 GiB.
  constexpr std::size_t kPiece = std::size_t{1} << 30;
  uLong value = crc;
  while (!bytes.empty()) {
    const std::size_t n = std::min(bytes.size(), kPiece);
    value = ::crc32(value, bytes.data(), static_cast<uInt>(n));
    bytes = bytes.subspan(n);
  }
  return static_cast<std::uint32_t>(value);
}

struct Decompressor::Contexts {
  ZSTD_DCtx* zstd = nullptr;
  LZ4F_dctx* lz4 = nullptr;

  ~Contexts() {
    ZSTD_freeDCtx(zstd);
    if (lz4 != nullptr) LZ4F_freeDecompressionContext(lz4);
  }
};

Decompressor::Decompressor() : contexts_(std::make_unique<Contexts>()) {}
Decompressor::~Decompressor() = default;
Decompressor::Decompressor(Decompressor&&) noexcept = default;
Decompressor& Decompressor::operator=(Decompressor&&) noexcept = default;

namespace {

Error corrupt(std::string what) {
  return Error(ErrorCode::kDataError, std::move(what));
}

Status zstdDecompress(ZSTD_DCtx* context, std::span<const std::uint8_t> in, std::span<std::uint8_t> out) {
  // The output is a flat buffer of the declared size: zstd decodes straight into it, needs no window buffer of its
  // own, and stops with dstSize_tooSmall if the frames hold more.
  const std::size_t n = ZSTD_decompressDCtx(context, out.data(), out.size(), in.data(), in.size());
  if (ZSTD_isError(n)) return corrupt(std::string("zstd: ") + ZSTD_getErrorName(n));
  if (n != out.size()) {
    return corrupt("zstd: decompressed to " + std::to_string(n) + " bytes, uncompressed_size says " +
                   std::to_string(out.size()));
  }
  return {};
}

Status lz4Decompress(LZ4F_dctx* context, std::span<const std::uint8_t> in, std::span<std::uint8_t> out) {
  std::size_t in_at = 0;
  std::size_t out_at = 0;
  std::size_t hint = 1;  // LZ4F_decompress returns 0 once a frame is complete
  // Each call consumes input or produces output, or the data is bad: the loop ends within |in| + |out| calls.
  while (in_at < in.size()) {
    std::size_t out_n = out.size() - out_at;
    std::size_t in_n = in.size() - in_at;
    hint = LZ4F_decompress(context, out.data() + out_at, &out_n, in.data() + in_at, &in_n, nullptr);
    if (LZ4F_isError(hint)) {
      LZ4F_resetDecompressionContext(context);
      return corrupt(std::string("lz4: ") + LZ4F_getErrorName(hint));
    }
    if (out_n == 0 && in_n == 0) {
      LZ4F_resetDecompressionContext(context);
      return corrupt("lz4: the frames hold more than uncompressed_size (" + std::to_string(out.size()) + " bytes)");
    }
    out_at += out_n;
    in_at += in_n;
  }
  if (hint != 0) {
    LZ4F_resetDecompressionContext(context);
    return corrupt("lz4: the frame is cut off");
  }
  if (out_at != out.size()) {
    return corrupt("lz4: decompressed to " + std::to_string(out_at) + " bytes, uncompressed_size says " +
                   std::to_string(out.size()));
  }
  return {};
}

}  // namespace

Status Decompressor::decompress(std::string_view compression, std::span<const std::uint8_t> in,
                                std::span<std::uint8_t> out) {
  if (compression.empty()) {
    if (in.size() != out.size()) {
      return corrupt("uncompressed records of " + std::to_string(in.size()) + " bytes, uncompressed_size says " +
                     std::to_string(out.size()));
    }
    std::copy(in.begin(), in.end(), out.begin());
    return {};
  }
  if (in.empty()) {
    if (out.empty()) return {};
    return corrupt(std::string(compression) + ": no compressed data for " + std::to_string(out.size()) + " bytes");
  }
  if (compression == "zstd") {
    if (contexts_->zstd == nullptr) contexts_->zstd = ZSTD_createDCtx();
    if (contexts_->zstd == nullptr) return Error(ErrorCode::kResourceExhausted, "zstd: cannot create a context");
    return zstdDecompress(contexts_->zstd, in, out);
  }
  if (compression == "lz4") {
    if (contexts_->lz4 == nullptr && LZ4F_isError(LZ4F_createDecompressionContext(&contexts_->lz4, LZ4F_VERSION))) {
      contexts_->lz4 = nullptr;
      return Error(ErrorCode::kResourceExhausted, "lz4: cannot create a context");
    }
    return lz4Decompress(contexts_->lz4, in, out);
  }
  return Error(ErrorCode::kDataError,
               "compression '" + std::string(compression) + "' is not supported (only '', 'zstd' and 'lz4')");
}

struct Compressor::Contexts {
  ZSTD_CCtx* zstd = nullptr;

  ~Contexts() { ZSTD_freeCCtx(zstd); }
};

Compressor::Compressor() : contexts_(std::make_unique<Contexts>()) {}
Compressor::~Compressor() = default;
Compressor::Compressor(Compressor&&) noexcept = default;
Compressor& Compressor::operator=(Compressor&&) noexcept = default;

Status Compressor::compress(Compression compression, int zstd_level, std::span<const std::uint8_t> in,
                            std::vector<std::uint8_t>& out) {
  switch (compression) {
    case Compression::kNone:
      out.assign(in.begin(), in.end());
      return {};
    case Compression::kZstd: {
      if (contexts_->zstd == nullptr) contexts_->zstd = ZSTD_createCCtx();
      if (contexts_->zstd == nullptr) return Error(ErrorCode::kResourceExhausted, "zstd: cannot create a context");
      out.resize(ZSTD_compressBound(in.size()));
      const std::size_t n =
          ZSTD_compressCCtx(contexts_->zstd, out.data(), out.size(), in.data(), in.size(), zstd_level);
      if (ZSTD_isError(n)) return Error(ErrorCode::kInternal, std::string("zstd: ") + ZSTD_getErrorName(n));
      out.resize(n);
      return {};
    }
    case Compression::kLz4: {
      LZ4F_preferences_t preferences{};
      // The frame header then carries the size, which lets a reader check it before decoding.
      preferences.frameInfo.contentSize = in.size();
      out.resize(LZ4F_compressFrameBound(in.size(), &preferences));
      const std::size_t n = LZ4F_compressFrame(out.data(), out.size(), in.data(), in.size(), &preferences);
      if (LZ4F_isError(n)) return Error(ErrorCode::kInternal, std::string("lz4: ") + LZ4F_getErrorName(n));
      out.resize(n);
      return {};
    }
  }
  return Error(ErrorCode::kInvalidArgument, "unknown compression");
}

}  // namespace cvislam::mcap::codec

#include "common/dataset/png_gray.hpp"

#include <fcntl.h>
#include <libdeflate.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <new>
#include <string>
#include <utility>

namespace cvislam::dataset {
namespace {

constexpr std::uint8_t kSignature[8] = {137, 'P', 'N', 'G', '\r', '\n', 26, '\n'};

std::uint32_t bigEndian32(const std::uint8_t* p) {
  return (std::uint32_t{p[0]} << 24) | (std::uint32_t{p[1]} << 16) | (std::uint32_t{p[2]} << 8) | std::uint32_t{p[3]};
}

bool isType(const std::uint8_t* p, const char* type) {
  return std::memcmp(p, type, 4) == 0;
}

// Grows `v` to at least n bytes; it never shrinks, so a decoder settles at the largest file it has seen.
void reserveBytes(std::vector<std::uint8_t>& v, std::size_t n) {
  if (v.size() < n) v.resize(n);
}

// Undoing PNG's row filters: out = filtered + predictor(left a, above b, above-left c), one byte per pixel, with
// the row above the first row and the pixel left of each row's first taken as 0. Filter types: 0 none, 1 left,
// 2 above, 3 average of left and above, 4 Paeth.
//
// Every pixel's predictor needs the pixel just decoded to its left, so a row is one serial chain. Pixel x of a
// row needs only pixels x-1 and x of the row above, so rows are undone in pairs, one pixel of each per step:
// two independent chains the CPU runs side by side. Each pair of filter types has its own loop (25 of them),
// so no step branches on a type, and Paeth's choice is made with masks: on camera images its branches are
// unpredictable. On a 2-core x86 VM a 752x480 frame's rows take 0.86 ms instead of 2.0 ms (simulated,
// mostly Paeth) and 0.61 ms instead of 1.28 ms (EuRoC, Paeth and average).
constexpr int kFilterTypes = 5;

inline int paeth(int a, int b, int c) {
  const int pa = std::abs(b - c);  // |p - a| with p = a + b - c
  const int pb = std::abs(a - c);
  const int pc = std::abs(a + b - 2 * c);
  const int take_b_or_c = -static_cast<int>((pa > pb) | (pa > pc));  // all ones or zero
  const int take_c = -static_cast<int>(pb > pc);
  const int b_or_c = (b & ~take_c) | (c & take_c);
  return (a & ~take_b_or_c) | (b_or_c & take_b_or_c);
}

template <int Type>
inline int predictor(int a, int b, int c) {
  if constexpr (Type == 0) return 0;
  if constexpr (Type == 1) return a;
  if constexpr (Type == 2) return b;
  if constexpr (Type == 3) return (a + b) >> 1;
  if constexpr (Type == 4) return paeth(a, b, c);
}

// One row of filter Type; `up` is the row above (zeros above the first row).
template <int Type>
void unfilterRow(const std::uint8_t* in, const std::uint8_t* up, std::uint8_t* out, std::size_t n) {
  int left = 0;
  int up_left = 0;
  for (std::size_t x = 0; x < n; ++x) {
    const int above = up[x];
    left = out[x] = static_cast<std::uint8_t>(in[x] + predictor<Type>(left, above, up_left));
    up_left = above;
  }
}

// Two consecutive rows of filter types Type0 and Type1; row 1's row above is row 0's output.
template <int Type0, int Type1>
void unfilterRowPair(const std::uint8_t* in0, const std::uint8_t* in1, const std::uint8_t* up, std::uint8_t* out0,
                     std::uint8_t* out1, std::size_t n) {
  int left0 = 0;
  int left1 = 0;
  int up_left0 = 0;
  int up_left1 = 0;
  for (std::size_t x = 0; x < n; ++x) {
    const int above0 = up[x];
    const int v0 = static_cast<std::uint8_t>(in0[x] + predictor<Type0>(left0, above0, up_left0));
    const int v1 = static_cast<std::uint8_t>(in1[x] + predictor<Type1>(left1, v0, up_left1));
    out0[x] = static_cast<std::uint8_t>(v0);
    out1[x] = static_cast<std::uint8_t>(v1);
    up_left0 = above0;
    up_left1 = v0;
    left0 = v0;
    left1 = v1;
  }
}

using RowFn = void (*)(const std::uint8_t*, const std::uint8_t*, std::uint8_t*, std::size_t);
using RowPairFn = void (*)(const std::uint8_t*, const std::uint8_t*, const std::uint8_t*, std::uint8_t*, std::uint8_t*,
                           std::size_t);

template <int... Types>
constexpr std::array<RowFn, kFilterTypes> rowTable(std::integer_sequence<int, Types...> /*types*/) {
  return {&unfilterRow<Types>...};
}
template <int... Pairs>
constexpr std::array<RowPairFn, kFilterTypes * kFilterTypes> rowPairTable(
    std::integer_sequence<int, Pairs...> /*pairs*/) {
  return {&unfilterRowPair<Pairs / kFilterTypes, Pairs % kFilterTypes>...};
}
constexpr auto kUnfilterRow = rowTable(std::make_integer_sequence<int, kFilterTypes>{});
constexpr auto kUnfilterRowPair = rowPairTable(std::make_integer_sequence<int, kFilterTypes * kFilterTypes>{});

}  // namespace

GrayPngDecoder::GrayPngDecoder() : inflater_(libdeflate_alloc_decompressor()) {
  if (inflater_ == nullptr) throw std::bad_alloc();
}

GrayPngDecoder::~GrayPngDecoder() {
  libdeflate_free_decompressor(inflater_);
}

Result<bool> GrayPngDecoder::decodeInto(const std::filesystem::path& path, int width, int height,
                                        std::span<std::uint8_t> pixels) {
  const std::string& name = path.native();  // no copy: nothing allocates unless something is wrong
  const int fd = ::open(name.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    if (errno == ENOENT) return Error{ErrorCode::kNotFound, name + ": image file does not exist"};
    return Error{ErrorCode::kIoError, name + ": cannot open image file: " + std::strerror(errno)};
  }
  struct stat st {};
  if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
    ::close(fd);
    return Error{ErrorCode::kNotFound, name + ": image file does not exist"};
  }
  const auto size = static_cast<std::size_t>(st.st_size);
  if (size == 0) {
    ::close(fd);
    return Error{ErrorCode::kDataError, name + ": image file is empty"};
  }
  reserveBytes(file_, size);
  std::size_t got = 0;
  while (got < size) {
    const ssize_t n = ::read(fd, file_.data() + got, size - got);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    got += static_cast<std::size_t>(n);
  }
  ::close(fd);
  if (got != size) return Error{ErrorCode::kIoError, name + ": image file could not be read whole"};
  return decodeInto(std::span<const std::uint8_t>(file_.data(), size), name, width, height, pixels);
}

Result<bool> GrayPngDecoder::decodeInto(std::span<const std::uint8_t> file, const std::string& name, int width,
                                        int height, std::span<std::uint8_t> pixels) {
  const auto bad = [&](const std::string& what) { return Error{ErrorCode::kDataError, name + ": " + what}; };
  if (width <= 0 || height <= 0 ||
      pixels.size() != static_cast<std::size_t>(width) * static_cast<std::size_t>(height)) {
    return Error{ErrorCode::kInvalidArgument, "GrayPngDecoder: buffer size does not match width*height"};
  }
  if (file.size() < sizeof(kSignature) || std::memcmp(file.data(), kSignature, sizeof(kSignature)) != 0) {
    return false;  // not a PNG: JPEG, PGM, ...; the loader says which
  }
  const std::uint8_t* const begin = file.data();
  const std::size_t end = file.size();
  std::size_t pos = sizeof(kSignature);
  bool have_header = false;
  bool have_end = false;
  std::size_t deflated_bytes = 0;
  while (pos < end && !have_end) {
    if (end - pos < 12) return bad("PNG truncated inside a chunk header");
    const std::uint32_t length = bigEndian32(begin + pos);
    const std::uint8_t* type = begin + pos + 4;
    if (length > 0x7fffffffU || end - pos - 12 < length) return bad("PNG truncated: a chunk runs past the file's end");
    const std::uint8_t* data = type + 4;
    const bool critical = (type[0] & 0x20) == 0;
    if (critical) {
      // Critical chunks are checked: a flipped bit there would otherwise show up as wrong pixels.
      const std::uint32_t crc = bigEndian32(data + length);
      if (libdeflate_crc32(0, type, length + 4) != crc) {
        return bad("PNG chunk " + std::string(reinterpret_cast<const char*>(type), 4) + " fails its checksum");
      }
    }
    if (!have_header) {
      if (!isType(type, "IHDR") || length != 13) return bad("PNG does not start with its header chunk");
      const std::uint32_t w = bigEndian32(data);
      const std::uint32_t h = bigEndian32(data + 4);
      const std::uint8_t bit_depth = data[8];
      const std::uint8_t colour_type = data[9];
      const std::uint8_t compression = data[10];
      const std::uint8_t filter = data[11];
      const std::uint8_t interlace = data[12];
      if (bit_depth != 8 || colour_type != 0 || interlace != 0 || compression != 0 || filter != 0) return false;
      if (w != static_cast<std::uint32_t>(width) || h != static_cast<std::uint32_t>(height)) {
        return bad("image is " + std::to_string(w) + "x" + std::to_string(h) + ", the calibration says " +
                   std::to_string(width) + "x" + std::to_string(height));
      }
      have_header = true;
    } else if (isType(type, "IDAT")) {
      reserveBytes(deflated_, deflated_bytes + length);
      std::memcpy(deflated_.data() + deflated_bytes, data, length);
      deflated_bytes += length;
    } else if (isType(type, "IEND")) {
      have_end = true;
    } else if (critical && !isType(type, "PLTE")) {
      return bad("PNG has an unknown critical chunk " + std::string(reinterpret_cast<const char*>(type), 4));
    }
    pos += 12 + length;
  }
  if (!have_header) return bad("PNG has no header chunk");
  if (deflated_bytes == 0) return bad("PNG has no image data");
  if (!have_end) return bad("PNG truncated: no end chunk");

  const auto row_bytes = static_cast<std::size_t>(width) + 1;
  const std::size_t filtered_bytes = row_bytes * static_cast<std::size_t>(height);
  reserveBytes(filtered_, filtered_bytes);
  // Exactly the rows the header promises: fewer or more is a corrupt file.
  const libdeflate_result r = libdeflate_zlib_decompress(inflater_, deflated_.data(), deflated_bytes, filtered_.data(),
                                                         filtered_bytes, nullptr);
  if (r == LIBDEFLATE_SHORT_OUTPUT) return bad("PNG image data ends before the last row");
  if (r == LIBDEFLATE_INSUFFICIENT_SPACE) return bad("PNG image data holds more than width x height pixels");
  if (r != LIBDEFLATE_SUCCESS) return bad("PNG image data is corrupt (does not inflate)");

  const auto w = static_cast<std::size_t>(width);
  const auto h = static_cast<std::size_t>(height);
  for (std::size_t y = 0; y < h; ++y) {
    const std::uint8_t type = filtered_[y * row_bytes];
    if (type >= kFilterTypes) {
      return bad("PNG row " + std::to_string(y) + " has an unknown filter type " + std::to_string(type));
    }
  }
  if (zero_row_.size() < w) zero_row_.assign(w, 0);  // grows like the other buffers, and stays zero
  const auto row = [&](std::size_t y) { return filtered_.data() + y * row_bytes; };
  const auto out = [&](std::size_t y) { return pixels.data() + y * w; };
  std::size_t y = 0;
  for (; y + 2 <= h; y += 2) {
    const std::uint8_t* up = y == 0 ? zero_row_.data() : out(y - 1);
    kUnfilterRowPair[static_cast<std::size_t>(row(y)[0] * kFilterTypes + row(y + 1)[0])](row(y) + 1, row(y + 1) + 1, up,
                                                                                         out(y), out(y + 1), w);
  }
  if (y < h) kUnfilterRow[row(y)[0]](row(y) + 1, y == 0 ? zero_row_.data() : out(y - 1), out(y), w);
  return true;
}

}  // namespace cvislam::dataset

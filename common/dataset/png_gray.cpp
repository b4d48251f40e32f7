#include "common/dataset/png_gray.hpp"

#include <fcntl.h>
#include <libdeflate.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <new>
#include <string>

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

// The inverse of PNG filter `type` for one row of one-byte pixels: out = filtered + predictor(left, up,
// up-left). `up` is the previous output row, or nullptr on the first row (PNG treats it as zeros).
bool unfilterRow(std::uint8_t type, const std::uint8_t* in, const std::uint8_t* up, std::uint8_t* out, std::size_t n) {
  switch (type) {
    case 0:
      std::memcpy(out, in, n);
      return true;
    case 1: {
      std::uint8_t left = 0;
      for (std::size_t x = 0; x < n; ++x) left = out[x] = static_cast<std::uint8_t>(in[x] + left);
      return true;
    }
    case 2:
      if (up == nullptr) {
        std::memcpy(out, in, n);
      } else {
        for (std::size_t x = 0; x < n; ++x) out[x] = static_cast<std::uint8_t>(in[x] + up[x]);
      }
      return true;
    case 3: {
      unsigned left = 0;
      for (std::size_t x = 0; x < n; ++x) {
        const unsigned above = up == nullptr ? 0U : up[x];
        out[x] = static_cast<std::uint8_t>(in[x] + ((left + above) >> 1));
        left = out[x];
      }
      return true;
    }
    case 4: {
      if (up == nullptr) return unfilterRow(1, in, up, out, n);  // b = c = 0: Paeth picks the left pixel
      int left = 0;
      int up_left = 0;
      for (std::size_t x = 0; x < n; ++x) {
        const int above = up[x];
        const int p = left + above - up_left;
        const int pa = std::abs(p - left);
        const int pb = std::abs(p - above);
        const int pc = std::abs(p - up_left);
        const int predictor = (pa <= pb && pa <= pc) ? left : (pb <= pc ? above : up_left);
        out[x] = static_cast<std::uint8_t>(in[x] + predictor);
        left = out[x];
        up_left = above;
      }
      return true;
    }
    default:
      return false;
  }
}

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
    return false;  // not a PNG: JPEG, PGM, ... for OpenCV
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
  for (std::size_t y = 0; y < static_cast<std::size_t>(height); ++y) {
    const std::uint8_t* row = filtered_.data() + y * row_bytes;
    std::uint8_t* out = pixels.data() + y * w;
    if (!unfilterRow(row[0], row + 1, y == 0 ? nullptr : out - w, out, w)) {
      return bad("PNG row " + std::to_string(y) + " has an unknown filter type " + std::to_string(row[0]));
    }
  }
  return true;
}

}  // namespace cvislam::dataset

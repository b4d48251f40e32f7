#include "common/dataset/image.hpp"

#include <array>
#include <cstring>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "common/dataset/png_gray.hpp"

namespace cvislam::dataset {
namespace {

constexpr std::array<std::uint8_t, 8> kPngSignature = {137, 'P', 'N', 'G', '\r', '\n', 26, '\n'};

std::uint32_t bigEndian32(const std::uint8_t* p) {
  return (std::uint32_t{p[0]} << 24) | (std::uint32_t{p[1]} << 16) | (std::uint32_t{p[2]} << 8) | std::uint32_t{p[3]};
}

// What a file that the grey PNG decoder handed back is, from its first bytes, and what to do about it.
Error unsupportedImage(const std::filesystem::path& path) {
  std::array<std::uint8_t, 32> head{};
  std::ifstream in(path, std::ios::binary);
  in.read(reinterpret_cast<char*>(head.data()), static_cast<std::streamsize>(head.size()));
  const auto got = static_cast<std::size_t>(in.gcount());
  std::string what = "not a PNG file";
  if (got >= 29 && std::memcmp(head.data(), kPngSignature.data(), kPngSignature.size()) == 0) {
    static constexpr std::array<const char*, 7> kColour = {"grey", "", "RGB", "palette", "grey+alpha", "", "RGBA"};
    const int depth = head[24];
    const int colour = head[25];
    const char* colour_name =
        colour < static_cast<int>(kColour.size()) ? kColour[static_cast<std::size_t>(colour)] : "";
    what = "a PNG with " + std::to_string(depth) + "-bit " +
           (colour_name[0] != '\0' ? std::string(colour_name) : "colour type " + std::to_string(colour)) + " pixels" +
           (head[28] != 0 ? ", interlaced" : "");
  } else if (got >= 2 && head[0] == 0xFF && head[1] == 0xD8) {
    what = "a JPEG file";
  } else if (got >= 2 && head[0] == 'P' && head[1] >= '1' && head[1] <= '6') {
    what = "a PGM/PNM file";
  }
  return Error{ErrorCode::kDataError, path.string() + ": " + what +
                                          "; cvislam reads 8-bit greyscale PNG, not interlaced (the EuRoC format). "
                                          "Convert the images, e.g. ImageMagick's `mogrify -format png -colorspace "
                                          "Gray -depth 8 -interlace none <files>`"};
}

}  // namespace

Result<GrayImage> readGrayImage(const std::filesystem::path& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return Error{ErrorCode::kNotFound, path.string() + ": image file does not exist"};
  }
  std::ifstream in(path, std::ios::binary);
  const std::vector<std::uint8_t> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (!in.good() && !in.eof()) return Error{ErrorCode::kIoError, path.string() + ": cannot read image file"};
  if (bytes.empty()) return Error{ErrorCode::kDataError, path.string() + ": image file is empty"};
  // The size from the header chunk, which a PNG starts with; the decoder checks the rest.
  if (bytes.size() < 24 || std::memcmp(bytes.data(), kPngSignature.data(), kPngSignature.size()) != 0) {
    return unsupportedImage(path);
  }
  const std::uint32_t width = bigEndian32(bytes.data() + 16);
  const std::uint32_t height = bigEndian32(bytes.data() + 20);
  if (width == 0 || height == 0 || width > 65535 || height > 65535) {
    return Error{ErrorCode::kDataError, path.string() + ": PNG header gives an image of " + std::to_string(width) +
                                            "x" + std::to_string(height) + " px"};
  }
  GrayImage image(static_cast<int>(width), static_cast<int>(height));
  GrayPngDecoder png;
  auto decoded = png.decodeInto(bytes, path.string(), image.width, image.height, image.pixels);
  if (!decoded) return decoded.error();
  if (!*decoded) return unsupportedImage(path);
  return image;
}

Status readGrayImageInto(const std::filesystem::path& path, int width, int height, std::span<std::uint8_t> pixels) {
  GrayPngDecoder png;
  return readGrayImageInto(path, width, height, pixels, png);
}

Status readGrayImageInto(const std::filesystem::path& path, int width, int height, std::span<std::uint8_t> pixels,
                         GrayPngDecoder& png) {
  auto decoded = png.decodeInto(path, width, height, pixels);
  if (!decoded) return decoded.error();
  if (!*decoded) return unsupportedImage(path);
  return Status::Ok();
}

}  // namespace cvislam::dataset

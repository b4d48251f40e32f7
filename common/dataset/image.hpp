// 8-bit grey images, and reading/writing them as files. OpenCV stays inside image.cpp.
#pragma once

#include <cstdint>
#include <filesystem>
#include <span>
#include <vector>

#include "common/core/result.hpp"

namespace cvislam::dataset {

// Row-major 8-bit grey pixels, stride == width.
struct GrayImage {
  int width = 0;
  int height = 0;
  std::vector<std::uint8_t> pixels;

  GrayImage() = default;
  GrayImage(int w, int h, std::uint8_t fill = 0)
      : width(w), height(h), pixels(static_cast<std::size_t>(w) * static_cast<std::size_t>(h), fill) {}

  [[nodiscard]] std::uint8_t at(int x, int y) const {
    return pixels[static_cast<std::size_t>(y) * static_cast<std::size_t>(width) + static_cast<std::size_t>(x)];
  }
  std::uint8_t& at(int x, int y) {
    return pixels[static_cast<std::size_t>(y) * static_cast<std::size_t>(width) + static_cast<std::size_t>(x)];
  }
  [[nodiscard]] bool empty() const { return pixels.empty(); }
};

// Reads PNG/JPEG/PGM; colour images are converted to grey. Errors name the file and say what is wrong
// (missing, empty, not decodable, unsupported bit depth).
Result<GrayImage> readGrayImage(const std::filesystem::path& path);

// Reads into caller-owned storage of exactly width*height bytes (the agent's preallocated frame buffers);
// fails if the image does not have that size.
Status readGrayImageInto(const std::filesystem::path& path, int width, int height, std::span<std::uint8_t> pixels);

class GrayPngDecoder;
// The same, with `png` decoding 8-bit grey PNGs (png_gray.hpp) and OpenCV everything else: a frame loader keeps
// one decoder for the run.
Status readGrayImageInto(const std::filesystem::path& path, int width, int height, std::span<std::uint8_t> pixels,
                         GrayPngDecoder& png);

// Writes a PNG. The bytes depend only on the pixels (fixed compression settings), so output is reproducible.
Status writeGrayPng(const std::filesystem::path& path, const GrayImage& image);

}  // namespace cvislam::dataset

// 8-bit grey images, and reading them from files: 8-bit greyscale PNG (not interlaced), the format of EuRoC-layout
// datasets, decoded by png_gray.hpp without OpenCV. Other formats (colour PNG, JPEG, PGM) and writing PNG are in
// image_codecs.hpp, through OpenCV's imgcodecs, for the tools; the agent does not link imgcodecs, which with the
// GDAL, GDCM and poppler libraries it loads costs about 40 MB of resident memory.
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

// Reads an 8-bit greyscale PNG. Errors name the file and say what is wrong (missing, empty, corrupt, or another
// format: which one, and how to convert it).
Result<GrayImage> readGrayImage(const std::filesystem::path& path);

// Reads into caller-owned storage of exactly width*height bytes (the agent's preallocated frame buffers);
// fails if the image does not have that size.
Status readGrayImageInto(const std::filesystem::path& path, int width, int height, std::span<std::uint8_t> pixels);

class GrayPngDecoder;
// The same with a decoder that keeps its buffers from file to file: a frame loader keeps one for the run.
Status readGrayImageInto(const std::filesystem::path& path, int width, int height, std::span<std::uint8_t> pixels,
                         GrayPngDecoder& png);

}  // namespace cvislam::dataset

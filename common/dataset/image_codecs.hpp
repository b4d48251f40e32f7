// Images through OpenCV's imgcodecs, for the tools (the simulator, the vocabulary trainer): any format OpenCV
// reads, and writing PNG. The agent reads its frames with image.hpp instead and does not link this.
#pragma once

#include <filesystem>

#include "common/core/result.hpp"
#include "common/dataset/image.hpp"

namespace cvislam::dataset {

// Reads PNG/JPEG/PGM/...; colour images are converted to grey. Errors name the file and say what is wrong
// (missing, empty, not decodable, unsupported bit depth).
Result<GrayImage> readImageAsGray(const std::filesystem::path& path);

// Writes a PNG. The bytes depend only on the pixels (fixed compression settings), so output is reproducible.
Status writeGrayPng(const std::filesystem::path& path, const GrayImage& image);

}  // namespace cvislam::dataset

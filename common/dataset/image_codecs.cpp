#include "common/dataset/image_codecs.hpp"

#include <cstring>
#include <string>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace cvislam::dataset {

Result<GrayImage> readImageAsGray(const std::filesystem::path& path) {
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return Error{ErrorCode::kNotFound, path.string() + ": image file does not exist"};
  }
  const auto size = std::filesystem::file_size(path, ec);
  if (ec || size == 0) return Error{ErrorCode::kDataError, path.string() + ": image file is empty"};
  cv::Mat image;
  try {
    image = cv::imread(path.string(), cv::IMREAD_UNCHANGED);
  } catch (const cv::Exception& e) {
    return Error{ErrorCode::kDataError, path.string() + ": cannot decode image: " + e.what()};
  }
  if (image.empty()) {
    return Error{ErrorCode::kDataError, path.string() + ": cannot decode image (corrupt or not an image file)"};
  }
  if (image.depth() != CV_8U) {
    return Error{ErrorCode::kDataError, path.string() + ": unsupported pixel format (" +
                                            std::to_string(8 * image.elemSize1()) + "-bit), expected 8-bit grey"};
  }
  if (image.channels() == 3) {
    cv::cvtColor(image, image, cv::COLOR_BGR2GRAY);
  } else if (image.channels() == 4) {
    cv::cvtColor(image, image, cv::COLOR_BGRA2GRAY);
  } else if (image.channels() != 1) {
    return Error{ErrorCode::kDataError,
                 path.string() + ": unsupported channel count " + std::to_string(image.channels())};
  }
  GrayImage out(image.cols, image.rows);
  for (int y = 0; y < image.rows; ++y) {
    std::memcpy(out.pixels.data() + static_cast<std::size_t>(y) * static_cast<std::size_t>(image.cols),
                image.ptr<std::uint8_t>(y), static_cast<std::size_t>(image.cols));
  }
  return out;
}

Status writeGrayPng(const std::filesystem::path& path, const GrayImage& image) {
  if (image.width <= 0 || image.height <= 0 ||
      image.pixels.size() != static_cast<std::size_t>(image.width) * static_cast<std::size_t>(image.height)) {
    return Error{ErrorCode::kInvalidArgument, path.string() + ": image has no pixels or a wrong pixel count"};
  }
  // cv::Mat over our buffer without copying; imwrite only reads it.
  const cv::Mat view(image.height, image.width, CV_8UC1, const_cast<std::uint8_t*>(image.pixels.data()));
  const std::vector<int> params = {cv::IMWRITE_PNG_COMPRESSION, 3, cv::IMWRITE_PNG_STRATEGY,
                                   cv::IMWRITE_PNG_STRATEGY_DEFAULT};
  bool ok = false;
  try {
    ok = cv::imwrite(path.string(), view, params);
  } catch (const cv::Exception& e) {
    return Error{ErrorCode::kIoError, path.string() + ": cannot write PNG: " + e.what()};
  }
  if (!ok) return Error{ErrorCode::kIoError, path.string() + ": cannot write PNG"};
  return Status::Ok();
}

}  // namespace cvislam::dataset

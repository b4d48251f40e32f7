// The frame loader's PNG decoding allocates nothing once its buffers have grown to the largest file.
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "common/dataset/image.hpp"
#include "common/dataset/image_codecs.hpp"
#include "common/dataset/png_gray.hpp"
#include "test/support/malloc_counter.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::dataset {
namespace {

TEST(GrayPngDecoder, AllocatesNothingOnceItsBuffersHaveGrown) {
  test::TempDir dir;
  std::mt19937 rng(5);
  // A noisy image compresses worst: its file is the largest, so the first decode grows every buffer.
  GrayImage noisy(752, 480);
  for (auto& p : noisy.pixels) p = static_cast<std::uint8_t>(rng() & 0xff);
  GrayImage smooth(752, 480);
  for (int y = 0; y < smooth.height; ++y) {
    for (int x = 0; x < smooth.width; ++x) smooth.at(x, y) = static_cast<std::uint8_t>((x + 2 * y) & 0xff);
  }
  ASSERT_TRUE(writeGrayPng(dir / "noisy.png", noisy).ok());
  ASSERT_TRUE(writeGrayPng(dir / "smooth.png", smooth).ok());
  const auto noisy_path = dir / "noisy.png";
  const auto smooth_path = dir / "smooth.png";

  GrayPngDecoder png;
  std::vector<std::uint8_t> pixels(noisy.pixels.size());
  ASSERT_TRUE(readGrayImageInto(noisy_path, 752, 480, pixels, png).ok());
  const long before = test::threadMallocCount();
  for (int i = 0; i < 5; ++i) {
    const Status a = readGrayImageInto(smooth_path, 752, 480, pixels, png);
    const Status b = readGrayImageInto(noisy_path, 752, 480, pixels, png);
    ASSERT_TRUE(a.ok() && b.ok());
  }
  EXPECT_EQ(test::threadMallocCount() - before, 0);
  EXPECT_EQ(pixels, noisy.pixels);
}

}  // namespace
}  // namespace cvislam::dataset

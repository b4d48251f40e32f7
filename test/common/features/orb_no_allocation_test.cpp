// Counts heap allocations (this binary replaces global operator new) while OrbExtractor extracts from real EuRoC
// frames: the agent's tracking loop extracts on every frame and must not allocate after start-up.
#include <vector>

#include <gtest/gtest.h>

#include "common/dataset/euroc.hpp"
#include "common/features/orb.hpp"
#include "test/support/allocation_counter.hpp"
#include "test/support/test_data.hpp"

namespace cvislam::features {
namespace {

TEST(OrbNoAllocation, TheCounterSeesAnAllocation) {
  const long before = test::allocationCount();
  std::vector<int> v(100);
  const volatile int first = v[0];  // keeps the allocation from being optimised away
  (void)first;
  EXPECT_GE(test::allocationCount() - before, 1);
}

TEST(OrbNoAllocation, ExtractDoesNotAllocateAfterCreate) {
  const std::filesystem::path path = test::findData("euroc-v101-excerpt");
  if (path.empty()) GTEST_SKIP() << "test data 'euroc-v101-excerpt' not found under " << test::dataRoot();
  auto seq = dataset::EurocSequence::open(path);
  ASSERT_TRUE(seq.ok()) << seq.error().toString();
  std::vector<dataset::GrayImage> frames;
  for (std::size_t i = 0; i < 21; ++i) {
    auto image = seq->loadImage(static_cast<int>(i % 2), i * 4);  // both cameras, frames 0 to 80
    ASSERT_TRUE(image.ok()) << image.error().toString();
    frames.push_back(std::move(*image));
  }
  const dataset::GrayImage smaller(320, 240, 128);  // another size: the per-size tables are rebuilt in place
  const dataset::GrayImage too_large(2000, 1200, 128);

  auto extractor = OrbExtractor::create({});
  ASSERT_TRUE(extractor.ok());
  ASSERT_TRUE(extractor->checkImageSize(frames[0].width, frames[0].height).ok());
  std::vector<Keypoint> keypoints(500);
  std::vector<Descriptor> descriptors(500);
  const auto extract = [&](const dataset::GrayImage& image) {
    return extractor->extract(image.pixels, image.width, image.height, keypoints, descriptors);
  };
  const int first = extract(frames[0]);

  std::vector<int> counts;
  counts.reserve(frames.size() + 2);
  const long before = test::allocationCount();
  for (std::size_t i = 1; i < frames.size(); ++i) counts.push_back(extract(frames[i]));
  counts.push_back(extract(smaller));
  counts.push_back(extract(too_large));
  counts.push_back(extract(frames[0]));
  const long allocations = test::allocationCount() - before;

  EXPECT_EQ(allocations, 0) << "heap allocations in " << counts.size() << " extract calls";
  EXPECT_EQ(first, 500);
  for (std::size_t i = 0; i + 3 < counts.size(); ++i) EXPECT_EQ(counts[i], 500) << "frame " << i + 1;
  EXPECT_EQ(counts[counts.size() - 2], 0) << "an image larger than max_width x max_height is refused";
  EXPECT_EQ(counts.back(), first);
}

}  // namespace
}  // namespace cvislam::features

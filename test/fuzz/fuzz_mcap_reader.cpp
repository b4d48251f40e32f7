// Fuzzes what the agent reads from a ROS 2 bag: the input as an MCAP file (Reader::openBytes, every message read,
// with and without CRC checks, small limits so that hostile sizes are refused at once), each message's data through the
// Image and Imu CDR decoders, and the input itself through both decoders. A message that decodes must encode and decode
// again to the same fields. Seeds: the sample bag of the MCAP tests in every writer layout, and its two CDR messages
// alone.
#include <cstring>
#include <vector>

#include "common/mcap/reader.hpp"
#include "common/ros2/messages.hpp"
#include "test/common/mcap/sample_bag.hpp"
#include "test/fuzz/fuzz_target.hpp"

namespace {

using namespace cvislam;

bool sameHeader(const ros2::HeaderView& a, const ros2::HeaderView& b) {
  return a.stamp == b.stamp && a.frame_id == b.frame_id;
}

void decodeBoth(std::span<const std::uint8_t> cdr) {
  std::vector<std::uint8_t> again;
  if (const auto image = ros2::decodeImage(cdr); image.ok()) {
    (void)ros2::checkImageLayout(image.value());
    if (!ros2::encodeImage(image.value(), again).ok()) __builtin_trap();
    const auto back = ros2::decodeImage(again);
    if (!back.ok() || !sameHeader(back->header, image->header) || back->height != image->height ||
        back->width != image->width || back->encoding != image->encoding || back->step != image->step ||
        back->is_bigendian != image->is_bigendian || back->data.size() != image->data.size() ||
        std::memcmp(back->data.data(), image->data.data(), image->data.size()) != 0) {
      __builtin_trap();
    }
  }
  if (const auto imu = ros2::decodeImu(cdr); imu.ok()) {
    if (!ros2::encodeImu(imu.value(), again).ok()) __builtin_trap();
    const auto back = ros2::decodeImu(again);
    // Compared as bytes: a NaN read from the input must come back as the same NaN.
    if (!back.ok() || !sameHeader(back->header, imu->header) ||
        std::memcmp(&back->orientation, &imu->orientation, sizeof imu->orientation) != 0 ||
        std::memcmp(back->linear_acceleration_covariance.data(), imu->linear_acceleration_covariance.data(),
                    sizeof imu->linear_acceleration_covariance) != 0) {
      __builtin_trap();
    }
  }
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::span<const std::uint8_t> input(data, size);
  // Twice: with the CRCs checked, and without, so that a mutation in CRC-covered bytes still reaches the parsers.
  for (const bool check_crcs : {true, false}) {
    mcap::ReaderOptions options;
    options.max_record_bytes = std::uint64_t{1} << 20;
    options.max_definition_bytes = std::uint64_t{1} << 20;
    options.check_crcs = check_crcs;
    auto reader = mcap::Reader::openBytes(std::vector<std::uint8_t>(input.begin(), input.end()), options);
    if (!reader.ok()) continue;
    mcap::MessageView m;
    std::uint64_t yielded = 0;
    for (auto more = reader->next(m); more.ok() && more.value(); more = reader->next(m)) {
      if (m.channel == nullptr || m.channel->id != m.channel_id) __builtin_trap();
      decodeBoth(m.data);
      ++yielded;
    }
    if (yielded != reader->counts().messages) __builtin_trap();
  }
  decodeBoth(input);
  return 0;
}

std::vector<std::string> cvislam::fuzz::seeds() {
  std::vector<std::string> out;
  const auto add = [&out](const std::vector<std::uint8_t>& bytes) { out.emplace_back(bytes.begin(), bytes.end()); };
  const mcap::test::SampleOptions sample{.imu_messages = 6, .imu_per_image = 3, .width = 8, .height = 4};
  for (const mcap::Compression compression :
       {mcap::Compression::kZstd, mcap::Compression::kLz4, mcap::Compression::kNone}) {
    for (const bool use_chunks : {true, false}) {
      mcap::WriterOptions o;
      o.compression = compression;
      o.use_chunks = use_chunks;
      o.chunk_bytes = 1024;
      if (auto bytes = mcap::test::sampleBytes(o, sample); bytes.ok()) add(bytes.value());
      o.write_summary = false;
      if (auto bytes = mcap::test::sampleBytes(o, sample); bytes.ok()) add(bytes.value());
    }
  }
  std::vector<std::uint8_t> cdr;
  const std::vector<std::uint8_t> pixels(12, 0x40);
  ros2::ImageView image;
  image.header = {{1403715273, 262142976}, "cam0"};
  image.height = 3;
  image.width = 4;
  image.encoding = "mono8";
  image.step = 4;
  image.data = pixels;
  if (ros2::encodeImage(image, cdr).ok()) add(cdr);
  ros2::ImuView imu;
  imu.header = {{1403715273, 262142976}, "imu0"};
  imu.linear_acceleration_m_s2 = {9.1, 0.1, -3.7};
  if (ros2::encodeImu(imu, cdr).ok()) add(cdr);
  return out;
}

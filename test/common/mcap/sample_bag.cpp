#include "test/common/mcap/sample_bag.hpp"

#include <cstdio>
#include <vector>

#include "common/mcap/codec.hpp"
#include "common/ros2/messages.hpp"

namespace cvislam::mcap::test {

Status writeSample(Writer& writer, const SampleOptions& options) {
  auto imu_schema = writer.addSchema(ros2::kImuType, ros2::kSchemaEncoding, ros2::kImuDefinition);
  auto image_schema = writer.addSchema(ros2::kImageType, ros2::kSchemaEncoding, ros2::kImageDefinition);
  if (!imu_schema.ok()) return imu_schema.error();
  if (!image_schema.ok()) return image_schema.error();
  auto imu = writer.addChannel(imu_schema.value(), "/imu0", ros2::kMessageEncoding);
  auto cam = writer.addChannel(image_schema.value(), "/cam0/image_raw", ros2::kMessageEncoding,
                               {{"offered_qos_profiles", ""}});
  auto notes = writer.addChannel(0, "/notes", "json");
  if (!imu.ok()) return imu.error();
  if (!cam.ok()) return cam.error();
  if (!notes.ok()) return notes.error();

  if (options.attachment_and_metadata) {
    const std::string calibration = "cam0: {fx: 458.654, fy: 457.296}\n";
    Attachment a;
    a.log_time_ns = options.start_ns;
    a.create_time_ns = options.start_ns - 1;
    a.name = "calibration.yaml";
    a.media_type = "application/yaml";
    a.data = {reinterpret_cast<const std::uint8_t*>(calibration.data()), calibration.size()};
    if (Status s = writer.writeAttachment(a); !s.ok()) return s;
    if (Status s = writer.writeMetadata({"mission", {{"agent", "3"}, {"sequence", "V1_01"}}}); !s.ok()) return s;
  }

  std::vector<std::uint8_t> cdr;
  std::vector<std::uint8_t> pixels(std::size_t{options.width} * options.height);
  std::uint32_t image_sequence = 0;
  for (int i = 0; i < options.imu_messages; ++i) {
    const std::uint64_t t_ns = options.start_ns + static_cast<std::uint64_t>(i) * 5'000'000ULL;  // 200 Hz
    auto stamp = ros2::timeFromNanoseconds(static_cast<std::int64_t>(t_ns));
    if (!stamp.ok()) return stamp.error();
    ros2::ImuView m;
    m.header = {stamp.value(), "imu0"};
    m.orientation_covariance[0] = -1;  // no orientation
    m.angular_velocity_rad_s = {0.01 * i, -0.02, 0.03};
    m.linear_acceleration_m_s2 = {9.1, 0.1 * i, -3.7};
    if (Status s = ros2::encodeImu(m, cdr); !s.ok()) return s;
    if (Status s = writer.write({imu.value(), static_cast<std::uint32_t>(i), t_ns, t_ns, cdr}); !s.ok()) return s;

    if (i % options.imu_per_image == 0) {
      for (std::uint32_t y = 0; y < options.height; ++y) {
        for (std::uint32_t x = 0; x < options.width; ++x) {
          pixels[y * options.width + x] = static_cast<std::uint8_t>(x * 7 + y * 13 + image_sequence * 31);
        }
      }
      ros2::ImageView image;
      image.header = {stamp.value(), "cam0"};
      image.height = options.height;
      image.width = options.width;
      image.encoding = "mono8";
      image.step = options.width;
      image.data = pixels;
      if (Status s = ros2::encodeImage(image, cdr); !s.ok()) return s;
      // The publish time of a camera frame is after its exposure: keep it apart from the log time.
      if (Status s = writer.write({cam.value(), image_sequence, t_ns, t_ns + 1'500'000, cdr}); !s.ok()) return s;
      const std::string note = "{\"frame\":" + std::to_string(image_sequence) + "}";
      const std::span<const std::uint8_t> note_bytes(reinterpret_cast<const std::uint8_t*>(note.data()), note.size());
      if (Status s = writer.write({notes.value(), image_sequence, t_ns, t_ns, note_bytes}); !s.ok()) return s;
      ++image_sequence;
    }
  }
  return {};
}

Result<std::vector<std::uint8_t>> sampleBytes(const WriterOptions& writer_options, const SampleOptions& options) {
  auto writer = Writer::createInMemory(writer_options);
  if (!writer.ok()) return writer.error();
  if (Status s = writeSample(writer.value(), options); !s.ok()) return s.error();
  if (Status s = writer->close(); !s.ok()) return s.error();
  return writer->memoryBytes();
}

std::string messageLine(const MessageView& message) {
  char crc[16];
  std::snprintf(crc, sizeof crc, "%08x", codec::crc32(0, message.data));
  return message.channel->topic + " " + std::to_string(message.sequence) + " " + std::to_string(message.log_time_ns) +
         " " + std::to_string(message.publish_time_ns) + " " + std::to_string(message.data.size()) + " " + crc;
}

Result<std::string> listMessages(Reader& reader) {
  std::string out;
  MessageView m;
  for (;;) {
    auto more = reader.next(m);
    if (!more.ok()) return more.error();
    if (!more.value()) return out;
    out += messageLine(m) + "\n";
  }
}

}  // namespace cvislam::mcap::test

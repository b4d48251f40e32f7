#include "test/support/euroc_to_mcap.hpp"

#include <algorithm>
#include <vector>

#include "common/dataset/euroc.hpp"
#include "common/mcap/writer.hpp"
#include "common/ros2/messages.hpp"

namespace cvislam::test {
namespace {

struct Item {
  std::int64_t t_ns = 0;
  int kind = 0;  // 0, 1: camera; 2: IMU
  std::size_t index = 0;
};

}  // namespace

Status writeEurocAsMcap(const std::filesystem::path& euroc_folder, const std::filesystem::path& mcap_file,
                        const EurocToMcapOptions& options) {
  auto sequence = dataset::EurocSequence::open(euroc_folder);
  if (!sequence) return sequence.error();
  mcap::WriterOptions writer_options;
  writer_options.compression = options.compression;
  writer_options.use_chunks = options.use_chunks;
  auto writer = mcap::Writer::create(mcap_file, writer_options);
  if (!writer) return writer.error();
  auto image_schema = writer->addSchema(ros2::kImageType, ros2::kSchemaEncoding, ros2::kImageDefinition);
  auto imu_schema = writer->addSchema(ros2::kImuType, ros2::kSchemaEncoding, ros2::kImuDefinition);
  if (!image_schema || !imu_schema) return Error{ErrorCode::kInternal, "cannot add the schemas"};
  std::vector<std::uint16_t> channels;
  for (int c = 0; c < sequence->cameraCount(); ++c) {
    auto channel = writer->addChannel(*image_schema, "/cam" + std::to_string(c) + "/image_raw", ros2::kMessageEncoding);
    if (!channel) return channel.error();
    channels.push_back(*channel);
  }
  auto imu_channel = writer->addChannel(*imu_schema, "/imu0", ros2::kMessageEncoding);
  if (!imu_channel) return imu_channel.error();

  std::vector<Item> items;
  for (int c = 0; c < sequence->cameraCount(); ++c) {
    const auto& frames = sequence->camera(c).frames;
    for (std::size_t i = 0; i < frames.size(); ++i) items.push_back({frames[i].t_ns, c, i});
  }
  for (std::size_t i = 0; i < sequence->imu().size(); ++i) items.push_back({sequence->imu()[i].t_ns, 2, i});
  std::stable_sort(items.begin(), items.end(), [](const Item& a, const Item& b) { return a.t_ns < b.t_ns; });

  const int channels_per_pixel = options.image_encoding == "mono8" ? 1 : 3;
  std::vector<std::uint8_t> cdr;
  std::vector<std::uint8_t> pixels;
  std::uint32_t sequence_number = 0;
  for (const Item& item : items) {
    auto stamp = ros2::timeFromNanoseconds(options.zero_header_stamps ? 0 : item.t_ns);
    if (!stamp) return stamp.error();
    Status encoded = Status::Ok();
    std::uint16_t channel = *imu_channel;
    if (item.kind < 2) {
      auto image = sequence->loadImage(item.kind, item.index);
      if (!image) return image.error();
      const auto n = static_cast<std::size_t>(image->width) * static_cast<std::size_t>(image->height);
      pixels.resize(n * static_cast<std::size_t>(channels_per_pixel));
      for (std::size_t p = 0; p < n; ++p) {
        for (int k = 0; k < channels_per_pixel; ++k) {
          pixels[p * static_cast<std::size_t>(channels_per_pixel) + static_cast<std::size_t>(k)] = image->pixels[p];
        }
      }
      ros2::ImageView view;
      view.header.stamp = *stamp;
      view.header.frame_id = item.kind == 0 ? "cam0" : "cam1";
      view.width = static_cast<std::uint32_t>(image->width);
      view.height = static_cast<std::uint32_t>(image->height);
      view.encoding = options.image_encoding;
      view.step = view.width * static_cast<std::uint32_t>(channels_per_pixel);
      view.data = pixels;
      encoded = ros2::encodeImage(view, cdr);
      channel = channels[static_cast<std::size_t>(item.kind)];
    } else {
      const dataset::ImuSample& s = sequence->imu()[item.index];
      ros2::ImuView view;
      view.header.stamp = *stamp;
      view.header.frame_id = "imu0";
      view.orientation_covariance[0] = -1.0;  // no orientation
      view.angular_velocity_rad_s = {s.gyro_s.x(), s.gyro_s.y(), s.gyro_s.z()};
      view.linear_acceleration_m_s2 = {s.accel_s.x(), s.accel_s.y(), s.accel_s.z()};
      encoded = ros2::encodeImu(view, cdr);
    }
    if (!encoded.ok()) return encoded;
    mcap::Message message;
    message.channel_id = channel;
    message.sequence = sequence_number++;
    message.log_time_ns = static_cast<std::uint64_t>(item.t_ns);
    message.publish_time_ns = message.log_time_ns;
    message.data = cdr;
    if (Status s = writer->write(message); !s.ok()) return s;
  }
  return writer->close();
}

}  // namespace cvislam::test

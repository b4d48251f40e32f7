#include "agent_rt/live/sensor_publisher.hpp"

#include <cstring>
#include <new>

#include "agent_rt/live/live_service.hpp"
#include "common/core/steady_clock.hpp"
#include "iceoryx_posh/popo/untyped_publisher.hpp"

namespace cvislam::agent::live {

Status SensorPublisherOptions::validate() const {
  const auto bad = [](const std::string& what) { return Error{ErrorCode::kInvalidArgument, what}; };
  if (stream.empty() || stream.size() > kMaxStreamNameLength) {
    return bad("the stream name must have 1 to " + std::to_string(kMaxStreamNameLength) + " characters");
  }
  if (width == 0 || height == 0 || width > 8192 || height > 8192) {
    return bad("image size " + std::to_string(width) + "x" + std::to_string(height) + " is outside 1..8192");
  }
  if (cameras != 1 && cameras != 2) return bad("cameras must be 1 (mono) or 2 (a stereo pair)");
  return Status::Ok();
}

struct SensorPublisher::Impl {
  explicit Impl(const SensorPublisherOptions& o)
      : options(o),
        frames(liveService(o.stream, kFramesEvent), publisherOptions()),
        imu(liveService(o.stream, kImuEvent), publisherOptions()) {}

  // A driver never waits for a slow reader: the reader's oldest queued message goes.
  static iox::popo::PublisherOptions publisherOptions() {
    iox::popo::PublisherOptions options;
    options.historyCapacity = 0;
    options.subscriberTooSlowPolicy = iox::popo::ConsumerTooSlowPolicy::DISCARD_OLDEST_DATA;
    return options;
  }

  void giveBackLoan() {
    if (loaned != nullptr) frames.release(loaned);
    loaned = nullptr;
  }

  SensorPublisherOptions options;
  iox::popo::UntypedPublisher frames;
  iox::popo::UntypedPublisher imu;
  void* loaned = nullptr;
  std::uint64_t frame_sequence = 0;
  std::uint64_t imu_sequence = 0;
  SensorPublisherStats stats;
};

Result<std::unique_ptr<SensorPublisher>> SensorPublisher::create(const SensorPublisherOptions& options) {
  if (Status s = options.validate(); !s.ok()) return s.error();
  return std::unique_ptr<SensorPublisher>(new SensorPublisher(std::make_unique<Impl>(options)));
}

SensorPublisher::SensorPublisher(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

SensorPublisher::~SensorPublisher() {
  impl_->giveBackLoan();
}

std::span<std::uint8_t> SensorPublisher::loanFrame() {
  Impl& d = *impl_;
  d.giveBackLoan();
  const SensorPublisherOptions& o = d.options;
  const std::size_t bytes = frameChunkBytes(o.width, o.height, o.cameras);
  auto loaned = d.frames.loan(static_cast<std::uint32_t>(bytes), alignof(FrameHeader));
  if (loaned.has_error()) {
    ++d.stats.frames_not_loaned;
    return {};
  }
  d.loaned = loaned.value();
  auto* pixels = static_cast<std::uint8_t*>(d.loaned) + sizeof(FrameHeader);
  return {pixels, bytes - sizeof(FrameHeader)};
}

void SensorPublisher::publishFrame(std::int64_t t_ns) {
  Impl& d = *impl_;
  if (d.loaned == nullptr) return;
  auto* header = new (d.loaned) FrameHeader{};
  header->sequence = d.frame_sequence++;
  header->t_ns = t_ns;
  header->captured_steady_ns = steadyNowNs();
  header->width = d.options.width;
  header->height = d.options.height;
  header->cameras = d.options.cameras;
  d.frames.publish(d.loaned);
  d.loaned = nullptr;
  ++d.stats.frames;
}

void SensorPublisher::publishImu(const dataset::ImuSample& sample) {
  Impl& d = *impl_;
  auto loaned = d.imu.loan(sizeof(ImuMessage), alignof(ImuMessage));
  if (loaned.has_error()) {
    ++d.stats.imu_not_loaned;
    return;
  }
  auto* message = new (loaned.value()) ImuMessage{};
  message->sequence = d.imu_sequence++;
  message->t_ns = sample.t_ns;
  message->captured_steady_ns = steadyNowNs();
  for (int k = 0; k < 3; ++k) {
    message->gyro_s[k] = sample.gyro_s[k];
    message->accel_s[k] = sample.accel_s[k];
  }
  d.imu.publish(loaned.value());
  ++d.stats.imu_samples;
}

void SensorPublisher::publishEndOfStream() {
  Impl& d = *impl_;
  d.giveBackLoan();
  auto loaned = d.frames.loan(sizeof(FrameHeader), alignof(FrameHeader));
  if (loaned.has_error()) {
    ++d.stats.frames_not_loaned;
    return;
  }
  auto* header = new (loaned.value()) FrameHeader{};
  header->sequence = d.frame_sequence++;
  header->captured_steady_ns = steadyNowNs();
  header->flags = kEndOfStream;
  d.frames.publish(loaned.value());
}

bool SensorPublisher::hasSubscribers() const {
  return impl_->frames.hasSubscribers();
}

const SensorPublisherStats& SensorPublisher::stats() const {
  return impl_->stats;
}

}  // namespace cvislam::agent::live

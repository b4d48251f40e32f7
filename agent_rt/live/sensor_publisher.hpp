// The driver's side of the live sensor topics (sensor_topics.hpp): what a camera/IMU driver process uses to
// publish onto the topics of one stream, and what cvislam_sensor_publisher plays recordings through. Images are
// written straight into loaned shared memory, which the agent then reads in place.
//
// The process must be attached to an iox-roudi first (attachToExternalRouDi in agent_rt/ipc/embedded_roudi.hpp).
// iceoryx headers stay in the .cpp.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string>

#include "common/core/result.hpp"
#include "common/dataset/types.hpp"

namespace cvislam::agent::live {

struct SensorPublisherOptions {
  std::string stream;  // the NAME of `cvislam_agent --live NAME`
  std::uint32_t width = 752;
  std::uint32_t height = 480;
  std::uint32_t cameras = 1;  // 2: every frame is a stereo pair

  [[nodiscard]] Status validate() const;
};

struct SensorPublisherStats {
  std::uint64_t frames = 0;
  std::uint64_t imu_samples = 0;
  // Shared memory had no chunk to lend (every chunk of the pool held by slow readers): the message was not sent.
  std::uint64_t frames_not_loaned = 0;
  std::uint64_t imu_not_loaned = 0;
};

class SensorPublisher {
 public:
  static Result<std::unique_ptr<SensorPublisher>> create(const SensorPublisherOptions& options);
  ~SensorPublisher();
  SensorPublisher(const SensorPublisher&) = delete;
  SensorPublisher& operator=(const SensorPublisher&) = delete;

  // The pixels of the next frame to write (cam0's rows, then cam1's), in a loaned chunk; empty when no chunk could
  // be loaned (counted in the stats). A frame loaned and not published is given back by the next loan.
  std::span<std::uint8_t> loanFrame();
  // Publishes the loaned frame, taken at `t_ns` on the camera's clock.
  void publishFrame(std::int64_t t_ns);
  void publishImu(const dataset::ImuSample& sample);
  // Tells the agent that the stream ended.
  void publishEndOfStream();

  // Whether an agent has subscribed to the frames.
  [[nodiscard]] bool hasSubscribers() const;
  [[nodiscard]] const SensorPublisherStats& stats() const;

 private:
  struct Impl;
  explicit SensorPublisher(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace cvislam::agent::live

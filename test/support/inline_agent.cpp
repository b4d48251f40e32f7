#include "test/support/inline_agent.hpp"

#include <algorithm>

#include "agent_rt/runtime/sensor_setup.hpp"

namespace cvislam::test {

Result<std::unique_ptr<InlineAgent>> InlineAgent::create(const dataset::EurocSequence& sequence, bool stereo,
                                                         agent::TrackerOptions tracker_options,
                                                         agent::MapperOptions mapper_options) {
  auto setup = agent::makeSensorSetup(sequence, stereo, 1.0);
  if (!setup) return setup.error();
  agent::applySensorSetup(*setup, tracker_options, mapper_options);
  const camera::CameraModel* right = setup->right ? &*setup->right : nullptr;
  std::unique_ptr<InlineAgent> agent(new InlineAgent(sequence, stereo));
  auto tracker = agent::Tracker::create(tracker_options, setup->left, right, setup->T_s_c);
  if (!tracker) return tracker.error();
  auto mapper = agent::Mapper::create(mapper_options, setup->left, right, setup->T_s_c, setup->T_c0_c1);
  if (!mapper) return mapper.error();
  agent->tracker_ = std::move(tracker.value());
  agent->mapper_ = std::move(mapper.value());
  agent->snapshot_ = std::make_unique<agent::MapSnapshotMessage>();
  agent->frames_ = agent::framesToRun(sequence, stereo);
  const auto& c0 = sequence.cam0().calibration;
  const auto pixels = static_cast<std::size_t>(c0.width) * static_cast<std::size_t>(c0.height);
  agent->left_.resize(pixels);
  if (stereo) agent->right_.resize(pixels);
  agent->input_.width = c0.width;
  agent->input_.height = c0.height;
  return agent;
}

Status InlineAgent::load(std::size_t i) {
  const dataset::RigFrame& frame = frames_.at(i);
  if (Status s = sequence_.loadImageInto(0, frame.cam0, left_); !s.ok()) return s;
  if (stereo_) {
    if (Status s = sequence_.loadImageInto(1, *frame.cam1, right_); !s.ok()) return s;
  }
  input_.t_ns = frame.t_ns;
  input_.left = left_;
  input_.right = stereo_ ? std::span<const std::uint8_t>(right_) : std::span<const std::uint8_t>();
  input_.imu = agent::imuCovering(sequence_.imu(), previous_t_ns_ < 0 ? frame.t_ns : previous_t_ns_, frame.t_ns);
  previous_t_ns_ = frame.t_ns;
  return Status::Ok();
}

void InlineAgent::coverCamera() {
  std::fill(left_.begin(), left_.end(), std::uint8_t{0});
  std::fill(right_.begin(), right_.end(), std::uint8_t{0});
}

void InlineAgent::offsetAccelerometer(const Eigen::Vector3d& offset_s) {
  disturbed_imu_.assign(input_.imu.begin(), input_.imu.end());
  for (dataset::ImuSample& sample : disturbed_imu_) sample.accel_s += offset_s;
  input_.imu = disturbed_imu_;
}

void InlineAgent::answerKeyframe() {
  if (mapping_frames_per_keyframe_ <= 0) {
    if (!sink_.published) return;
    sink_.published = false;
    process(*sink_.message);
    return;
  }
  // The slow mapper: the tracker reuses its message, so the queue keeps copies.
  if (sink_.published) {
    sink_.published = false;
    queue_.push_back(std::make_unique<agent::KeyframeMessage>(*sink_.message));
  }
  if (queue_.empty()) return;
  if (++mapping_busy_frames_ < mapping_frames_per_keyframe_) return;
  mapping_busy_frames_ = 0;
  process(*queue_.front());
  queue_.pop_front();
}

void InlineAgent::process(const agent::KeyframeMessage& message) {
  if (before_keyframe_) before_keyframe_(*mapper_);
  const auto report = mapper_->process(message, *snapshot_, delta_.get());
  const bool processed = report.ok();
  if (processed && after_keyframe_) after_keyframe_(*report);
  if (delta_ && delta_sink_) {
    delta_->sequence = delta_sequence_++;
    delta_sink_(*delta_);
  }
  if (processed) tracker_->adoptSnapshot(snapshot_.get());
}

}  // namespace cvislam::test

#include "test/support/inline_agent.hpp"

#include <algorithm>

namespace cvislam::test {

Result<std::unique_ptr<InlineAgent>> InlineAgent::create(const dataset::EurocSequence& sequence, bool stereo,
                                                         agent::TrackerOptions tracker_options,
                                                         agent::MapperOptions mapper_options) {
  if (stereo && sequence.cam1() == nullptr) return Error{ErrorCode::kInvalidArgument, "stereo needs cam1"};
  if (!sequence.imuCalibration()) return Error{ErrorCode::kInvalidArgument, "the sequence has no IMU calibration"};
  const auto& c0 = sequence.cam0().calibration;
  auto left = camera::CameraModel::create(c0);
  if (!left) return left.error();
  std::optional<camera::CameraModel> right;
  geometry::SE3d T_c0_c1;
  if (stereo) {
    auto r = camera::CameraModel::create(sequence.cam1()->calibration);
    if (!r) return r.error();
    right.emplace(*r);
    T_c0_c1 = c0.T_b_c.inverse() * sequence.cam1()->calibration.T_b_c;
  }
  const geometry::SE3d T_s_c = sequence.imuCalibration()->T_b_i.inverse() * c0.T_b_c;
  tracker_options.noise = imu::ImuNoise::fromCalibration(*sequence.imuCalibration());
  mapper_options.ba.noise = tracker_options.noise;
  mapper_options.ba.intrinsics = {c0.fx, c0.fy, c0.cx, c0.cy};
  if (stereo) mapper_options.imu_init_keyframes = std::min(mapper_options.imu_init_keyframes, 10);

  std::unique_ptr<InlineAgent> agent(new InlineAgent(sequence, stereo));
  auto tracker = agent::Tracker::create(tracker_options, *left, right ? &*right : nullptr, T_s_c);
  if (!tracker) return tracker.error();
  auto mapper = agent::Mapper::create(mapper_options, *left, right ? &*right : nullptr, T_s_c, T_c0_c1);
  if (!mapper) return mapper.error();
  agent->tracker_ = std::move(tracker.value());
  agent->mapper_ = std::move(mapper.value());
  agent->snapshot_ = std::make_unique<agent::MapSnapshotMessage>();
  for (const dataset::RigFrame& f : sequence.rigFrames()) {
    if (!stereo || f.cam1) agent->frames_.push_back(f);
  }
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
  const auto& imu = sequence_.imu();
  const std::int64_t from = previous_t_ns_ < 0 ? frame.t_ns : previous_t_ns_;
  auto first = std::upper_bound(imu.begin(), imu.end(), from,
                                [](std::int64_t t, const dataset::ImuSample& s) { return t < s.t_ns; });
  if (first != imu.begin()) --first;
  auto last = std::lower_bound(imu.begin(), imu.end(), frame.t_ns,
                               [](const dataset::ImuSample& s, std::int64_t t) { return s.t_ns < t; });
  if (last != imu.end()) ++last;
  input_.t_ns = frame.t_ns;
  input_.left = left_;
  input_.right = stereo_ ? std::span<const std::uint8_t>(right_) : std::span<const std::uint8_t>();
  input_.imu =
      first < last ? std::span(&*first, static_cast<std::size_t>(last - first)) : std::span<const dataset::ImuSample>();
  previous_t_ns_ = frame.t_ns;
  return Status::Ok();
}

void InlineAgent::answerKeyframe() {
  if (!sink_.published) return;
  sink_.published = false;
  if (mapper_->process(*sink_.message, *snapshot_).ok()) tracker_->adoptSnapshot(snapshot_.get());
}

}  // namespace cvislam::test

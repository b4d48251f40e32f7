#include "test/server_cloud/link_messages.hpp"

#include <array>
#include <cmath>
#include <random>

#include "common/dataset/euroc_calibration.hpp"
#include "proto/wire/wire.hpp"

namespace cvislam::server::test {

std::int64_t keyframeTime(std::uint32_t counter) {
  return kFirstKeyframeNs + static_cast<std::int64_t>(counter) * kKeyframeSpacingNs;
}

v1::Hello makeHello(const std::string& mission, std::uint32_t agent_id, std::uint64_t session, bool stereo) {
  v1::Hello hello;
  hello.set_protocol_version(wire::kProtocolVersion);
  hello.set_mission(mission);
  hello.set_agent_id(agent_id);
  hello.set_session(session);
  hello.set_mode(stereo ? v1::SENSOR_MODE_STEREO : v1::SENSOR_MODE_MONO);
  hello.set_uses_imu(true);
  hello.set_software("server test");
  // EuRoC's cameras and IMU (body = IMU frame, so T_s_c is the camera's T_BS).
  const dataset::CameraCalibration cam0 = dataset::eurocCam0();
  wire::toProto(cam0, cam0.T_b_c, hello.mutable_cam0());
  if (stereo) {
    const dataset::CameraCalibration cam1 = dataset::eurocCam1();
    wire::toProto(cam1, cam1.T_b_c, hello.mutable_cam1());
  }
  const dataset::ImuCalibration imu = dataset::eurocImu();
  wire::toProto(imu::ImuNoise::fromCalibration(imu), imu.rate_hz, hello.mutable_imu());
  return hello;
}

v1::AgentUplink helloMessage(const std::string& mission, std::uint32_t agent_id, std::uint64_t session) {
  v1::AgentUplink message;
  *message.mutable_hello() = makeHello(mission, agent_id, session);
  return message;
}

v1::KeyframeState makeState(std::uint32_t counter) {
  const double c = counter;
  const double yaw = 0.05 * c;
  v1::KeyframeState state;
  state.set_counter(counter);
  v1::Pose* pose = state.mutable_t_w_s();
  pose->set_px(0.1 * c);
  pose->set_py(0.02 * c);
  pose->set_pz(1.0);
  pose->set_qx(0.0F);
  pose->set_qy(0.0F);
  pose->set_qz(static_cast<float>(std::sin(yaw / 2)));
  pose->set_qw(static_cast<float>(std::cos(yaw / 2)));
  for (float v : {1.0F, 0.1F * static_cast<float>(counter), 0.0F}) state.add_v_w(v);
  for (float b : {0.001F, 0.002F, 0.003F}) state.add_bias_gyro(b);
  for (float b : {0.01F, 0.02F, 0.03F}) state.add_bias_accel(b);
  return state;
}

v1::Keyframe makeKeyframe(std::uint32_t counter, std::uint32_t agent_map, std::optional<std::uint32_t> imu_from) {
  v1::Keyframe kf;
  kf.set_counter(counter);
  kf.set_agent_map(agent_map);
  kf.set_t_ns(keyframeTime(counter));
  *kf.mutable_state() = makeState(counter);

  std::mt19937 rng(counter);  // descriptors differ per keyframe, and are the same on every run
  std::uniform_int_distribution<int> byte(0, 255);
  v1::Keypoints* kp = kf.mutable_keypoints();
  std::string octave;
  std::string angle;
  for (int i = 0; i < kKeypointsPerKeyframe; ++i) {
    const int column = i % 10;
    const int row = i / 10;
    kp->add_xy(20.0F + static_cast<float>(column) * 70.0F);  // x in [20, 650]
    kp->add_xy(20.0F + static_cast<float>(row) * 100.0F);    // y in [20, 420]
    octave.push_back(static_cast<char>(i % 4));
    angle.push_back(static_cast<char>((i * 5) % 256));
    std::array<std::uint8_t, 32> descriptor{};
    for (auto& b : descriptor) b = static_cast<std::uint8_t>(byte(rng));
    wire::packDescriptor(descriptor.data(), kp->mutable_descriptors());
  }
  kp->set_octave(octave);
  kp->set_angle(angle);

  if (imu_from) {
    kf.set_imu_from(*imu_from);
    const std::int64_t t0 = keyframeTime(*imu_from);
    const std::int64_t t1 = keyframeTime(counter);
    v1::ImuSamples* imu = kf.mutable_imu();
    for (std::int64_t t = t0; t <= t1; t += kImuPeriodNs) {
      imu->add_dt_ns(t == t0 ? t0 - t1 : kImuPeriodNs);  // the first relative to this keyframe's time
      for (float g : {0.01F, -0.02F, 0.05F}) imu->add_gyro(g);
      for (float a : {0.1F, 0.0F, 9.81F}) imu->add_accel(a);
    }
  }
  return kf;
}

v1::MapPoint makePoint(std::uint32_t counter, std::uint32_t reference_keyframe) {
  v1::MapPoint p;
  p.set_counter(counter);
  p.set_reference_keyframe(reference_keyframe);
  for (float v : {0.1F * static_cast<float>(counter), 2.0F, 5.0F}) p.add_p_w(v);
  std::array<std::uint8_t, 32> orb{};
  for (int b = 0; b < 32; ++b) orb[static_cast<std::size_t>(b)] = static_cast<std::uint8_t>((counter * 7 + b) % 256);
  wire::packDescriptor(orb.data(), p.mutable_orb());
  p.set_octave(1);
  return p;
}

void addObservations(v1::MapBatch& batch, std::uint32_t keyframe, const std::vector<std::uint32_t>& keypoint,
                     const std::vector<std::uint32_t>& point) {
  v1::Observations* o = batch.add_observations();
  o->set_keyframe(keyframe);
  for (std::uint32_t k : keypoint) o->add_keypoint(k);
  for (std::uint32_t p : point) o->add_point(p);
}

v1::MapBatch makeKeyframeBatch(std::uint64_t sequence, std::uint32_t first, std::uint32_t count) {
  v1::MapBatch batch;
  batch.set_sequence(sequence);
  batch.set_sensor_time_ns(keyframeTime(first + count - 1));
  for (std::uint32_t c = first; c < first + count; ++c) {
    *batch.add_keyframes() = makeKeyframe(c, 0, c > 0 ? std::optional<std::uint32_t>(c - 1) : std::nullopt);
    *batch.add_points() = makePoint(c, c);
    addObservations(batch, c, {0}, {c});
    if (c > first) addObservations(batch, c - 1, {1}, {c});
  }
  return batch;
}

v1::AgentUplink batchMessage(const v1::MapBatch& batch) {
  v1::AgentUplink message;
  *message.mutable_batch() = batch;
  return message;
}

v1::AgentUplink goodbyeMessage(bool end_of_mission) {
  v1::AgentUplink message;
  message.mutable_goodbye()->set_end_of_mission(end_of_mission);
  return message;
}

}  // namespace cvislam::server::test

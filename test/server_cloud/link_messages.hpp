// Hand-made cvislam.v1 agent-link messages for the server tests: a valid Hello of a EuRoC-like monocular-inertial
// agent (752x480 camera, 200 Hz IMU), and valid keyframes, points and observations to build MapBatch messages
// from. Tests break one field of a valid message to check one rule of the server.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "cvislam/v1/agent_link.pb.h"

namespace cvislam::server::test {

inline constexpr std::uint32_t kImageWidth = 752;
inline constexpr std::uint32_t kImageHeight = 480;
inline constexpr int kKeypointsPerKeyframe = 50;
inline constexpr std::int64_t kImuPeriodNs = 5'000'000;          // 200 Hz
inline constexpr std::int64_t kKeyframeSpacingNs = 100'000'000;  // 0.1 s: 21 IMU samples per keyframe
inline constexpr std::int64_t kFirstKeyframeNs = 1'000'000'000;

// The time of keyframe `counter` when keyframes are kKeyframeSpacingNs apart.
std::int64_t keyframeTime(std::uint32_t counter);

// A Hello of an agent with EuRoC's sensors: cam0 (and cam1 when `stereo`) and the IMU.
v1::Hello makeHello(const std::string& mission, std::uint32_t agent_id, std::uint64_t session, bool stereo = false);
v1::AgentUplink helloMessage(const std::string& mission, std::uint32_t agent_id, std::uint64_t session);

// The state of keyframe `counter`: a pose that moves along x and turns about z, unit quaternion, a velocity
// and small biases, all different per counter.
v1::KeyframeState makeState(std::uint32_t counter);

// A keyframe of `agent_map` at keyframeTime(counter) with kKeypointsPerKeyframe keypoints inside the image.
// With `imu_from`, it carries the 200 Hz IMU samples from that keyframe's time to its own (both included).
v1::Keyframe makeKeyframe(std::uint32_t counter, std::uint32_t agent_map = 0,
                          std::optional<std::uint32_t> imu_from = std::nullopt);

v1::MapPoint makePoint(std::uint32_t counter, std::uint32_t reference_keyframe);

// `keypoint[i]` of `keyframe` observes point `point[i]`.
void addObservations(v1::MapBatch& batch, std::uint32_t keyframe, const std::vector<std::uint32_t>& keypoint,
                     const std::vector<std::uint32_t>& point);

// A batch with keyframes [first, first + count) of agent map 0, each IMU-linked to the one before (the first
// to first - 1 when first > 0), and one point per keyframe referenced and observed by it (point counter =
// keyframe counter), also observed by the keyframe before it in the batch when there is one.
v1::MapBatch makeKeyframeBatch(std::uint64_t sequence, std::uint32_t first, std::uint32_t count);

v1::AgentUplink batchMessage(const v1::MapBatch& batch);
v1::AgentUplink goodbyeMessage(bool end_of_mission);

}  // namespace cvislam::server::test

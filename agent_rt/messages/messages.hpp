// The messages between the agent's tracking and mapping threads. They travel through iceoryx shared memory,
// zero-copy: the sender loans a chunk, writes the message in place and publishes; the receiver reads the same
// memory. So every message is fixed-size and trivially copyable (plain arrays, no Eigen, no pointers), with
// capacities from CMake (agent_rt/map/capacities.hpp).
//
//   tracking --KeyframeMessage-->  mapping    a new keyframe: its keypoints, descriptors, the map points
//                                             tracking matched, the IMU since the previous keyframe and, in
//                                             stereo, the second camera's image (mapping does the stereo work)
//   mapping  --MapSnapshotMessage--> tracking the refined local map after local BA: points with descriptors,
//                                             keyframe states, and any change of the world frame (IMU
//                                             initialisation rescales and rotates it)
//   mapping  --MapDeltaMessage-->   link     what changed in the local map with this keyframe: the keyframe in
//                                             full, the points made, every structural change in order (map
//                                             events), and the states and positions of everything in the map
//   link     --AnchorMessage-->     mapping  what the server sends down, decoded and checked: its covisible map
//                                             (keyframes and points that local BA holds fixed and tracking can
//                                             match) and its refined states of the agent's own keyframes
//
// Tracking never waits on mapping: it takes the newest snapshot when one is there and keeps using the one it
// holds otherwise.
#pragma once

#include <array>
#include <cstdint>
#include <type_traits>

#include "agent_rt/map/capacities.hpp"
#include "agent_rt/map/map_events.hpp"
#include "common/core/ids.hpp"

namespace cvislam::agent {

// IMU samples one keyframe message carries: the samples since the previous keyframe (1024 = 5 s at 200 Hz).
inline constexpr std::size_t kMaxImuSamplesPerKeyframe = 1024;
// The IMU kept from before a stream's first frame (the feeds) and before each keyframe (tracking): when mapping
// estimates the camera-IMU time offset it moves keyframes to their images' times, which a negative offset puts up
// to this long before their stamps (imu.max_time_offset_s's default; larger offsets keep the camera's time).
inline constexpr std::int64_t kImuKeptBeforeStampNs = 100'000'000;

struct PoseMsg {
  std::array<double, 3> p{};            // translation
  std::array<double, 4> q{0, 0, 0, 1};  // rotation quaternion x y z w
};

struct KeyframeStateMsg {
  KeyframeId id;
  std::int64_t t_ns = 0;
  std::int64_t time_correction_ns = 0;  // the correction to the calibrated camera-IMU time offset t_ns carries
  PoseMsg T_w_s;
  std::array<double, 3> v_w{};
  std::array<double, 6> bias{};  // b_g, b_a
};

struct KeypointMsg {
  float x = 0.0F;  // distorted pixel, level-0 coordinates
  float y = 0.0F;
  float response = 0.0F;
  float angle_deg = 0.0F;
  std::uint8_t octave = 0;
};

struct ImuSampleMsg {
  std::int64_t t_ns = 0;
  std::array<double, 3> gyro{};
  std::array<double, 3> accel{};
};

enum class KeyframeKind : std::uint8_t {
  kTracked = 0,  // tracked against the map; `matched` links keypoints to map points
  kNewMap = 1,   // the first keyframe of a new map (start, or tracking lost beyond relocalisation)
};

struct KeyframeMessage {
  std::uint64_t sequence = 0;          // per agent, from 0: mapping spots lost messages by gaps
  std::int64_t publish_steady_ns = 0;  // steady clock at publish, for the publish-to-receive latency
  std::uint32_t map_epoch = 0;         // the world frame the state is expressed in (see MapSnapshotMessage)
  KeyframeKind kind = KeyframeKind::kTracked;
  // A new map that continues the old one's metric, gravity-aligned world frame (the IMU was initialised):
  // the state's velocity and biases hold, and the IMU needs no new initialisation.
  std::uint8_t continues_frame = 0;
  KeyframeStateMsg state;
  // The correction to the calibrated camera-IMU time offset that state.t_ns already carries (the estimate tracking
  // had from the last snapshot): local BA shifts the pose by the rest of the estimated offset.
  std::int64_t time_correction_ns = 0;
  std::uint16_t keypoint_count = 0;
  std::array<KeypointMsg, kMaxKeypointsPerKeyframe> keypoints{};
  std::array<std::array<std::uint8_t, 32>, kMaxKeypointsPerKeyframe> descriptors{};
  std::array<MapPointId, kMaxKeypointsPerKeyframe> matched{};  // valid where has_match
  std::array<std::uint8_t, kMaxKeypointsPerKeyframe> has_match{};
  // IMU from the previous keyframe's time to this one's (inclusive of one sample either side), whatever tracking made
  // of it: mapping integrates the link itself and finds a gap or a missing start on its own, and, with the time
  // offset estimated, keeps the samples so that a link can be made once the keyframes are re-timed into them.
  std::uint32_t imu_count = 0;
  std::array<ImuSampleMsg, kMaxImuSamplesPerKeyframe> imu{};
  // The second camera's image at the same time, when stereo.
  std::uint16_t right_width = 0;
  std::uint16_t right_height = 0;
  std::array<std::uint8_t, kMaxImagePixels> right_pixels{};
};

struct MapPointMsg {
  MapPointId id;
  std::array<double, 3> p_w{};
  std::array<std::uint8_t, 32> descriptor{};
  std::uint8_t octave = 0;  // pyramid level it was seen at, for the search radius and pixel noise
};

// One observation of a snapshot point by a window keyframe: the undistorted cam0 keypoint and its noise.
struct KeyframeObservationMsg {
  float u = 0.0F;
  float v = 0.0F;
  float sigma_px = 1.0F;
  std::uint32_t point = 0;  // index into MapSnapshotMessage::points
};

// A keyframe of tracking's motion-only BA window, with what it observes of the snapshot's points.
struct WindowKeyframeMsg {
  std::uint16_t keyframe = 0;  // index into MapSnapshotMessage::keyframes
  std::uint16_t observation_count = 0;
  std::array<KeyframeObservationMsg, kMaxKeypointsPerKeyframe> observations{};
};

struct MapSnapshotMessage {
  std::uint64_t sequence = 0;
  std::int64_t publish_steady_ns = 0;
  // The world frame. It changes when IMU initialisation rescales the map and rotates it to gravity (and when
  // a new map starts): states of epoch e map into epoch e+1 by p' = s R p + t, v' = s R v.
  std::uint32_t map_epoch = 0;
  std::uint32_t map_id = 0;  // counts new maps
  double epoch_scale = 1.0;
  PoseMsg epoch_transform;  // R, t of the change into this epoch
  std::uint8_t imu_initialised = 0;
  // The estimated correction to the calibrated camera-IMU time offset (0 while not estimated): tracking adds it to
  // the frames' times from the next frame on.
  std::int64_t time_correction_ns = 0;
  KeyframeId newest_keyframe;  // the newest keyframe mapping has processed
  // Keyframe messages mapping has taken, as the sequence of the last one + 1: tracking's count of keyframes
  // published and not yet answered (its back-off while mapping is busy) is its own sequence minus this.
  std::uint64_t keyframes_taken = 0;
  std::uint16_t keyframe_count = 0;
  std::array<KeyframeStateMsg, kMaxKeyframes> keyframes{};
  std::array<std::uint8_t, kMaxKeyframes> keyframe_is_anchor{};  // the server's keyframes (another agent's, or
                                                                 // this agent's own from long ago)
  std::uint32_t point_count = 0;
  std::array<MapPointMsg, kMaxMapPoints> points{};
  // The agent's newest own keyframes, oldest first, for motion-only BA over the newest n keyframes.
  std::uint16_t window_count = 0;
  std::array<WindowKeyframeMsg, kMaxMotionBaKeyframes> window{};
};

// Structural changes one keyframe may cause that a delta carries; beyond it they are counted as lost.
inline constexpr std::size_t kMaxMapEventsPerKeyframe = 4096;

// A map point of the local map as the link sees it: id and world position.
struct DeltaPointMsg {
  MapPointId id;
  std::array<float, 3> p_w{};
};

// A map point made with this keyframe, in full.
struct NewPointMsg {
  MapPointId id;
  KeyframeId reference;  // the keyframe whose keypoint made it
  std::array<float, 3> p_w{};
  std::array<std::uint8_t, 32> descriptor{};
  std::uint8_t octave = 0;
};

// Mapping -> link, once per processed keyframe, after local BA. One message carries structure and states
// together, so that the link never pairs a keyframe with a state from another world frame (the frame changes
// when the IMU is initialised).
struct MapDeltaMessage {
  std::uint64_t sequence = 0;  // per agent, from 0: the link spots a lost delta by a gap
  std::int64_t publish_steady_ns = 0;
  std::uint32_t map_id = 0;  // the agent's map now (counts new maps)
  std::uint32_t map_epoch = 0;
  // The map's world frame is final: metric and gravity-aligned (the IMU is initialised; vision only: the map
  // has started). Until then nothing of this map leaves the agent.
  std::uint8_t ready = 0;
  std::int64_t t_ns = 0;  // the keyframe's time
  // The keyframe just processed, in full, when it is still in the map.
  std::uint8_t has_keyframe = 0;
  // The keyframe's state is tracking's: its local BA runs after this delta went (the link sends the keyframe
  // sooner), and a later delta carries the refined state.
  std::uint8_t keyframe_before_local_ba = 0;
  std::uint32_t keyframe_map_id = 0;
  KeyframeStateMsg keyframe;
  std::uint8_t has_imu_link = 0;  // `imu` joins `imu_from` (the previous keyframe of this map) to this one
  KeyframeId imu_from;
  std::uint16_t keypoint_count = 0;
  std::array<KeypointMsg, kMaxKeypointsPerKeyframe> keypoints{};
  std::array<std::array<std::uint8_t, 32>, kMaxKeypointsPerKeyframe> descriptors{};
  std::array<std::uint8_t, kMaxKeypointsPerKeyframe> has_right{};
  std::array<std::array<float, 2>, kMaxKeypointsPerKeyframe> right_px{};  // cam1, undistorted to its pinhole
  std::array<std::uint8_t, kMaxKeypointsPerKeyframe> right_octave{};
  std::array<std::uint8_t, kMaxKeypointsPerKeyframe> has_observation{};  // the keyframe's links, as they are now
  std::array<MapPointId, kMaxKeypointsPerKeyframe> observation{};
  std::uint32_t imu_count = 0;
  std::array<ImuSampleMsg, kMaxImuSamplesPerKeyframe> imu{};
  // Points made while processing this keyframe that are still in the map.
  std::uint16_t new_point_count = 0;
  std::array<NewPointMsg, kMaxKeypointsPerKeyframe> new_points{};
  // Every structural change, in the order it happened.
  std::uint16_t event_count = 0;
  std::uint32_t events_lost = 0;
  std::array<MapEvent, kMaxMapEventsPerKeyframe> events{};
  // Everything in the local map now: keyframe states and point positions.
  std::uint16_t keyframe_count = 0;
  std::array<KeyframeStateMsg, kMaxKeyframes> keyframes{};
  std::uint32_t point_count = 0;
  std::array<DeltaPointMsg, kMaxMapPoints> points{};
};

// ---- The server's covisible map (the downlink), as the link decoded and checked it ----
// Capacities of one message; a server message beyond them is refused whole (the server's K is 10, and its byte
// budget keeps a message to a few thousand points).
inline constexpr std::size_t kMaxAnchorKeyframesPerMessage = 32;
inline constexpr std::size_t kMaxAnchorPointsPerMessage = 8192;

// A keypoint of an anchor keyframe observing an anchor point: normalised image coordinates (x/z, y/z) of an
// ideal pinhole, so that the keyframe's own camera does not matter.
struct AnchorObservationMsg {
  float x = 0.0F;
  float y = 0.0F;
  MapPointId point;
  std::uint8_t octave = 0;
};

struct AnchorKeyframeMsg {
  KeyframeId id;
  std::int64_t t_ns = 0;
  PoseMsg T_w_c;  // its camera's pose in this agent's world frame
  std::uint16_t observation_count = 0;
  std::array<AnchorObservationMsg, kMaxKeypointsPerKeyframe> observations{};
};

struct AnchorPointMsg {
  MapPointId id;
  std::array<double, 3> p_w{};
  std::array<std::uint8_t, 32> descriptor{};
  std::uint8_t octave = 0;
};

struct AnchorPoseUpdateMsg {
  KeyframeId id;
  PoseMsg T_w_c;
};

struct AnchorPointUpdateMsg {
  MapPointId id;
  std::array<double, 3> p_w{};
};

// Corrections of the agent's own keyframes one message carries; beyond it the oldest are left out (mapping
// applies them only to keyframes still in its local map, the newest ones).
inline constexpr std::size_t kMaxAnchorCorrectionsPerMessage = 1024;

// Link -> mapping: one downlink message's covisible map and corrections. Keyframes and points come in full once
// while they are selected; afterwards only updates of what moved. `selected` is the server's current choice,
// best first: the agent holds exactly the selected keyframes it has received, and lets go of the others (the
// server sends a keyframe again in full when it is selected again).
struct AnchorMessage {
  std::uint32_t stream = 0;    // the link's stream (connection) count: sequences restart on a new stream
  std::uint64_t sequence = 0;  // the downlink message's sequence on its stream
  std::int64_t publish_steady_ns = 0;
  std::uint8_t has_covisible = 0;  // 0: corrections only (selection, keyframes, points and updates are empty)
  std::uint32_t agent_map = 0;     // the agent map whose world frame all of this is in
  std::uint16_t selected_count = 0;
  std::array<KeyframeId, kMaxAnchorKeyframesPerMessage> selected{};
  std::uint16_t keyframe_count = 0;
  std::array<AnchorKeyframeMsg, kMaxAnchorKeyframesPerMessage> keyframes{};
  std::uint32_t point_count = 0;
  std::array<AnchorPointMsg, kMaxAnchorPointsPerMessage> points{};
  std::uint16_t keyframe_update_count = 0;
  std::array<AnchorPoseUpdateMsg, kMaxAnchorKeyframesPerMessage> keyframe_updates{};
  std::uint32_t point_update_count = 0;
  std::array<AnchorPointUpdateMsg, kMaxAnchorPointsPerMessage> point_updates{};
  // The server's states of the agent's own keyframes (after global BA, a loop closure, a merge), in the
  // agent's world frame.
  std::uint16_t correction_count = 0;
  std::array<KeyframeStateMsg, kMaxAnchorCorrectionsPerMessage> corrections{};
};

static_assert(std::is_trivially_copyable_v<KeyframeMessage>);
static_assert(std::is_trivially_copyable_v<AnchorMessage>);
static_assert(std::is_trivially_copyable_v<MapSnapshotMessage>);
static_assert(std::is_trivially_copyable_v<MapDeltaMessage>);

}  // namespace cvislam::agent

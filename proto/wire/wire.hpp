// Conversions between the project's types and the cvislam.v1 wire messages, shared by the agent's link and the
// server. Decoding validates: a non-finite value, a quaternion that is not unit length or a wrong number of
// values is an error that names the field, never a crash.
#pragma once

#include <array>
#include <cstdint>
#include <string>

#include <Eigen/Core>

#include "common/core/result.hpp"
#include "common/dataset/types.hpp"
#include "common/geometry/lie.hpp"
#include "common/imu/preintegration.hpp"

namespace cvislam::v1 {
class MapBatch;
class CovisibleMap;
class Pose;
class KeyframeState;
class CameraCalibration;
class ImuCalibration;
}  // namespace cvislam::v1

namespace google::protobuf {
template <typename T>
class RepeatedField;
}

namespace cvislam::wire {

// The protocol this build speaks; a Hello with another version is refused.
inline constexpr std::uint32_t kProtocolVersion = 1;
// Scale-out: when a replica refuses an agent's Hello because another replica serves its mission, the stream's
// trailing metadata names that replica's host:port under this key, and the agent connects there next.
inline constexpr const char* kOwnerMetadataKey = "cvislam-owner";

// What one covisible map (downlink) may carry at most: the server never sends more, the agent refuses more.
inline constexpr int kMaxCovisibleKeyframesPerMessage = 32;  // selected, in full, and pose updates, each
inline constexpr int kMaxCovisiblePointsPerMessage = 8192;   // in full, and position updates, each
inline constexpr std::uint32_t kMaxOctave = 31;              // pyramid levels, as ingest accepts them

// Physical bounds on what peers send. Values outside them are finite but absurd (a focal length of 1e-300 px, a
// pose 1e308 m away, a noise density of 1e300) and would become inf or NaN in maps other agents share and in their
// optimisation, so they are refused like non-finite ones. Each is far beyond any real robot's.
inline constexpr double kMaxPositionM = 1e6;  // poses: within 1000 km of their frame's origin
// Map points: a point triangulated from nearly parallel rays may lie absurdly far and still be what the agent's
// map holds (1.2e8 m was seen on real EuRoC data); the bound only keeps its products with poses finite.
inline constexpr double kMaxPointDistanceM = 1e12;
inline constexpr double kMaxSpeedMps = 1e3;
inline constexpr double kMaxGyroBiasRadps = 10.0;
inline constexpr double kMaxAccelBiasMps2 = 100.0;
inline constexpr double kMinFocalPx = 1.0;
inline constexpr double kMaxFocalPx = 1e5;
inline constexpr double kMaxDistortion = 10.0;  // |coefficient|
inline constexpr double kMaxCameraToImuM = 10.0;
inline constexpr double kMaxRateHz = 1e4;  // camera and IMU
inline constexpr double kMinNoise = 1e-9;  // IMU noise densities and random walks
inline constexpr double kMaxNoise = 10.0;

// A position within `limit_m` of the origin (finite): OK, else an error naming `what`.
Status checkPosition(const Eigen::Vector3d& p, const std::string& what, double limit_m = kMaxPositionM);

void toProto(const geometry::SE3d& T, v1::Pose* out);
// `what` names the field in errors ("keyframe 3:12 T_w_s").
Result<geometry::SE3d> fromProto(const v1::Pose& pose, const std::string& what);

struct KeyframeStateValues {
  geometry::SE3d T_w_s;
  Eigen::Vector3d v_w = Eigen::Vector3d::Zero();
  imu::ImuBias bias;
};
void toProto(std::uint32_t counter, const KeyframeStateValues& state, v1::KeyframeState* out);
Result<KeyframeStateValues> fromProto(const v1::KeyframeState& state, const std::string& what);

void toProto(const dataset::CameraCalibration& calibration, const geometry::SE3d& T_s_c, v1::CameraCalibration* out);
// The calibration and T_s_c (camera -> IMU).
Result<std::pair<dataset::CameraCalibration, geometry::SE3d>> fromProto(const v1::CameraCalibration& calibration,
                                                                        const std::string& what);

void toProto(const imu::ImuNoise& noise, double rate_hz, v1::ImuCalibration* out);
Result<imu::ImuNoise> fromProto(const v1::ImuCalibration& imu, const std::string& what);

// Exactly `count` finite values.
Status checkFinite(const google::protobuf::RepeatedField<float>& values, int count, const std::string& what);

// A 32-byte descriptor as the 4 words of the protocol (byte 8w+b is bits 8b..8b+7 of word w), and back.
void packDescriptor(const std::uint8_t* bytes32, google::protobuf::RepeatedField<std::uint64_t>* words);
void unpackDescriptor(const std::uint64_t* words4, std::uint8_t* bytes32);

// What one batch carries, part by part: (objects, serialized bytes) per kind, so that the agent and the server
// count traffic the same way. Kinds: keyframe, point, observation, merge, keyframe_update, point_update, removal.
struct BatchPart {
  const char* kind;
  std::uint64_t count;
  std::uint64_t bytes;
};
std::array<BatchPart, 7> batchParts(const v1::MapBatch& batch);
// The same for the downlink's covisible map: covisible_keyframe, covisible_point, covisible_update (keyframe
// poses and point positions the server changed).
std::array<BatchPart, 3> covisibleParts(const v1::CovisibleMap& map);

// Bytes of an unsigned varint: what an id costs in a packed repeated field.
std::uint64_t varintBytes(std::uint64_t value);

// Keypoint orientation, 256 steps per turn.
std::uint8_t encodeAngle(float angle_deg);
float decodeAngle(std::uint8_t code);

}  // namespace cvislam::wire

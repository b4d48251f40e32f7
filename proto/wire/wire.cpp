#include "proto/wire/wire.hpp"

#include <cmath>

#include "cvislam/v1/agent_link.pb.h"
#include "cvislam/v1/types.pb.h"
#include "google/protobuf/repeated_field.h"

namespace cvislam::wire {

namespace {
Error invalid(const std::string& what) {
  return Error{ErrorCode::kInvalidArgument, what};
}
bool allFinite(std::initializer_list<double> values) {
  for (double v : values) {
    if (!std::isfinite(v)) return false;
  }
  return true;
}
}  // namespace

Status checkPosition(const Eigen::Vector3d& p, const std::string& what, double limit_m) {
  if (!p.allFinite()) return invalid(what + ": a non-finite position");
  if (p.norm() > limit_m) {
    return invalid(what + ": a position " + std::to_string(p.norm()) + " m from the origin (at most " +
                   std::to_string(limit_m) + " m)");
  }
  return Status::Ok();
}

namespace {
// |v| <= limit for each component of a 3-vector; `what` names the field.
Status checkBound(const Eigen::Vector3d& v, double limit, const std::string& what) {
  if (v.cwiseAbs().maxCoeff() > limit) {
    return invalid(what + ": a component of magnitude " + std::to_string(v.cwiseAbs().maxCoeff()) + " (at most " +
                   std::to_string(limit) + ")");
  }
  return Status::Ok();
}
}  // namespace

void toProto(const geometry::SE3d& T, v1::Pose* out) {
  out->set_px(T.translation().x());
  out->set_py(T.translation().y());
  out->set_pz(T.translation().z());
  const Eigen::Quaterniond& q = T.so3().quaternion();
  out->set_qx(static_cast<float>(q.x()));
  out->set_qy(static_cast<float>(q.y()));
  out->set_qz(static_cast<float>(q.z()));
  out->set_qw(static_cast<float>(q.w()));
}

Result<geometry::SE3d> fromProto(const v1::Pose& pose, const std::string& what) {
  const double qx = pose.qx();
  const double qy = pose.qy();
  const double qz = pose.qz();
  const double qw = pose.qw();
  if (!allFinite({pose.px(), pose.py(), pose.pz(), qx, qy, qz, qw})) return invalid(what + ": a non-finite value");
  const double norm = std::sqrt(qx * qx + qy * qy + qz * qz + qw * qw);
  if (std::abs(norm - 1.0) > 1e-3) {
    return invalid(what + ": the rotation quaternion has norm " + std::to_string(norm) + ", not 1");
  }
  const Eigen::Vector3d t(pose.px(), pose.py(), pose.pz());
  if (Status s = checkPosition(t, what); !s.ok()) return s.error();
  const Eigen::Quaterniond q(qw / norm, qx / norm, qy / norm, qz / norm);
  return geometry::SE3d(geometry::SO3d(q), t);
}

Status checkFinite(const google::protobuf::RepeatedField<float>& values, int count, const std::string& what) {
  if (values.size() != count) {
    return invalid(what + ": " + std::to_string(values.size()) + " values, expected " + std::to_string(count));
  }
  for (float v : values) {
    if (!std::isfinite(v)) return invalid(what + ": a non-finite value");
  }
  return Status::Ok();
}

void toProto(std::uint32_t counter, const KeyframeStateValues& state, v1::KeyframeState* out) {
  out->set_counter(counter);
  toProto(state.T_w_s, out->mutable_t_w_s());
  out->clear_v_w();
  out->clear_bias_gyro();
  out->clear_bias_accel();
  for (int i = 0; i < 3; ++i) {
    out->add_v_w(static_cast<float>(state.v_w[i]));
    out->add_bias_gyro(static_cast<float>(state.bias.gyro[i]));
    out->add_bias_accel(static_cast<float>(state.bias.accel[i]));
  }
}

Result<KeyframeStateValues> fromProto(const v1::KeyframeState& state, const std::string& what) {
  if (!state.has_t_w_s()) return invalid(what + ": no pose");
  auto T = fromProto(state.t_w_s(), what + " T_w_s");
  if (!T) return T.error();
  if (Status s = checkFinite(state.v_w(), 3, what + " v_w"); !s.ok()) return s.error();
  if (Status s = checkFinite(state.bias_gyro(), 3, what + " bias_gyro"); !s.ok()) return s.error();
  if (Status s = checkFinite(state.bias_accel(), 3, what + " bias_accel"); !s.ok()) return s.error();
  KeyframeStateValues out;
  out.T_w_s = *T;
  for (int i = 0; i < 3; ++i) {
    out.v_w[i] = state.v_w(i);
    out.bias.gyro[i] = state.bias_gyro(i);
    out.bias.accel[i] = state.bias_accel(i);
  }
  if (Status s = checkBound(out.v_w, kMaxSpeedMps, what + " v_w"); !s.ok()) return s.error();
  if (Status s = checkBound(out.bias.gyro, kMaxGyroBiasRadps, what + " bias_gyro"); !s.ok()) return s.error();
  if (Status s = checkBound(out.bias.accel, kMaxAccelBiasMps2, what + " bias_accel"); !s.ok()) return s.error();
  return out;
}

void toProto(const dataset::CameraCalibration& c, const geometry::SE3d& T_s_c, v1::CameraCalibration* out) {
  out->set_width(static_cast<std::uint32_t>(c.width));
  out->set_height(static_cast<std::uint32_t>(c.height));
  out->set_rate_hz(c.rate_hz);
  out->set_fx(c.fx);
  out->set_fy(c.fy);
  out->set_cx(c.cx);
  out->set_cy(c.cy);
  switch (c.distortion) {
    case dataset::DistortionModel::kNone:
      out->set_distortion(v1::DISTORTION_NONE);
      break;
    case dataset::DistortionModel::kRadialTangential:
      out->set_distortion(v1::DISTORTION_RADIAL_TANGENTIAL);
      break;
    case dataset::DistortionModel::kEquidistant:
      out->set_distortion(v1::DISTORTION_EQUIDISTANT);
      break;
  }
  out->clear_distortion_coefficients();
  for (double k : c.distortion_coefficients) out->add_distortion_coefficients(k);
  toProto(T_s_c, out->mutable_t_s_c());
}

Result<std::pair<dataset::CameraCalibration, geometry::SE3d>> fromProto(const v1::CameraCalibration& in,
                                                                        const std::string& what) {
  dataset::CameraCalibration c;
  if (in.width() == 0 || in.height() == 0 || in.width() > 16384 || in.height() > 16384) {
    return invalid(what + ": image size " + std::to_string(in.width()) + "x" + std::to_string(in.height()) +
                   " is not in [1, 16384]");
  }
  if (!allFinite({in.fx(), in.fy(), in.cx(), in.cy(), in.rate_hz()}) || !(in.fx() > 0) || !(in.fy() > 0)) {
    return invalid(what + ": focal lengths must be positive and every intrinsic finite");
  }
  if (in.fx() < kMinFocalPx || in.fy() < kMinFocalPx || in.fx() > kMaxFocalPx || in.fy() > kMaxFocalPx) {
    return invalid(what + ": focal lengths " + std::to_string(in.fx()) + ", " + std::to_string(in.fy()) +
                   " px are not in [1, 1e5]");
  }
  const double w = in.width();
  const double h = in.height();
  if (in.cx() < -w || in.cx() > 2 * w || in.cy() < -h || in.cy() > 2 * h) {
    return invalid(what + ": principal point (" + std::to_string(in.cx()) + ", " + std::to_string(in.cy()) +
                   ") is far outside the image");
  }
  if (in.rate_hz() < 0 || in.rate_hz() > kMaxRateHz) {
    return invalid(what + ": rate_hz " + std::to_string(in.rate_hz()) + " is not in [0, 1e4] (0: not said)");
  }
  if (in.distortion_coefficients_size() != 4) {
    return invalid(what + ": " + std::to_string(in.distortion_coefficients_size()) +
                   " distortion coefficients, expected 4");
  }
  c.width = static_cast<int>(in.width());
  c.height = static_cast<int>(in.height());
  c.rate_hz = in.rate_hz();
  c.fx = in.fx();
  c.fy = in.fy();
  c.cx = in.cx();
  c.cy = in.cy();
  switch (in.distortion()) {
    case v1::DISTORTION_NONE:
      c.distortion = dataset::DistortionModel::kNone;
      break;
    case v1::DISTORTION_RADIAL_TANGENTIAL:
      c.distortion = dataset::DistortionModel::kRadialTangential;
      break;
    case v1::DISTORTION_EQUIDISTANT:
      c.distortion = dataset::DistortionModel::kEquidistant;
      break;
    default:
      return invalid(what + ": unknown distortion model " + std::to_string(in.distortion()));
  }
  for (int i = 0; i < 4; ++i) {
    c.distortion_coefficients[static_cast<std::size_t>(i)] = in.distortion_coefficients(i);
    if (!std::isfinite(in.distortion_coefficients(i))) return invalid(what + ": a non-finite distortion coefficient");
    if (std::abs(in.distortion_coefficients(i)) > kMaxDistortion) {
      return invalid(what + ": distortion coefficient " + std::to_string(in.distortion_coefficients(i)) +
                     " is beyond +-10");
    }
  }
  if (!in.has_t_s_c()) return invalid(what + ": no T_s_c (camera to IMU)");
  auto T = fromProto(in.t_s_c(), what + " T_s_c");
  if (!T) return T.error();
  if (T->translation().norm() > kMaxCameraToImuM) {
    return invalid(what + ": the camera is " + std::to_string(T->translation().norm()) + " m from the IMU (T_s_c)");
  }
  c.T_b_c = *T;
  return std::pair{c, *T};
}

void toProto(const imu::ImuNoise& noise, double rate_hz, v1::ImuCalibration* out) {
  out->set_rate_hz(rate_hz);
  out->set_gyro_noise_density(noise.gyro_noise_density);
  out->set_gyro_random_walk(noise.gyro_random_walk);
  out->set_accel_noise_density(noise.accel_noise_density);
  out->set_accel_random_walk(noise.accel_random_walk);
}

Result<imu::ImuNoise> fromProto(const v1::ImuCalibration& in, const std::string& what) {
  imu::ImuNoise noise;
  noise.gyro_noise_density = in.gyro_noise_density();
  noise.gyro_random_walk = in.gyro_random_walk();
  noise.accel_noise_density = in.accel_noise_density();
  noise.accel_random_walk = in.accel_random_walk();
  if (!std::isfinite(in.rate_hz()) || !(in.rate_hz() > 0) || in.rate_hz() > kMaxRateHz) {
    return invalid(what + ": rate_hz must be positive and at most 1e4");
  }
  if (Status s = noise.validate(); !s.ok()) return s.error().withContext(what);
  for (double v :
       {noise.gyro_noise_density, noise.gyro_random_walk, noise.accel_noise_density, noise.accel_random_walk}) {
    if (v < kMinNoise || v > kMaxNoise) {
      return invalid(what + ": a noise figure of " + std::to_string(v) + " is not in [1e-9, 10]");
    }
  }
  return noise;
}

void packDescriptor(const std::uint8_t* bytes32, google::protobuf::RepeatedField<std::uint64_t>* words) {
  for (int w = 0; w < 4; ++w) {
    std::uint64_t word = 0;
    for (int b = 0; b < 8; ++b)
      word |= static_cast<std::uint64_t>(bytes32[8 * w + b]) << (8U * static_cast<unsigned>(b));
    words->Add(word);
  }
}

void unpackDescriptor(const std::uint64_t* words4, std::uint8_t* bytes32) {
  for (int w = 0; w < 4; ++w) {
    for (int b = 0; b < 8; ++b) {
      bytes32[8 * w + b] = static_cast<std::uint8_t>((words4[w] >> (8U * static_cast<unsigned>(b))) & 0xFFU);
    }
  }
}

std::uint64_t varintBytes(std::uint64_t value) {
  std::uint64_t n = 1;
  for (; value >= 128; value >>= 7U) ++n;
  return n;
}

std::array<BatchPart, 7> batchParts(const v1::MapBatch& b) {
  const auto sum = [](const auto& messages) {
    std::uint64_t bytes = 0;
    for (const auto& m : messages) bytes += m.ByteSizeLong();
    return bytes;
  };
  std::uint64_t observations = 0;
  for (const auto& o : b.observations()) observations += static_cast<std::uint64_t>(o.keypoint_size());
  std::uint64_t removal_bytes = 0;
  for (std::uint32_t c : b.removed_points()) removal_bytes += varintBytes(c);
  for (std::uint32_t c : b.removed_keyframes()) removal_bytes += varintBytes(c);
  const auto count = [](int n) { return static_cast<std::uint64_t>(n); };
  return {{{"keyframe", count(b.keyframes_size()), sum(b.keyframes())},
           {"point", count(b.points_size()), sum(b.points())},
           {"observation", observations, sum(b.observations())},
           {"merge", count(b.merges().drop_size()), b.has_merges() ? b.merges().ByteSizeLong() : 0},
           {"keyframe_update", count(b.keyframe_updates_size()), sum(b.keyframe_updates())},
           {"point_update", count(b.point_updates().point_size()),
            b.has_point_updates() ? b.point_updates().ByteSizeLong() : 0},
           {"removal", count(b.removed_points_size() + b.removed_keyframes_size()), removal_bytes}}};
}

std::array<BatchPart, 3> covisibleParts(const v1::CovisibleMap& m) {
  const auto sum = [](const auto& messages) {
    std::uint64_t bytes = 0;
    for (const auto& x : messages) bytes += x.ByteSizeLong();
    return bytes;
  };
  std::uint64_t point_update_bytes = 4ULL * static_cast<std::uint64_t>(m.point_update_p_w_size());
  for (std::uint32_t a : m.point_update_agent()) point_update_bytes += varintBytes(a);
  for (std::uint32_t c : m.point_update_counter()) point_update_bytes += varintBytes(c);
  const auto count = [](int n) { return static_cast<std::uint64_t>(n); };
  return {{{"covisible_keyframe", count(m.keyframes_size()), sum(m.keyframes())},
           {"covisible_point", count(m.points_size()), sum(m.points())},
           {"covisible_update", count(m.keyframe_updates_size() + m.point_update_counter_size()),
            sum(m.keyframe_updates()) + point_update_bytes}}};
}

std::uint8_t encodeAngle(float angle_deg) {
  float a = std::fmod(angle_deg, 360.0F);
  if (a < 0) a += 360.0F;
  return static_cast<std::uint8_t>(static_cast<int>(std::lround(a * 256.0F / 360.0F)) & 0xFF);
}

float decodeAngle(std::uint8_t code) {
  return static_cast<float>(code) * 360.0F / 256.0F;
}

}  // namespace cvislam::wire

// The mapper's test fixture: a synthetic scene with exact keypoints and one random descriptor per 3D point (so
// matching is by identity), seen by a monocular camera stepping sideways, and the mapper made for it. Used by
// mapper_test.cpp (the keyframe pipeline) and mapper_downlink_test.cpp (what the server sends down).
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <optional>
#include <random>
#include <vector>

#include <gtest/gtest.h>

#include "agent_rt/mapping/mapper.hpp"
#include "agent_rt/messages/conversions.hpp"
#include "common/dataset/euroc_calibration.hpp"

namespace cvislam::agent {

struct Scene {
  std::vector<Eigen::Vector3d> p_w;
  std::vector<std::array<std::uint8_t, 32>> descriptors;
};

inline Scene makeScene(int points, std::uint64_t seed) {
  Scene s;
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> x(-4.0, 4.0);
  std::uniform_real_distribution<double> y(-3.0, 3.0);
  std::uniform_real_distribution<double> z(4.0, 9.0);
  std::uniform_int_distribution<int> byte(0, 255);
  for (int i = 0; i < points; ++i) {
    s.p_w.emplace_back(x(rng), y(rng), z(rng));
    std::array<std::uint8_t, 32> d{};
    for (auto& b : d) b = static_cast<std::uint8_t>(byte(rng));
    s.descriptors.push_back(d);
  }
  return s;
}

class MapperTest : public ::testing::Test {
 protected:
  void SetUp() override {
    calibration_ = dataset::eurocCam0();
    calibration_.distortion = dataset::DistortionModel::kNone;
    camera_.emplace(camera::CameraModel::create(calibration_).value());
    T_s_c_ = calibration_.T_b_c;
    MapperOptions options;
    options.use_imu = false;
    options.max_keyframes = 6;
    options.retention.place_keyframes = 0;  // the newest only, unless a test asks for more
    options.ba.window = 4;
    options.ba.intrinsics = {calibration_.fx, calibration_.fy, calibration_.cx, calibration_.cy};
    options.imu_init_keyframes = 4;
    options.imu_init_max_keyframes = 6;
    options.mono_init_min_matches = 50;
    adjust(options);
    options_ = options;
    auto mapper = Mapper::create(options, *camera_, nullptr, T_s_c_, geometry::SE3d());
    ASSERT_TRUE(mapper.ok()) << mapper.error().toString();
    mapper_ = std::move(mapper.value());
    message_ = std::make_unique<KeyframeMessage>();
    snapshot_ = std::make_unique<MapSnapshotMessage>();
  }

  virtual void adjust(MapperOptions& /*options*/) {}

  // The camera looks along world z; keyframe k sits at x = 0.25 k (or x_m_[k]), with a small yaw. `scale` scales the
  // camera's position (a monocular map is the scene up to scale about camera 0).
  [[nodiscard]] geometry::SE3d truePose(int k, double scale = 1.0) const {
    const double x_m = x_m_.empty() ? step_m_ * k : x_m_[static_cast<std::size_t>(k)];
    const geometry::SE3d T_w_c(geometry::SO3d::exp(Eigen::Vector3d(0.0, 0.02 * k, 0.0)),
                               scale * Eigen::Vector3d(x_m, 0.02 * k, 0.0));
    return T_w_c * T_s_c_.inverse();
  }

  // A keyframe message seeing the scene from keyframe k's true pose; tracking's matches where `match_ids`
  // names a map point for a scene point.
  const KeyframeMessage& keyframe(int k, KeyframeKind kind, const geometry::SE3d& T_w_s_estimate,
                                  const std::vector<MapPointId>* match_ids = nullptr,
                                  const std::vector<bool>* detected = nullptr) {
    KeyframeMessage& m = *message_;
    m = KeyframeMessage{};
    m.sequence = static_cast<std::uint64_t>(k);
    m.kind = kind;
    m.state.id = KeyframeId{0, static_cast<std::uint32_t>(k)};
    m.state.t_ns = 1'000'000'000LL * (k + 1);
    m.state.T_w_s = toMsg(T_w_s_estimate);
    const geometry::SE3d T_c_w = (truePose(k) * T_s_c_).inverse();
    keypoint_point_.clear();
    for (std::size_t i = 0; i < scene_.p_w.size() && m.keypoint_count < kMaxKeypointsPerKeyframe; ++i) {
      const Eigen::Vector3d p_c = T_c_w * scene_.p_w[i];
      const auto px = camera_->project(p_c);
      if (p_c.z() < 0.5 || !px || px->x() < 20 || px->y() < 20 || px->x() > 730 || px->y() > 460) continue;
      if (detected != nullptr && !(*detected)[i]) continue;
      const std::uint16_t k_index = m.keypoint_count++;
      m.keypoints[k_index] = KeypointMsg{static_cast<float>(px->x()), static_cast<float>(px->y()), 1.0F, 0.0F, 0};
      m.descriptors[k_index] = scene_.descriptors[i];
      if (match_ids != nullptr && (*match_ids)[i].counter != 0xFFFFFFFF) {
        m.matched[k_index] = (*match_ids)[i];
        m.has_match[k_index] = 1;
      }
      keypoint_point_.push_back(i);
    }
    return m;
  }

  dataset::CameraCalibration calibration_;
  std::optional<camera::CameraModel> camera_;
  geometry::SE3d T_s_c_;
  MapperOptions options_;
  std::unique_ptr<Mapper> mapper_;
  std::unique_ptr<KeyframeMessage> message_;
  std::unique_ptr<MapSnapshotMessage> snapshot_;
  std::vector<std::size_t> keypoint_point_;
  Scene scene_ = makeScene(400, 3);
  double step_m_ = 0.25;     // sideways between keyframes k and k + 1
  std::vector<double> x_m_;  // when set, keyframe k's sideways position instead (a start that moves back and forth)
};

}  // namespace cvislam::agent

// A frame to track for the pose optimisation tests: the observations of one keyframe of the synthetic
// visual-inertial scene (test/support/vi_scenario), with 0.5 px noise and a share of wrong matches placed
// anywhere in the image.
#pragma once

#include <cstdint>
#include <random>
#include <vector>

#include "agent_rt/tracking/pose_optimizer.hpp"
#include "test/support/vi_scenario.hpp"

namespace cvislam::agent {

struct TrackingCase {
  test::ViScenario scenario;
  int frame = 3;
  std::vector<PoseObservation> observations;
  std::vector<std::uint8_t> corrupted;  // per observation: a wrong match

  [[nodiscard]] const geometry::SE3d& truePose() const {
    return scenario.keyframe_states[static_cast<std::size_t>(frame)].T_w_s;
  }
};

inline TrackingCase makeTrackingCase(double outlier_fraction, std::uint64_t seed, const imu::ImuBias& bias = {}) {
  TrackingCase c;
  test::ViScenarioOptions options;
  options.pixel_sigma = 0.5;
  options.seed = seed;
  options.bias = bias;
  c.scenario = test::makeViScenario(options);
  std::mt19937_64 rng(seed + 100);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  for (const test::ViObservation& o : c.scenario.observations) {
    if (o.keyframe != c.frame) continue;
    PoseObservation p;
    p.p_w = c.scenario.points[static_cast<std::size_t>(o.point)].p_w;
    p.keypoint_px = o.keypoint_px;
    p.sigma_px = 0.5;
    const bool corrupt = unit(rng) < outlier_fraction;
    if (corrupt) p.keypoint_px = Eigen::Vector2d(752.0 * unit(rng), 480.0 * unit(rng));
    c.observations.push_back(p);
    c.corrupted.push_back(corrupt ? 1 : 0);
  }
  return c;
}

}  // namespace cvislam::agent

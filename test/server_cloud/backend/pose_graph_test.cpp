// The loop pose graph on its own: a chain whose second half drifted, closed by one loop edge.
#include "server_cloud/backend/pose_graph.hpp"

#include <cmath>

#include <gtest/gtest.h>

#include "server_cloud/backend/map_fusion.hpp"

namespace cvislam::server::backend {
namespace {

using Eigen::Vector3d;
using geometry::SE3d;
using geometry::SO3d;

constexpr double kDeg = M_PI / 180.0;

SO3d aboutZ(double rad) {
  return SO3d::exp(Vector3d(0.0, 0.0, rad));
}

// The turn about gravity between two attitudes, R_a R_b^T read as a yaw [deg].
double turnDeg(const SO3d& R_a, const SO3d& R_b) {
  return yawOf((R_a * R_b.inverse()).matrix()) / kDeg;
}

struct DriftedChain {
  std::vector<SE3d> truth;
  PoseGraph graph;
};

// 20 keyframes a quarter of a circle of 3 m apart, the sensor mounted as `R_mount` on a body that faces along the
// path. From keyframe 10 on the estimate drifts, up to `drift_deg` about gravity and 30 cm at keyframe 19. The
// chain's edges hold the drifted relative poses; one loop edge 0 -> 19 holds the true one, turned by `tilt_deg`
// about the sensor's y+z diagonal (what a loop measured from points carries).
DriftedChain driftedChain(const SO3d& R_mount, double drift_deg, double tilt_deg) {
  DriftedChain c;
  std::vector<SE3d> estimate;
  for (int i = 0; i < 20; ++i) {
    const double a = 0.5 * M_PI * i / 19.0;
    const SE3d T(aboutZ(a + 0.5 * M_PI) * R_mount, Vector3d(3.0 * std::cos(a), 3.0 * std::sin(a), 1.0 + 0.02 * i));
    c.truth.push_back(T);
    const double f = i < 10 ? 0.0 : (i - 9) / 10.0;
    estimate.push_back(SE3d(aboutZ(f * drift_deg * kDeg), f * Vector3d(0.2, -0.2, 0.05)) * T);
    c.graph.nodes.push_back({KeyframeId{1, static_cast<std::uint32_t>(i)}, i, estimate.back(), std::nullopt});
  }
  for (int i = 0; i + 1 < 20; ++i) c.graph.edges.push_back({i, i + 1, estimate[i].inverse() * estimate[i + 1], 1.0});
  const SE3d T_0_19 = c.truth[0].inverse() * c.truth[19] *
                      SE3d(SO3d::exp(Vector3d(0.0, 1.0, 1.0).normalized() * tilt_deg * kDeg), Vector3d::Zero());
  c.graph.edges.push_back({0, 19, T_0_19, PoseGraphOptions{}.loop_weight});
  return c;
}

const SE3d* corrected(const std::vector<KeyframeCorrection>& corrections, std::uint32_t counter) {
  for (const KeyframeCorrection& k : corrections) {
    if (k.id.counter == counter) return &k.T_w_s_after;
  }
  return nullptr;
}

void expectTheLoopTakesOutTheDrift(const SO3d& R_mount) {
  DriftedChain c = driftedChain(R_mount, 3.0, 0.1);
  const auto corrections = solvePoseGraph(c.graph, PoseGraphOptions{});
  ASSERT_TRUE(corrections.ok()) << corrections.error().toString();
  const SE3d* last = corrected(*corrections, 19);
  ASSERT_NE(last, nullptr);
  EXPECT_LT(std::abs(turnDeg(last->so3(), c.truth[19].so3())), 0.3) << "of the 3 deg drift, about gravity";
  EXPECT_LT((last->translation() - c.truth[19].translation()).norm(), 0.03);
  // Roll and pitch are held: the correction is a turn about gravity only.
  const SO3d change = last->so3() * c.graph.nodes[19].T_w_s.so3().inverse();
  EXPECT_LT(std::abs(change.log().x()) + std::abs(change.log().y()), 1e-9);
}

TEST(PoseGraph, ALoopTakesOutTheDriftAboutGravityWithTheSensorLevel) {
  expectTheLoopTakesOutTheDrift(SO3d());
}

TEST(PoseGraph, ALoopTakesOutTheDriftAboutGravityWithTheSensorsXAxisNearlyUpAsEurocsImu) {
  // EuRoC's IMU (and the simulator's) has its x-axis within a few degrees of the vertical: Euler yaw of such an
  // attitude is near its singularity. 3.5 deg off the vertical, as the simulator's rig.
  const SO3d x_up(Eigen::Quaterniond(Eigen::AngleAxisd(0.5 * M_PI, Vector3d::UnitZ()) *
                                     Eigen::AngleAxisd(-0.5 * M_PI + 3.5 * kDeg, Vector3d::UnitY())));
  ASSERT_GT((x_up * Vector3d::UnitX()).z(), 0.99);
  expectTheLoopTakesOutTheDrift(x_up);
}

}  // namespace
}  // namespace cvislam::server::backend

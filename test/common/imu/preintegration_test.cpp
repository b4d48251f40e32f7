// Preintegration against analytic truth, numeric bias Jacobians, Monte-Carlo covariance, and real EuRoC data.
#include "common/imu/preintegration.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <random>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "common/dataset/calibration.hpp"
#include "common/dataset/euroc.hpp"
#include "test/support/numeric_diff.hpp"
#include "test/support/test_data.hpp"
#include "test/support/vi_scenario.hpp"

namespace cvislam::imu {
namespace {

using Eigen::Vector3d;
using geometry::SO3d;
using Vec9 = Eigen::Matrix<double, 9, 1>;

// The deltas between two true states, in the preintegration's definition.
struct Deltas {
  SO3d dR;
  Vector3d dv;
  Vector3d dp;
};

Deltas trueDeltas(const NavState& i, const NavState& j, double dt) {
  const SO3d R_i_inv = i.T_w_s.so3().inverse();
  return {R_i_inv * j.T_w_s.so3(), R_i_inv * (j.v_w - i.v_w - kGravityW * dt),
          R_i_inv * (j.T_w_s.translation() - i.T_w_s.translation() - i.v_w * dt - 0.5 * kGravityW * dt * dt)};
}

// [Log(dR_ref^T dR), dv - dv_ref, dp - dp_ref]: the error vector the covariance describes.
Vec9 deltaError(const Deltas& reference, const SO3d& dR, const Vector3d& dv, const Vector3d& dp) {
  Vec9 e;
  e << (reference.dR.inverse() * dR).log(), dv - reference.dv, dp - reference.dp;
  return e;
}

TEST(Preintegration, NoiseFreeSamplesReproduceTheAnalyticDeltas) {
  test::ViScenarioOptions options;
  options.bias.gyro = Vector3d(0.01, -0.02, 0.015);
  options.bias.accel = Vector3d(0.05, -0.03, 0.02);
  const test::ViScenario s = test::makeViScenario(options);
  for (std::size_t k = 0; k + 1 < s.keyframe_states.size(); ++k) {
    Preintegration sut(options.bias, s.noise);
    ASSERT_TRUE(sut.integrateInterval(s.imu, s.keyframe_t_ns[k], s.keyframe_t_ns[k + 1]).ok());
    EXPECT_NEAR(sut.dt(), options.keyframe_interval_s, 1e-12);
    const Deltas truth = trueDeltas(s.keyframe_states[k], s.keyframe_states[k + 1], sut.dt());
    const Vec9 e = deltaError(truth, sut.deltaR(), sut.deltaV(), sut.deltaP());
    EXPECT_LT(e.head<3>().norm(), 1e-6) << "interval " << k;
    EXPECT_LT(e.segment<3>(3).norm(), 1e-5) << "interval " << k;
    EXPECT_LT(e.tail<3>().norm(), 1e-6) << "interval " << k;
    // predict() closes the loop from state i to state j.
    const NavState predicted = sut.predict(s.keyframe_states[k], options.bias);
    EXPECT_LT((predicted.T_w_s.translation() - s.keyframe_states[k + 1].T_w_s.translation()).norm(), 1e-5);
    EXPECT_LT((predicted.v_w - s.keyframe_states[k + 1].v_w).norm(), 1e-5);
  }
}

TEST(Preintegration, BiasJacobiansMatchNumericReintegration) {
  const test::ViScenario s = test::makeViScenario({});
  ImuBias b0;
  b0.gyro = Vector3d(0.02, -0.01, 0.03);
  b0.accel = Vector3d(-0.1, 0.2, 0.05);
  const auto integrate_at = [&](const ImuBias& bias) {
    Preintegration p(bias, s.noise);
    EXPECT_TRUE(p.integrateInterval(s.imu, s.keyframe_t_ns[1], s.keyframe_t_ns[3]).ok());
    return p;
  };
  const Preintegration sut = integrate_at(b0);
  const Deltas at_b0{sut.deltaR(), sut.deltaV(), sut.deltaP()};
  const auto f = [&](const Eigen::Matrix<double, 6, 1>& db) {
    ImuBias b = b0;
    b.gyro += db.head<3>();
    b.accel += db.tail<3>();
    const Preintegration p = integrate_at(b);
    return deltaError(at_b0, p.deltaR(), p.deltaV(), p.deltaP());
  };
  const Eigen::Matrix<double, 9, 6> J_numeric = test::numericJacobian<9, 6>(f, Eigen::Matrix<double, 6, 1>::Zero());
  Eigen::Matrix<double, 9, 6> J = Eigen::Matrix<double, 9, 6>::Zero();
  J.block<3, 3>(0, 0) = sut.dR_dbg();
  J.block<3, 3>(3, 0) = sut.dv_dbg();
  J.block<3, 3>(3, 3) = sut.dv_dba();
  J.block<3, 3>(6, 0) = sut.dp_dbg();
  J.block<3, 3>(6, 3) = sut.dp_dba();
  EXPECT_LT((J - J_numeric).cwiseAbs().maxCoeff(), 1e-6) << "analytic\n" << J << "\nnumeric\n" << J_numeric;

  // The first-order correction beats the stale deltas by two orders of magnitude for a small bias change.
  ImuBias b1 = b0;
  b1.gyro += Vector3d(2e-3, -1e-3, 1.5e-3);
  b1.accel += Vector3d(0.02, 0.01, -0.03);
  const Preintegration reintegrated = integrate_at(b1);
  const Deltas exact{reintegrated.deltaR(), reintegrated.deltaV(), reintegrated.deltaP()};
  const Vec9 corrected_error =
      deltaError(exact, sut.correctedDeltaR(b1), sut.correctedDeltaV(b1), sut.correctedDeltaP(b1));
  const Vec9 stale_error = deltaError(exact, sut.deltaR(), sut.deltaV(), sut.deltaP());
  EXPECT_LT(corrected_error.norm(), 1e-2 * stale_error.norm());
}

TEST(Preintegration, PropagatedCovarianceMatchesMonteCarlo) {
  constexpr int kRuns = 2000;
  constexpr double kRateHz = 200.0;
  test::ViScenarioOptions options;
  options.imu_rate_hz = kRateHz;
  const test::ViScenario s = test::makeViScenario(options);
  // Exaggerated noise so that the error is far above the discretisation error of the clean run.
  ImuNoise noise;
  noise.gyro_noise_density = 0.01;
  noise.accel_noise_density = 0.1;
  const double dt = 1.0 / kRateHz;
  const std::size_t first = 40;
  const std::size_t count = 200;  // 1 s

  Preintegration clean(ImuBias{}, noise);
  for (std::size_t k = first; k < first + count; ++k) clean.integrate(dt, s.imu[k].gyro_s, s.imu[k].accel_s);
  const Deltas reference{clean.deltaR(), clean.deltaV(), clean.deltaP()};

  std::mt19937_64 rng(42);
  std::normal_distribution<double> normal(0.0, 1.0);
  const double sigma_g = noise.gyro_noise_density / std::sqrt(dt);
  const double sigma_a = noise.accel_noise_density / std::sqrt(dt);
  Mat9 empirical = Mat9::Zero();
  for (int run = 0; run < kRuns; ++run) {
    Preintegration noisy(ImuBias{}, noise);
    for (std::size_t k = first; k < first + count; ++k) {
      const Vector3d n_g(normal(rng), normal(rng), normal(rng));
      const Vector3d n_a(normal(rng), normal(rng), normal(rng));
      noisy.integrate(dt, s.imu[k].gyro_s + sigma_g * n_g, s.imu[k].accel_s + sigma_a * n_a);
    }
    const Vec9 e = deltaError(reference, noisy.deltaR(), noisy.deltaV(), noisy.deltaP());
    empirical += e * e.transpose() / kRuns;
  }
  const Mat9& predicted = clean.covariance();
  // A variance estimated from N samples has a relative standard error of sqrt(2/N) = 3.2 %; allow 4 of them.
  for (int i = 0; i < 9; ++i) {
    EXPECT_NEAR(empirical(i, i) / predicted(i, i), 1.0, 0.13) << "component " << i;
  }
  // Correlations too (v-phi, p-v couplings), measured relative to the diagonal.
  Eigen::Matrix<double, 9, 1> inv_sd = predicted.diagonal().cwiseSqrt().cwiseInverse();
  const Mat9 corr_predicted = inv_sd.asDiagonal() * predicted * inv_sd.asDiagonal();
  const Mat9 corr_empirical = inv_sd.asDiagonal() * empirical * inv_sd.asDiagonal();
  EXPECT_LT((corr_predicted - corr_empirical).cwiseAbs().maxCoeff(), 0.12);
}

TEST(Preintegration, IntervalBetweenSampleTimesIsCutExactly) {
  const test::ViScenario s = test::makeViScenario({});
  Preintegration sut(ImuBias{}, s.noise);
  const std::int64_t t0 = 123'456'789;  // between two 1 kHz samples
  const std::int64_t t1 = 456'789'012;
  ASSERT_TRUE(sut.integrateInterval(s.imu, t0, t1).ok());
  EXPECT_NEAR(sut.dt(), static_cast<double>(t1 - t0) * 1e-9, 1e-12);
  EXPECT_EQ(sut.sampleCount(), 334);  // the partial first, 332 whole ones, the partial last
}

TEST(Preintegration, UncoveredIntervalsAndGapsAreReportedWithTheirTimes) {
  const test::ViScenario s = test::makeViScenario({});
  Preintegration sut(ImuBias{}, s.noise);
  const Status before = sut.integrateInterval(s.imu, -1'000'000, 10'000'000);
  ASSERT_FALSE(before.ok());
  EXPECT_NE(before.error().message().find("do not cover"), std::string::npos) << before.error().message();

  std::vector<dataset::ImuSample> gappy(s.imu.begin(), s.imu.end());
  gappy.erase(gappy.begin() + 100, gappy.begin() + 200);  // 100 ms missing after t = 99 ms
  Preintegration sut2(ImuBias{}, s.noise);
  const Status gap = sut2.integrateInterval(gappy, 0, 300'000'000);
  ASSERT_FALSE(gap.ok());
  EXPECT_NE(gap.error().message().find("IMU gap of 101 ms after t = 99000000 ns"), std::string::npos)
      << gap.error().message();

  const Status reversed = sut2.integrateInterval(s.imu, 10, 5);
  EXPECT_FALSE(reversed.ok());
}

TEST(ImuNoise, ValidateNamesTheBadField) {
  ImuNoise noise;
  EXPECT_TRUE(noise.validate().ok());
  noise.accel_random_walk = -1.0;
  const Status status = noise.validate();
  ASSERT_FALSE(status.ok());
  EXPECT_NE(status.error().message().find("accel_random_walk"), std::string::npos);
}

// ---------------------------------------------------------------------------------------------- real data
struct ConsistencyStats {
  int windows = 0;
  std::array<int, 9> within_3_sigma{};
  double max_position_error_m = 0.0;
  std::vector<double> nees;                        // normalised estimation error squared, 9 dof
  std::array<std::vector<double>, 3> error_norms;  // |e| of rotation [deg], velocity [m/s], position [m]
  std::array<std::vector<double>, 3> sigmas;       // sqrt(trace/3) of the blocks, same units
  std::array<std::vector<double>, 9> normalised;   // |e_k| / sigma_k per component
};

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0.0 : v[v.size() / 2];
}

// Preintegrates the real IMU over windows of `window_s` between ground-truth states (biases from the ground
// truth at the window start) and compares with the ground-truth deltas, normalised by the propagated sigma.
struct RealImuData {
  std::vector<dataset::ImuSample> imu;
  std::vector<dataset::GroundTruthState> gt;
  ImuNoise noise;
};

// Reads imu0 (data.csv, sensor.yaml) and the ground truth of a EuRoC folder; images are not needed.
RealImuData readRealImuData(const std::filesystem::path& mav0) {
  RealImuData data;
  Diagnostics diagnostics;
  auto imu = dataset::readImuCsv(mav0 / "imu0" / "data.csv", true, diagnostics);
  EXPECT_TRUE(imu.ok()) << imu.error().toString();
  auto gt = dataset::readGroundTruthCsv(mav0 / "state_groundtruth_estimate0" / "data.csv", true, diagnostics);
  EXPECT_TRUE(gt.ok()) << gt.error().toString();
  auto calibration = dataset::readImuCalibration(mav0 / "imu0" / "sensor.yaml");
  EXPECT_TRUE(calibration.ok()) << calibration.error().toString();
  if (imu.ok()) data.imu = *imu;
  if (gt.ok()) data.gt = *gt;
  if (calibration.ok()) data.noise = ImuNoise::fromCalibration(*calibration);
  return data;
}

ConsistencyStats checkAgainstGroundTruth(const RealImuData& data, double window_s, double stride_s) {
  ConsistencyStats stats;
  const auto& gt = data.gt;
  const auto& imu = data.imu;
  const ImuNoise& noise = data.noise;
  const auto window_ns = static_cast<std::int64_t>(window_s * 1e9);
  const auto stride_ns = static_cast<std::int64_t>(stride_s * 1e9);
  std::size_t i = 0;
  while (i < gt.size()) {
    const std::int64_t t0 = gt[i].t_ns;
    auto j_it = std::lower_bound(gt.begin() + static_cast<std::ptrdiff_t>(i), gt.end(), t0 + window_ns,
                                 [](const dataset::GroundTruthState& g, std::int64_t t) { return g.t_ns < t; });
    if (j_it == gt.end()) break;
    const std::size_t j = static_cast<std::size_t>(j_it - gt.begin());
    if (t0 >= imu.front().t_ns && gt[j].t_ns <= imu.back().t_ns) {
      ImuBias bias;
      bias.gyro = gt[i].gyro_bias;
      bias.accel = gt[i].accel_bias;
      Preintegration pre(bias, noise);
      if (pre.integrateInterval(imu, t0, gt[j].t_ns).ok()) {
        const NavState si{gt[i].T_w_b, gt[i].v_w};
        const NavState sj{gt[j].T_w_b, gt[j].v_w};
        const Deltas truth = trueDeltas(si, sj, pre.dt());
        const Vec9 e = deltaError(truth, pre.deltaR(), pre.deltaV(), pre.deltaP());
        const Mat9& P = pre.covariance();
        for (int k = 0; k < 9; ++k) {
          const double z = std::abs(e(k)) / std::sqrt(P(k, k));
          if (z <= 3.0) ++stats.within_3_sigma[static_cast<std::size_t>(k)];
          stats.normalised[static_cast<std::size_t>(k)].push_back(z);
        }
        stats.nees.push_back(e.dot(P.ldlt().solve(e)));
        for (int b = 0; b < 3; ++b) {
          const double unit = b == 0 ? 180.0 / M_PI : 1.0;
          stats.error_norms[static_cast<std::size_t>(b)].push_back(
              unit * e.segment<3>(3 * static_cast<Eigen::Index>(b)).norm());
          stats.sigmas[static_cast<std::size_t>(b)].push_back(
              unit *
              std::sqrt(P.block<3, 3>(3 * static_cast<Eigen::Index>(b), 3 * static_cast<Eigen::Index>(b)).trace() / 3));
        }
        stats.max_position_error_m = std::max(stats.max_position_error_m, e.tail<3>().norm());
        ++stats.windows;
      }
    }
    auto next = std::lower_bound(gt.begin() + static_cast<std::ptrdiff_t>(i), gt.end(), t0 + stride_ns,
                                 [](const dataset::GroundTruthState& g, std::int64_t t) { return g.t_ns < t; });
    i = static_cast<std::size_t>(next - gt.begin());
  }
  return stats;
}

// Prints the consistency of the real deltas with the covariance propagated from the sensor.yaml noise
// densities, and returns the smallest factor k by which those densities must be multiplied for 95 % of the
// errors of every component to lie within 3 sigma.
double reportConsistency(const std::string& name, const ConsistencyStats& stats) {
  EXPECT_GT(stats.windows, 10) << name;
  std::printf("%s: %d windows; within 3 sigma per axis [%%]:", name.c_str(), stats.windows);
  double k_needed = 0.0;
  for (std::size_t k = 0; k < 9; ++k) {
    std::printf(" %.0f", 100.0 * static_cast<double>(stats.within_3_sigma[k]) / std::max(stats.windows, 1));
    std::vector<double> z = stats.normalised[k];
    std::sort(z.begin(), z.end());
    if (!z.empty()) k_needed = std::max(k_needed, z[static_cast<std::size_t>(0.95 * (z.size() - 1))] / 3.0);
  }
  std::printf("; NEES median %.0f (9 if consistent)\n", median(stats.nees));
  std::printf(
      "  median |error| vs median sigma: rot %.4f vs %.4f deg, vel %.4f vs %.4f m/s, pos %.4f vs %.4f m;"
      " noise must be x%.1f for 95 %% within 3 sigma\n",
      median(stats.error_norms[0]), median(stats.sigmas[0]), median(stats.error_norms[1]), median(stats.sigmas[1]),
      median(stats.error_norms[2]), median(stats.sigmas[2]), k_needed);
  return k_needed;
}

// Real flights are not as clean as the datasheet densities say: rotor vibration, ground-truth error and the
// ground truth's own bias estimates all add to the difference. The sensor.yaml densities underestimate it
// about tenfold (VIO systems inflate them for EuRoC: VINS-Fusion runs with 50x the accelerometer and 60x the
// gyroscope density). The test therefore checks (1) accuracy in physical units, which any frame, sign,
// gravity or bias mistake would break by orders of magnitude, and (2) that the covariance has the right
// shape: a uniform inflation of at most kMaxInflation makes 95 % of every component lie within 3 sigma.
constexpr double kMaxInflation = 15.0;

void checkRealData(const std::string& sequence, const RealImuData& data, double stride_s) {
  ASSERT_FALSE(data.imu.empty());
  ASSERT_FALSE(data.gt.empty());
  for (const double window_s : {0.25, 0.5, 1.0}) {
    const ConsistencyStats stats = checkAgainstGroundTruth(data, window_s, stride_s);
    const std::string name = sequence + " " + std::to_string(window_s).substr(0, 4) + " s";
    const double inflation = reportConsistency(name, stats);
    EXPECT_LE(inflation, kMaxInflation) << name;
    EXPECT_LT(median(stats.error_norms[0]), 0.25 * window_s) << name << ": rotation [deg]";
    EXPECT_LT(median(stats.error_norms[1]), 0.1 * window_s) << name << ": velocity [m/s]";
    EXPECT_LT(median(stats.error_norms[2]), 0.05 * window_s * window_s) << name << ": position [m]";
  }
}

TEST(PreintegrationRealData, EurocV102DeltasAgreeWithGroundTruth) {
  CVISLAM_REQUIRE_DATA(path, "euroc-v102-imu-gt");
  checkRealData("V1_02", readRealImuData(path / "mav0"), 0.25);
}

TEST(PreintegrationRealData, EurocV101DeltasAgreeWithGroundTruth) {
  CVISLAM_REQUIRE_DATA(path, "euroc-v101-excerpt");
  checkRealData("V1_01", readRealImuData(path / "mav0"), 0.5);
}

// 200 Hz readings of a linear ramp (gyro and accel), from t = 0, with seeded white noise of sigma.
std::vector<dataset::ImuSample> rampSamples(int count, double noise_sigma, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> noise(0.0, noise_sigma);
  std::vector<dataset::ImuSample> out;
  for (int i = 0; i < count; ++i) {
    const std::int64_t t_ns = 5'000'000LL * i;
    const double t = static_cast<double>(t_ns) * 1e-9;
    const Vector3d gyro(0.2 + 3.0 * t + noise(rng), -0.1 - 1.0 * t + noise(rng), 0.5 + noise(rng));
    const Vector3d accel(1.0 + 40.0 * t + noise(rng), 9.81 - 20.0 * t + noise(rng), 0.3 + noise(rng));
    out.push_back({t_ns, gyro, accel});
  }
  return out;
}

TEST(ExtrapolateImu, FollowsALinearSignalExactlyPastTheNewestSample) {
  const std::vector<dataset::ImuSample> samples = rampSamples(20, 0.0, 1);
  const std::int64_t t_ns = samples.back().t_ns + 25'000'000;
  const dataset::ImuSample want = rampSamples(25, 0.0, 1).back();  // the ramp's own reading 25 ms on
  ASSERT_EQ(want.t_ns, t_ns);
  const dataset::ImuSample got = extrapolateImu(samples, t_ns);
  EXPECT_EQ(got.t_ns, t_ns);
  EXPECT_LT((got.gyro_s - want.gyro_s).norm(), 1e-9);
  EXPECT_LT((got.accel_s - want.accel_s).norm(), 1e-9);
}

TEST(ExtrapolateImu, OnANoisyRampBeatsHoldingTheNewestSample) {
  // 25 ms past the newest of noisy readings (0.02 per axis) of a ramp of 40 m/s^3: holding is off by the ramp
  // (1 m/s^2), the fit by the noise it averages. Over 200 seeded trials.
  double fit_error = 0.0;
  double held_error = 0.0;
  for (std::uint64_t seed = 1; seed <= 200; ++seed) {
    const std::vector<dataset::ImuSample> samples = rampSamples(20, 0.02, seed);
    const std::int64_t t_ns = samples.back().t_ns + 25'000'000;
    const dataset::ImuSample truth = rampSamples(25, 0.0, seed).back();
    fit_error += (extrapolateImu(samples, t_ns).accel_s - truth.accel_s).norm() / 200.0;
    held_error += (samples.back().accel_s - truth.accel_s).norm() / 200.0;
  }
  std::printf("mean accel error 25 ms past the newest sample: fitted %.4f, held %.4f m/s^2\n", fit_error, held_error);
  EXPECT_LT(fit_error, 0.1);
  EXPECT_LT(fit_error, 0.1 * held_error);
}

TEST(ExtrapolateImu, HoldsTheNewestSampleWhenTooFewToFit) {
  const std::vector<dataset::ImuSample> samples = rampSamples(5, 0.0, 1);
  const dataset::ImuSample got = extrapolateImu(samples, samples.back().t_ns + 10'000'000);
  EXPECT_EQ(got.t_ns, samples.back().t_ns + 10'000'000);
  EXPECT_EQ(got.gyro_s, samples.back().gyro_s);
  EXPECT_EQ(got.accel_s, samples.back().accel_s);
}

}  // namespace
}  // namespace cvislam::imu

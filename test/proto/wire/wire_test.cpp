// wire: the project's types survive a trip through the cvislam.v1 messages (to the precision the wire keeps),
// and decoding refuses what is not a valid value, naming the field.
#include "proto/wire/wire.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <random>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include "cvislam/v1/types.pb.h"

namespace cvislam::wire {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;

geometry::SE3d randomPose(std::mt19937& rng) {
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  const Eigen::Vector3d phi(u(rng), u(rng), u(rng));
  return {geometry::SO3d::exp(2.0 * phi), Eigen::Vector3d(100 * u(rng), 100 * u(rng), 10 * u(rng))};
}

TEST(Wire, PoseRoundTripKeepsThePositionExactlyAndTheRotationToFloatPrecision) {
  std::mt19937 rng(7);
  for (int i = 0; i < 100; ++i) {
    const geometry::SE3d T = randomPose(rng);
    v1::Pose message;

    toProto(T, &message);
    auto back = fromProto(message, "pose");

    ASSERT_TRUE(back.ok()) << back.error().toString();
    EXPECT_EQ(back->translation(), T.translation());
    EXPECT_LT((back->so3().inverse() * T.so3()).log().norm(), 1e-6);
    EXPECT_NEAR(back->so3().quaternion().norm(), 1.0, 1e-12);  // renormalised after the float trip
  }
}

TEST(Wire, PoseWithANonFiniteValueIsRefusedNamingTheField) {
  v1::Pose message;
  toProto(geometry::SE3d(), &message);
  message.set_py(std::numeric_limits<double>::infinity());

  auto back = fromProto(message, "keyframe 1:2 T_w_s");

  ASSERT_FALSE(back.ok());
  EXPECT_EQ(back.error().code(), ErrorCode::kInvalidArgument);
  EXPECT_THAT(back.error().message(), AllOf(HasSubstr("keyframe 1:2 T_w_s"), HasSubstr("non-finite")));
}

TEST(Wire, PoseWithAQuaternionOffUnitLengthIsRefusedWithItsNorm) {
  v1::Pose message;
  toProto(geometry::SE3d(), &message);
  message.set_qw(1.01F);

  auto back = fromProto(message, "T_s_c");

  ASSERT_FALSE(back.ok());
  EXPECT_EQ(back.error().code(), ErrorCode::kInvalidArgument);
  EXPECT_THAT(back.error().message(), AllOf(HasSubstr("T_s_c"), HasSubstr("norm 1.01"), HasSubstr("not 1")));
}

TEST(Wire, KeyframeStateRoundTripKeepsEveryValueToFloatPrecision) {
  std::mt19937 rng(11);
  KeyframeStateValues state;
  state.T_w_s = randomPose(rng);
  state.v_w = Eigen::Vector3d(1.25, -0.5, 3.0);
  state.bias.gyro = Eigen::Vector3d(1e-3, -2e-3, 3e-3);
  state.bias.accel = Eigen::Vector3d(0.05, 0.1, -0.15);
  v1::KeyframeState message;

  toProto(42, state, &message);
  toProto(42, state, &message);  // written twice into one message: the repeated fields do not grow
  auto back = fromProto(message, "state");

  ASSERT_TRUE(back.ok()) << back.error().toString();
  EXPECT_EQ(message.counter(), 42U);
  EXPECT_EQ(message.v_w_size(), 3);
  EXPECT_TRUE(back->v_w.isApprox(state.v_w, 1e-7));
  EXPECT_TRUE(back->bias.gyro.isApprox(state.bias.gyro, 1e-6));
  EXPECT_TRUE(back->bias.accel.isApprox(state.bias.accel, 1e-6));
  EXPECT_EQ(back->T_w_s.translation(), state.T_w_s.translation());
}

TEST(Wire, KeyframeStateWithoutPoseOrWithAShortColumnIsRefused) {
  v1::KeyframeState no_pose;
  v1::KeyframeState short_bias;
  toProto(1, KeyframeStateValues{}, &short_bias);
  short_bias.mutable_bias_accel()->RemoveLast();

  auto a = fromProto(no_pose, "update");
  auto b = fromProto(short_bias, "update");

  ASSERT_FALSE(a.ok());
  EXPECT_THAT(a.error().message(), HasSubstr("update: no pose"));
  ASSERT_FALSE(b.ok());
  EXPECT_THAT(b.error().message(), HasSubstr("update bias_accel: 2 values, expected 3"));
}

TEST(Wire, CameraCalibrationRoundTripKeepsTheIntrinsicsAndTheExtrinsics) {
  dataset::CameraCalibration calibration;  // EuRoC cam0
  calibration.distortion_coefficients = {-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05};
  std::mt19937 rng(3);
  // A turned camera a few centimetres from the IMU, as on a real rig.
  const geometry::SE3d T_s_c(randomPose(rng).so3(), Eigen::Vector3d(-0.0216, -0.0647, 0.0098));
  v1::CameraCalibration message;

  toProto(calibration, T_s_c, &message);
  auto back = fromProto(message, "cam0");

  ASSERT_TRUE(back.ok()) << back.error().toString();
  const auto& [c, T] = *back;
  EXPECT_EQ(c.width, 752);
  EXPECT_EQ(c.height, 480);
  EXPECT_EQ(c.fx, calibration.fx);
  EXPECT_EQ(c.cy, calibration.cy);
  EXPECT_EQ(c.distortion, dataset::DistortionModel::kRadialTangential);
  EXPECT_EQ(c.distortion_coefficients, calibration.distortion_coefficients);
  EXPECT_EQ(T.translation(), T_s_c.translation());
  EXPECT_EQ(c.T_b_c.translation(), T_s_c.translation());
}

TEST(Wire, CameraCalibrationWithABadValueIsRefusedNamingIt) {
  v1::CameraCalibration valid;
  toProto(dataset::CameraCalibration{}, geometry::SE3d(), &valid);
  v1::CameraCalibration zero_width = valid;
  zero_width.set_width(0);
  v1::CameraCalibration negative_focal = valid;
  negative_focal.set_fx(-1.0);
  v1::CameraCalibration three_coefficients = valid;
  three_coefficients.mutable_distortion_coefficients()->RemoveLast();
  v1::CameraCalibration nan_coefficient = valid;
  nan_coefficient.set_distortion_coefficients(2, std::nan(""));
  v1::CameraCalibration no_extrinsics = valid;
  no_extrinsics.clear_t_s_c();

  EXPECT_THAT(fromProto(zero_width, "cam0").error().message(), HasSubstr("cam0: image size 0x480"));
  EXPECT_THAT(fromProto(negative_focal, "cam0").error().message(), HasSubstr("focal lengths must be positive"));
  EXPECT_THAT(fromProto(three_coefficients, "cam0").error().message(), HasSubstr("3 distortion coefficients"));
  EXPECT_THAT(fromProto(nan_coefficient, "cam0").error().message(), HasSubstr("non-finite distortion coefficient"));
  EXPECT_THAT(fromProto(no_extrinsics, "cam0").error().message(), HasSubstr("no T_s_c"));
}

TEST(Wire, ImuCalibrationRoundTripsAndANonPositiveDensityIsRefused) {
  imu::ImuNoise noise;
  v1::ImuCalibration message;
  toProto(noise, 200.0, &message);
  v1::ImuCalibration zero_walk = message;
  zero_walk.set_gyro_random_walk(0.0);
  v1::ImuCalibration no_rate = message;
  no_rate.set_rate_hz(0.0);

  auto back = fromProto(message, "imu");
  auto bad_walk = fromProto(zero_walk, "hello imu");
  auto bad_rate = fromProto(no_rate, "hello imu");

  ASSERT_TRUE(back.ok()) << back.error().toString();
  EXPECT_EQ(back->gyro_noise_density, noise.gyro_noise_density);
  EXPECT_EQ(back->accel_random_walk, noise.accel_random_walk);
  ASSERT_FALSE(bad_walk.ok());
  EXPECT_THAT(bad_walk.error().message(), AllOf(HasSubstr("hello imu"), HasSubstr("gyro_random_walk")));
  ASSERT_FALSE(bad_rate.ok());
  EXPECT_THAT(bad_rate.error().message(), HasSubstr("rate_hz must be positive"));
}

// Finite but physically absurd values are refused like non-finite ones: each would become inf or NaN once a
// shared map or its optimisation used it.
TEST(Wire, AbsurdFiniteCalibrationsAndPosesAreRefusedNamingTheField) {
  v1::CameraCalibration valid;
  toProto(dataset::CameraCalibration{}, geometry::SE3d(), &valid);
  const auto camera = [&](auto&& change) {
    v1::CameraCalibration c = valid;
    change(c);
    auto decoded = fromProto(c, "cam0");
    return decoded.ok() ? std::string("accepted") : decoded.error().message();
  };
  EXPECT_THAT(camera([](auto& c) { c.set_fx(1e-300); }), HasSubstr("not in [1, 1e5]"));
  EXPECT_THAT(camera([](auto& c) { c.set_fy(1e300); }), HasSubstr("not in [1, 1e5]"));
  EXPECT_THAT(camera([](auto& c) { c.set_cx(1e9); }), HasSubstr("far outside the image"));
  EXPECT_THAT(camera([](auto& c) { c.set_distortion_coefficients(0, 1e300); }), HasSubstr("beyond +-10"));
  EXPECT_THAT(camera([](auto& c) { c.set_rate_hz(-20.0); }), HasSubstr("rate_hz"));
  EXPECT_THAT(camera([](auto& c) { c.mutable_t_s_c()->set_px(1e300); }), HasSubstr("cam0 T_s_c"));
  EXPECT_THAT(camera([](auto& c) { c.mutable_t_s_c()->set_px(50.0); }), HasSubstr("m from the IMU"));
  EXPECT_EQ(camera([](auto&) {}), "accepted");

  v1::ImuCalibration imu;
  toProto(imu::ImuNoise{}, 200.0, &imu);
  for (double bad : {1e-300, 1e300}) {
    v1::ImuCalibration noisy = imu;
    noisy.set_accel_noise_density(bad);
    auto decoded = fromProto(noisy, "imu");
    ASSERT_FALSE(decoded.ok()) << bad;
    EXPECT_THAT(decoded.error().message(), HasSubstr("imu"));
  }

  v1::Pose far;
  toProto(geometry::SE3d(), &far);
  far.set_py(-1e300);
  auto decoded = fromProto(far, "keyframe 3:2 T_w_s");
  ASSERT_FALSE(decoded.ok());
  EXPECT_THAT(decoded.error().message(), HasSubstr("keyframe 3:2 T_w_s: a position"));
}

TEST(Wire, AngleCodeRoundTripsWithinHalfAStepAndWrapsAroundTheTurn) {
  constexpr float kStepDeg = 360.0F / 256.0F;
  for (float angle = 0.0F; angle < 360.0F; angle += 0.37F) {
    const float back = decodeAngle(encodeAngle(angle));
    float error = std::abs(back - angle);
    error = std::min(error, 360.0F - error);  // 359.9 deg encodes as 0
    EXPECT_LE(error, 0.5F * kStepDeg + 1e-4F) << angle;
  }
  EXPECT_EQ(encodeAngle(-90.0F), encodeAngle(270.0F));
  EXPECT_EQ(encodeAngle(720.0F + 45.0F), encodeAngle(45.0F));
  EXPECT_EQ(encodeAngle(359.9F), 0);
  EXPECT_EQ(encodeAngle(90.0F), 64);
}

}  // namespace
}  // namespace cvislam::wire

namespace cvislam::wire {
namespace {

TEST(DescriptorWords, ThirtyTwoBytesGoIntoFourWordsAndBackInTheProtocolsByteOrder) {
  std::array<std::uint8_t, 32> bytes{};
  for (std::size_t i = 0; i < bytes.size(); ++i) bytes[i] = static_cast<std::uint8_t>(7 * i + 3);
  google::protobuf::RepeatedField<std::uint64_t> words;
  packDescriptor(bytes.data(), &words);
  ASSERT_EQ(words.size(), 4);
  // Byte 8w+b is bits 8b..8b+7 of word w: byte 9 (= 66) is the second byte of word 1.
  EXPECT_EQ((words.Get(1) >> 8U) & 0xFFU, 66U);
  std::array<std::uint8_t, 32> back{};
  unpackDescriptor(words.data(), back.data());
  EXPECT_EQ(back, bytes);
}

}  // namespace
}  // namespace cvislam::wire

// Test checks on calibrations: two cameras with the same image size, pinhole intrinsics and distortion.
#pragma once

#include <cstddef>

#include <gtest/gtest.h>

#include "common/dataset/types.hpp"

namespace cvislam::test {

inline void expectSameIntrinsics(const dataset::CameraCalibration& a, const dataset::CameraCalibration& b) {
  EXPECT_EQ(a.width, b.width);
  EXPECT_EQ(a.height, b.height);
  EXPECT_DOUBLE_EQ(a.fx, b.fx);
  EXPECT_DOUBLE_EQ(a.fy, b.fy);
  EXPECT_DOUBLE_EQ(a.cx, b.cx);
  EXPECT_DOUBLE_EQ(a.cy, b.cy);
  EXPECT_EQ(a.distortion, b.distortion);
  for (std::size_t i = 0; i < 4; ++i) EXPECT_DOUBLE_EQ(a.distortion_coefficients[i], b.distortion_coefficients[i]);
}

}  // namespace cvislam::test

// A small, valid EuRoC sequence written with EurocWriter, for tests that then corrupt a copy of it.
#pragma once

#include <filesystem>

#include "common/dataset/euroc_writer.hpp"

namespace cvislam::test {

struct SmallSequenceSpec {
  int frames = 6;
  bool stereo = true;
  int imu_per_frame = 10;  // 200 Hz IMU for 20 Hz frames
  int width = 64;
  int height = 48;
};

// Writes SEQ/mav0 with cam0 (and cam1), imu0 and ground truth. Frame k is at 1e9 + k * 50 ms.
void writeSmallSequence(const std::filesystem::path& seq, const SmallSequenceSpec& spec = {});

dataset::CameraCalibration smallCamera(const SmallSequenceSpec& spec, int index);

}  // namespace cvislam::test

// The EuRoC MAV calibration (ASL sensor.yaml of cam0, cam1 and imu0), built in: the defaults for tools that
// must work without a dataset (the simulator). test/common/camera/camera_model_test.cpp checks them against
// the sensor.yaml files in the shared data.
#pragma once

#include "common/dataset/types.hpp"

namespace cvislam::dataset {

CameraCalibration eurocCam0();
CameraCalibration eurocCam1();
ImuCalibration eurocImu();

}  // namespace cvislam::dataset

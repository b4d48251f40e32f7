#include "agent_rt/sources/kalibr_rig.hpp"

#include <cstdlib>
#include <string>

#include "common/dataset/kalibr.hpp"

namespace cvislam::agent {
namespace {

// The images are the recording's: a calibration for another resolution cannot describe them.
Status sameResolution(const dataset::CameraCalibration& kalibr, const dataset::CameraCalibration& recording,
                      const std::filesystem::path& file) {
  if (kalibr.width == recording.width && kalibr.height == recording.height) return Status::Ok();
  return Error{ErrorCode::kInvalidArgument,
               file.string() + ": " + kalibr.name + " is calibrated at " + std::to_string(kalibr.width) + "x" +
                   std::to_string(kalibr.height) + " but the recording's " + kalibr.name + " images are " +
                   std::to_string(recording.width) + "x" + std::to_string(recording.height)};
}

// One shift moves the rig's frames; a stereo pair is taken together, so its cameras must agree.
Status sameShift(const dataset::KalibrCamera& cam0, const dataset::KalibrCamera& cam1,
                 const std::filesystem::path& file) {
  if (std::llabs(cam1.timeshift_cam_imu_ns - cam0.timeshift_cam_imu_ns) <= 1'000'000) return Status::Ok();
  return Error{ErrorCode::kInvalidArgument, file.string() +
                                                ": cam0 and cam1 have timeshift_cam_imu more than 1 ms apart; "
                                                "a stereo pair is taken at one time"};
}

}  // namespace

Result<std::int64_t> applyKalibrFiles(const RecordingOptions& options, SensorRig& rig) {
  std::int64_t shift_ns = 0;
  if (!options.calibration.empty()) {
    auto chain = dataset::readKalibrCamchain(options.calibration);
    if (!chain) return chain.error();
    dataset::CameraCalibration cam0 = (*chain)[0].calibration;
    if (Status s = sameResolution(cam0, rig.cam0, options.calibration); !s.ok()) return s.error();
    cam0.rate_hz = rig.cam0.rate_hz;  // Kalibr's files do not carry it
    rig.cam0 = cam0;
    shift_ns = (*chain)[0].timeshift_cam_imu_ns;
    if (rig.cam1 && chain->size() > 1) {
      dataset::CameraCalibration cam1 = (*chain)[1].calibration;
      if (Status s = sameResolution(cam1, *rig.cam1, options.calibration); !s.ok()) return s.error();
      cam1.rate_hz = rig.cam1->rate_hz;
      if (Status s = sameShift((*chain)[0], (*chain)[1], options.calibration); !s.ok()) return s.error();
      rig.cam1 = cam1;
    } else {
      rig.cam1.reset();
    }
    if (rig.imu) rig.imu->T_b_i = geometry::SE3d();
  }
  if (!options.imu_calibration.empty()) {
    auto imu = dataset::readKalibrImu(options.imu_calibration);
    if (!imu) return imu.error();
    rig.imu = imu->calibration;
  }
  rig.timeshift_cam_imu_ns = shift_ns;
  return shift_ns;
}

Result<SensorRig> rigFromKalibrFiles(const std::filesystem::path& calibration,
                                     const std::filesystem::path& imu_calibration) {
  if (calibration.empty()) {
    return Error{ErrorCode::kInvalidArgument,
                 "no calibration given: a stream without files needs Kalibr's camera chain (camchain-imucam.yaml)"};
  }
  auto chain = dataset::readKalibrCamchain(calibration);
  if (!chain) return chain.error();
  SensorRig rig;
  rig.cam0 = (*chain)[0].calibration;
  rig.timeshift_cam_imu_ns = (*chain)[0].timeshift_cam_imu_ns;
  if (chain->size() > 1) {
    if (Status s = sameShift((*chain)[0], (*chain)[1], calibration); !s.ok()) return s.error();
    rig.cam1 = (*chain)[1].calibration;
  }
  if (!imu_calibration.empty()) {
    auto imu = dataset::readKalibrImu(imu_calibration);
    if (!imu) return imu.error();
    rig.imu = imu->calibration;
  }
  return rig;
}

}  // namespace cvislam::agent

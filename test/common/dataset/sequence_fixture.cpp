#include "test/common/dataset/sequence_fixture.hpp"

#include <stdexcept>

namespace cvislam::test {

dataset::CameraCalibration smallCamera(const SmallSequenceSpec& spec, int index) {
  dataset::CameraCalibration cam;
  cam.width = spec.width;
  cam.height = spec.height;
  cam.fx = 40.0;
  cam.fy = 41.0;
  cam.cx = spec.width / 2.0;
  cam.cy = spec.height / 2.0;
  cam.distortion_coefficients = {-0.28, 0.07, 1e-4, -2e-5};
  cam.T_b_c = geometry::SE3d(geometry::SO3d::exp(Eigen::Vector3d(0.01, -0.02, 1.57)),
                             Eigen::Vector3d(-0.02, index == 0 ? -0.06 : 0.05, 0.01));
  return cam;
}

void writeSmallSequence(const std::filesystem::path& seq, const SmallSequenceSpec& spec) {
  dataset::EurocWriterOptions options;
  options.cameras.push_back(smallCamera(spec, 0));
  if (spec.stereo) options.cameras.push_back(smallCamera(spec, 1));
  options.imu = dataset::ImuCalibration{};
  auto writer = dataset::EurocWriter::create(seq, options);
  if (!writer) throw std::runtime_error(writer.error().toString());
  const std::int64_t t0 = 1'000'000'000;
  const std::int64_t frame_dt = 50'000'000;
  for (int k = 0; k < spec.frames; ++k) {
    const std::int64_t t = t0 + k * frame_dt;
    for (int cam = 0; cam < (spec.stereo ? 2 : 1); ++cam) {
      dataset::GrayImage image(spec.width, spec.height);
      for (int y = 0; y < spec.height; ++y) {
        for (int x = 0; x < spec.width; ++x)
          image.at(x, y) = static_cast<std::uint8_t>((x * 7 + y * 3 + k * 11 + cam) & 0xff);
      }
      if (Status st = writer->addImage(cam, t, image); !st) throw std::runtime_error(st.error().toString());
    }
    for (int i = 0; i < spec.imu_per_frame; ++i) {
      dataset::ImuSample s;
      s.t_ns = t + i * (frame_dt / spec.imu_per_frame);
      s.gyro_s = Eigen::Vector3d(0.01 * k, -0.02, 0.1 + 1e-3 * i);
      s.accel_s = Eigen::Vector3d(9.81, 0.1 * i, -0.3);
      if (Status st = writer->addImu(s); !st) throw std::runtime_error(st.error().toString());
    }
    dataset::GroundTruthState gt;
    gt.t_ns = t;
    gt.T_w_b =
        geometry::SE3d(geometry::SO3d::exp(Eigen::Vector3d(0.0, 0.0, 0.1 * k)), Eigen::Vector3d(0.1 * k, 1.0, 1.5));
    gt.v_w = Eigen::Vector3d(2.0, 0.0, 0.0);
    gt.gyro_bias = Eigen::Vector3d(-0.002, 0.02, 0.07);
    gt.accel_bias = Eigen::Vector3d(-0.01, 0.1, 0.09);
    gt.has_velocity_and_biases = true;
    if (Status st = writer->addGroundTruth(gt); !st) throw std::runtime_error(st.error().toString());
  }
  if (Status st = writer->close(); !st) throw std::runtime_error(st.error().toString());
}

}  // namespace cvislam::test

#include "common/dataset/euroc_writer.hpp"

#include <string>

#include "common/core/text.hpp"
#include "common/dataset/calibration.hpp"
#include "common/dataset/image_codecs.hpp"

namespace cvislam::dataset {

namespace {

// One CSV file being written, with the last timestamp so that time can only move forward.
struct CsvStream {
  std::filesystem::path path;
  std::ofstream out;
  std::int64_t last_t_ns = -1;
};

}  // namespace

struct EurocWriter::Impl {
  using Stream = CsvStream;
  std::filesystem::path mav0;
  std::vector<CameraCalibration> cameras;
  std::vector<Stream> camera_csv;
  std::optional<Stream> imu_csv;
  std::optional<Stream> gt_csv;
  bool closed = false;

  static Status open(Stream& s, const std::filesystem::path& path, const char* header) {
    s.path = path;
    s.out.open(path, std::ios::binary | std::ios::trunc);
    if (!s.out) return Error{ErrorCode::kIoError, path.string() + ": cannot open for writing"};
    s.out << header << '\n';
    return Status::Ok();
  }

  static Status checkTime(Stream& s, std::int64_t t_ns) {
    if (t_ns < 0 || t_ns <= s.last_t_ns) {
      return Error{ErrorCode::kInvalidArgument, s.path.string() + ": timestamp " + std::to_string(t_ns) +
                                                    " ns must be >= 0 and after the previous one (" +
                                                    std::to_string(s.last_t_ns) + " ns)"};
    }
    s.last_t_ns = t_ns;
    return Status::Ok();
  }

  static void appendValues(std::string& line, const Eigen::Vector3d& v) {
    for (int i = 0; i < 3; ++i) {
      line += ',';
      line += text::formatDouble(v(i));
    }
  }
};

Status EurocWriterOptions::validate() const {
  if (cameras.empty() || cameras.size() > 2) {
    return Error{ErrorCode::kInvalidArgument, "EuRoC writer: give cam0 and optionally cam1"};
  }
  for (const CameraCalibration& cam : cameras) {
    if (Status st = dataset::validate(cam); !st) return st;
  }
  if (imu) return dataset::validate(*imu);
  return Status::Ok();
}

EurocWriter::EurocWriter(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
EurocWriter::EurocWriter(EurocWriter&&) noexcept = default;
EurocWriter& EurocWriter::operator=(EurocWriter&&) noexcept = default;
EurocWriter::~EurocWriter() {
  if (impl_ && !impl_->closed) (void)close();
}

const std::filesystem::path& EurocWriter::mav0() const {
  return impl_->mav0;
}

Result<EurocWriter> EurocWriter::create(const std::filesystem::path& sequence_folder,
                                        const EurocWriterOptions& options) {
  if (Status st = options.validate(); !st) return st.error();
  auto impl = std::make_unique<Impl>();
  impl->mav0 = sequence_folder / "mav0";
  std::error_code ec;
  if (std::filesystem::exists(impl->mav0, ec) && !options.overwrite) {
    return Error{ErrorCode::kInvalidArgument, impl->mav0.string() + " already exists; remove it or allow overwriting"};
  }
  std::filesystem::create_directories(impl->mav0, ec);
  if (ec) return Error{ErrorCode::kIoError, impl->mav0.string() + ": cannot create folder: " + ec.message()};

  if (Status st = [&]() -> Status {
        std::ofstream body(impl->mav0 / "body.yaml");
        body << "%YAML:1.0\ncomment: 'The body frame is the IMU frame (imu0).'\n";
        return body ? Status::Ok() : Status(Error{ErrorCode::kIoError, "cannot write body.yaml"});
      }();
      !st) {
    return st.error();
  }

  impl->cameras = options.cameras;
  impl->camera_csv.resize(options.cameras.size());
  for (std::size_t i = 0; i < options.cameras.size(); ++i) {
    const std::string name = "cam" + std::to_string(i);
    impl->cameras[i].name = name;
    const std::filesystem::path folder = impl->mav0 / name;
    std::filesystem::create_directories(folder / "data", ec);
    if (ec) return Error{ErrorCode::kIoError, folder.string() + ": cannot create folder: " + ec.message()};
    if (Status st = writeCameraCalibration(folder / "sensor.yaml", impl->cameras[i]); !st) return st.error();
    if (Status st = Impl::open(impl->camera_csv[i], folder / "data.csv", "#timestamp [ns],filename"); !st) {
      return st.error();
    }
  }
  if (options.imu) {
    const std::filesystem::path folder = impl->mav0 / "imu0";
    std::filesystem::create_directories(folder, ec);
    if (Status st = writeImuCalibration(folder / "sensor.yaml", *options.imu); !st) return st.error();
    impl->imu_csv.emplace();
    if (Status st = Impl::open(*impl->imu_csv, folder / "data.csv",
                               "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
                               "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]");
        !st) {
      return st.error();
    }
  }
  if (options.ground_truth) {
    const std::filesystem::path folder = impl->mav0 / "state_groundtruth_estimate0";
    std::filesystem::create_directories(folder, ec);
    impl->gt_csv.emplace();
    if (Status st = Impl::open(
            *impl->gt_csv, folder / "data.csv",
            "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
            "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], "
            "b_w_RS_S_z [rad s^-1], b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]");
        !st) {
      return st.error();
    }
  }
  return EurocWriter(std::move(impl));
}

Status EurocWriter::addImage(int camera, std::int64_t t_ns, const GrayImage& image) {
  if (camera < 0 || static_cast<std::size_t>(camera) >= impl_->cameras.size()) {
    return Error{ErrorCode::kInvalidArgument, "addImage: no camera " + std::to_string(camera)};
  }
  const auto index = static_cast<std::size_t>(camera);
  const CameraCalibration& cal = impl_->cameras[index];
  if (image.width != cal.width || image.height != cal.height) {
    return Error{ErrorCode::kInvalidArgument, "addImage: image is " + std::to_string(image.width) + "x" +
                                                  std::to_string(image.height) + ", " + cal.name + " is " +
                                                  std::to_string(cal.width) + "x" + std::to_string(cal.height)};
  }
  Impl::Stream& s = impl_->camera_csv[index];
  if (Status st = Impl::checkTime(s, t_ns); !st) return st;
  const std::string filename = std::to_string(t_ns) + ".png";
  if (Status st = writeGrayPng(impl_->mav0 / cal.name / "data" / filename, image); !st) return st;
  s.out << t_ns << ',' << filename << '\n';
  return Status::Ok();
}

Status EurocWriter::addImu(const ImuSample& sample) {
  if (!impl_->imu_csv) return Error{ErrorCode::kInvalidArgument, "addImu: the writer was created without imu0"};
  if (Status st = Impl::checkTime(*impl_->imu_csv, sample.t_ns); !st) return st;
  std::string line = std::to_string(sample.t_ns);
  Impl::appendValues(line, sample.gyro_s);
  Impl::appendValues(line, sample.accel_s);
  impl_->imu_csv->out << line << '\n';
  return Status::Ok();
}

Status EurocWriter::addGroundTruth(const GroundTruthState& state) {
  if (!impl_->gt_csv) {
    return Error{ErrorCode::kInvalidArgument, "addGroundTruth: the writer was created without ground truth"};
  }
  if (Status st = Impl::checkTime(*impl_->gt_csv, state.t_ns); !st) return st;
  std::string line = std::to_string(state.t_ns);
  Impl::appendValues(line, state.T_w_b.translation());
  const Eigen::Quaterniond& q = state.T_w_b.quaternion();
  for (double v : {q.w(), q.x(), q.y(), q.z()}) {
    line += ',';
    line += text::formatDouble(v);
  }
  Impl::appendValues(line, state.v_w);
  Impl::appendValues(line, state.gyro_bias);
  Impl::appendValues(line, state.accel_bias);
  impl_->gt_csv->out << line << '\n';
  return Status::Ok();
}

Status EurocWriter::close() {
  if (impl_->closed) return Status::Ok();
  impl_->closed = true;
  Status result;
  const auto finish = [&](Impl::Stream& s) {
    s.out.close();
    if (!s.out && result.ok()) result = Error{ErrorCode::kIoError, s.path.string() + ": write failed (disk full?)"};
  };
  for (auto& s : impl_->camera_csv) finish(s);
  if (impl_->imu_csv) finish(*impl_->imu_csv);
  if (impl_->gt_csv) finish(*impl_->gt_csv);
  return result;
}

}  // namespace cvislam::dataset

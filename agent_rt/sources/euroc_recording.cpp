#include "agent_rt/sources/euroc_recording.hpp"

#include <filesystem>
#include <string>
#include <vector>

#include "agent_rt/sources/kalibr_rig.hpp"
#include "common/dataset/png_gray.hpp"

namespace cvislam::agent {
namespace {

class EurocRecording final : public Recording {
 public:
  EurocRecording(dataset::EurocSequence sequence, SensorRig rig, std::vector<dataset::RigFrame> frames, bool simulated)
      : sequence_(std::move(sequence)), rig_(std::move(rig)), frames_(std::move(frames)), simulated_(simulated) {}

  [[nodiscard]] const SensorRig& rig() const override { return rig_; }
  [[nodiscard]] std::span<const dataset::ImuSample> imu() const override { return sequence_.imu(); }
  [[nodiscard]] std::span<const dataset::RigFrame> rigFrames() const override { return frames_; }
  [[nodiscard]] const Diagnostics& diagnostics() const override { return sequence_.diagnostics(); }
  [[nodiscard]] std::string describe() const override { return "EuRoC folder " + sequence_.root().string(); }
  [[nodiscard]] bool simulated() const override { return simulated_; }
  [[nodiscard]] Status loadImageInto(int camera, std::size_t frame, std::span<std::uint8_t> pixels) override {
    return sequence_.loadImageInto(camera, frame, pixels, png_);
  }

 private:
  dataset::EurocSequence sequence_;
  SensorRig rig_;
  std::vector<dataset::RigFrame> frames_;  // the sequence's, moved onto the IMU's clock
  bool simulated_;
  dataset::GrayPngDecoder png_;  // the loading thread's; its buffers settle at the first frame's size
};

}  // namespace

Result<std::unique_ptr<Recording>> openEurocRecording(const RecordingOptions& options) {
  dataset::EurocReaderOptions reader;
  reader.require_imu = options.require_imu;
  auto sequence = dataset::EurocSequence::open(options.dataset, reader);
  if (!sequence) return sequence.error().withContext("dataset " + options.dataset.string());
  SensorRig rig = sensorRigOf(*sequence);
  std::vector<dataset::RigFrame> frames(sequence->rigFrames().begin(), sequence->rigFrames().end());
  auto shift_ns = applyKalibrFiles(options, rig);
  if (!shift_ns) return shift_ns.error();
  for (dataset::RigFrame& f : frames) f.t_ns += *shift_ns;
  // The simulator writes mission.yaml beside its agents' folders.
  const bool simulated = std::filesystem::exists(options.dataset / "mission.yaml") ||
                         std::filesystem::exists(options.dataset.parent_path() / "mission.yaml");
  return std::unique_ptr<Recording>(
      std::make_unique<EurocRecording>(std::move(sequence).value(), std::move(rig), std::move(frames), simulated));
}

}  // namespace cvislam::agent

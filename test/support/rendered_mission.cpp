#include "test/support/rendered_mission.hpp"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <fstream>

#include "test/sim/mission_writer.hpp"

namespace cvislam::test {

namespace fs = std::filesystem;

namespace {

// Written last: a folder without it is a rendering that did not finish.
constexpr const char* kCompleteMarker = ".complete";

// An exclusive lock on a file beside the mission's folder, held for the object's life.
class FolderLock {
 public:
  explicit FolderLock(const fs::path& path) : fd_(::open(path.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644)) {
    if (fd_ >= 0) ::flock(fd_, LOCK_EX);
  }
  ~FolderLock() {
    if (fd_ >= 0) ::close(fd_);  // releases the lock
  }
  FolderLock(const FolderLock&) = delete;
  FolderLock& operator=(const FolderLock&) = delete;
  [[nodiscard]] bool held() const { return fd_ >= 0; }

 private:
  int fd_;
};

// Renders into `dir` through a sibling folder renamed into place, so that a reader never sees half a mission.
Status renderInto(const MissionSpec& spec, const fs::path& dir) {
  const fs::path partial = dir.string() + ".partial";
  std::error_code ec;
  fs::remove_all(partial, ec);
  fs::remove_all(dir, ec);
  if (Status s = sim::renderPreset(spec.preset, spec.seed, spec.duration_s, spec.stereo, partial, spec.threads);
      !s.ok()) {
    return s;
  }
  std::ofstream(partial / kCompleteMarker) << spec.name() << "\n";
  fs::rename(partial, dir, ec);
  if (ec) return Error{ErrorCode::kIoError, "cannot move " + partial.string() + " into place: " + ec.message()};
  return Status::Ok();
}

Status renderLocked(const MissionSpec& spec, const fs::path& root, bool fresh) {
  std::error_code ec;
  fs::create_directories(root, ec);
  const fs::path dir = root / spec.name();
  FolderLock lock(dir.string() + ".lock");
  if (!lock.held()) {
    return Error{ErrorCode::kIoError, "cannot lock " + dir.string() + ".lock: " + std::strerror(errno)};
  }
  if (!fresh && fs::exists(dir / kCompleteMarker)) return Status::Ok();
  return renderInto(spec, dir);
}

}  // namespace

std::string MissionSpec::name() const {
  char duration[32];
  std::snprintf(duration, sizeof(duration), "%g", duration_s);
  return preset + "-seed" + std::to_string(seed) + "-" + duration + "s-" + (stereo ? "stereo" : "mono");
}

Result<fs::path> renderedMission(const MissionSpec& spec, const fs::path& private_dir) {
  const char* shared = std::getenv("CVISLAM_TEST_MISSIONS");
  if (shared == nullptr || *shared == '\0') {
    if (Status s = sim::renderPreset(spec.preset, spec.seed, spec.duration_s, spec.stereo, private_dir, spec.threads);
        !s.ok()) {
      return s.error();
    }
    return private_dir;
  }
  if (Status s = renderLocked(spec, shared, /*fresh=*/false); !s.ok()) return s.error();
  return fs::path(shared) / spec.name();
}

Status renderSharedMission(const MissionSpec& spec, const fs::path& root) {
  return renderLocked(spec, root, /*fresh=*/true);
}

void linkedCopy(const fs::path& source, const fs::path& target) {
  fs::create_directories(target);
  std::error_code ec;
  fs::copy(source, target, fs::copy_options::recursive | fs::copy_options::create_hard_links, ec);
  if (!ec) return;
  // Another file system (a private /tmp, say): copy instead.
  fs::remove_all(target);
  fs::create_directories(target);
  fs::copy(source, target, fs::copy_options::recursive);
}

}  // namespace cvislam::test

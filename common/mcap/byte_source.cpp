#include "common/mcap/byte_source.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <string>
#include <utility>

namespace cvislam::mcap {
namespace {

class MemorySource final : public Source {
 public:
  explicit MemorySource(std::vector<std::uint8_t> bytes) : bytes_(std::move(bytes)) {}
  [[nodiscard]] std::uint64_t size() const override { return bytes_.size(); }
  Status read(std::uint64_t offset, std::span<std::uint8_t> out) override {
    std::copy_n(bytes_.begin() + static_cast<std::ptrdiff_t>(offset), out.size(), out.begin());
    return {};
  }

 private:
  std::vector<std::uint8_t> bytes_;
};

// A file, read with pread through a read-ahead window: a bag of small unchunked messages would otherwise cost two
// system calls a record.
class FileSource final : public Source {
 public:
  static Result<std::unique_ptr<Source>> open(const std::filesystem::path& path) {
    const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
    if (fd < 0) {
      const int e = errno;
      return Error(e == ENOENT ? ErrorCode::kNotFound : ErrorCode::kIoError,
                   "mcap: cannot open " + path.string() + ": " + std::strerror(e));
    }
    struct stat st {};
    if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
      ::close(fd);
      return Error(ErrorCode::kIoError, "mcap: " + path.string() + " is not a regular file");
    }
    return std::unique_ptr<Source>(new FileSource(fd, static_cast<std::uint64_t>(st.st_size)));
  }
  ~FileSource() override { ::close(fd_); }
  FileSource(const FileSource&) = delete;
  FileSource& operator=(const FileSource&) = delete;

  [[nodiscard]] std::uint64_t size() const override { return size_; }

  Status read(std::uint64_t offset, std::span<std::uint8_t> out) override {
    if (out.size() >= kWindowBytes) return pread(offset, out);
    if (offset < window_offset_ || offset + out.size() > window_offset_ + window_.size()) {
      window_.resize(static_cast<std::size_t>(std::min<std::uint64_t>(kWindowBytes, size_ - offset)));
      window_offset_ = offset;
      if (Status s = pread(offset, window_); !s.ok()) {
        window_.clear();
        return s;
      }
    }
    std::copy_n(window_.begin() + static_cast<std::ptrdiff_t>(offset - window_offset_), out.size(), out.begin());
    return {};
  }

 private:
  static constexpr std::size_t kWindowBytes = std::size_t{1} << 20;

  FileSource(int fd, std::uint64_t size) : fd_(fd), size_(size) {}

  Status pread(std::uint64_t offset, std::span<std::uint8_t> out) const {
    std::size_t done = 0;
    while (done < out.size()) {
      const ssize_t n = ::pread(fd_, out.data() + done, out.size() - done, static_cast<off_t>(offset + done));
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) {
        return Error(ErrorCode::kIoError, "read failed at offset " + std::to_string(offset + done) + ": " +
                                              (n == 0 ? std::string("unexpected end of file") : std::strerror(errno)));
      }
      done += static_cast<std::size_t>(n);
    }
    return {};
  }

  int fd_;
  std::uint64_t size_;
  std::vector<std::uint8_t> window_;
  std::uint64_t window_offset_ = 0;
};

}  // namespace

std::unique_ptr<Source> memorySource(std::vector<std::uint8_t> bytes) {
  return std::make_unique<MemorySource>(std::move(bytes));
}

Result<std::unique_ptr<Source>> openFileSource(const std::filesystem::path& path) {
  return FileSource::open(path);
}

}  // namespace cvislam::mcap

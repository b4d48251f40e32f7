// A mission's feed (mission_feed.hpp) written as an MCAP file: the viewer's channels, schemas and timestamps, so that
// Foxglove, Lichtblick or any MCAP reader replays what a live viewer saw. The server's --record and
// cvislam_mapctl export --mcap both write through it. Not thread-safe: one owner writes.
#pragma once

#include <cstdint>
#include <filesystem>
#include <map>
#include <memory>
#include <vector>

#include "common/core/result.hpp"
#include "server_cloud/viewer/mission_feed.hpp"

namespace cvislam::mcap {
class Writer;
}

namespace cvislam::server::viewer {

class McapRecorder {
 public:
  // Creates (or truncates) the file; the error names it.
  static Result<McapRecorder> create(const std::filesystem::path& file);
  McapRecorder(McapRecorder&&) noexcept;
  McapRecorder& operator=(McapRecorder&&) noexcept;
  ~McapRecorder();  // closes the file if close() was not called

  // Messages of `channels` (the feed's, by index); channels not seen before are added to the file first.
  Status write(const std::vector<FeedChannel>& channels, const std::vector<FeedMessage>& messages);
  // Hands what was written to the operating system: after a crash the file reads up to here.
  Status flush();
  Status close();

  [[nodiscard]] const std::filesystem::path& file() const { return file_; }
  [[nodiscard]] std::uint64_t messages() const { return messages_; }

 private:
  McapRecorder(std::filesystem::path file, std::unique_ptr<mcap::Writer> writer);

  std::filesystem::path file_;
  std::unique_ptr<mcap::Writer> writer_;
  std::map<std::size_t, std::uint16_t> channel_ids_;  // feed channel index -> MCAP channel id
  std::map<std::size_t, std::uint32_t> sequences_;
  std::uint64_t messages_ = 0;
};

}  // namespace cvislam::server::viewer

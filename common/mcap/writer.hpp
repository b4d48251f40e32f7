// Writing MCAP files: a recording that grows message by message and is finished by close().
//
// Schema and Channel records go into the data section as they are added; messages go into chunks (compressed with
// zstd, LZ4 or not at all) that are written once they reach WriterOptions::chunk_bytes, each followed by one
// MessageIndex record per channel. close() writes the last chunk, the DataEnd (with the CRC of everything before it),
// the summary section (Schema, Channel, Statistics, ChunkIndex, AttachmentIndex, MetadataIndex), the SummaryOffset
// records and the Footer (with the summary CRC). What has been written before a crash is readable by a forward scan
// up to the last complete chunk; flush() bounds what a crash can lose.
#pragma once

#include <cstdint>
#include <filesystem>
#include <map>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "common/core/result.hpp"
#include "common/mcap/records.hpp"

namespace cvislam::mcap {

struct WriterOptions {
  std::string profile = "ros2";  // the Header's profile: "ros2" makes the file a ROS 2 bag
  std::string library = "cvislam mcap";
  // Messages in chunks (indexed, compressible); off: Message records straight into the data section.
  bool use_chunks = true;
  // A chunk is written once its uncompressed records reach this size (a single larger message makes its own chunk).
  std::uint64_t chunk_bytes = std::uint64_t{4} << 20;
  Compression compression = Compression::kZstd;
  int zstd_level = 3;  // 1 (fastest) to 19
  bool write_message_indexes = true;
  // The summary section (schemas, channels, statistics and the indexes) and the SummaryOffset records.
  bool write_summary = true;
  bool write_summary_offsets = true;
  // Chunk, data section, summary and attachment CRCs; off writes 0 ("not computed").
  bool write_crcs = true;

  [[nodiscard]] Status validate() const;
};

class Writer {
 public:
  // Creates (or truncates) the file and writes the magic and the Header.
  static Result<Writer> create(const std::filesystem::path& path, WriterOptions options = {});
  // The same into memory; the bytes are in memoryBytes() after close().
  static Result<Writer> createInMemory(WriterOptions options = {});

  Writer(Writer&&) noexcept;
  Writer& operator=(Writer&&) noexcept;
  // Closes the file if close() was not called; an error then is lost, so call close().
  ~Writer();

  // Returns the id of a schema (from 1). Adding one with the same name, encoding and data again returns the same id.
  Result<std::uint16_t> addSchema(std::string_view name, std::string_view encoding, std::string_view data);
  // Returns the id of a new channel (from 1). schema_id is 0 (no schema) or an id from addSchema().
  Result<std::uint16_t> addChannel(std::uint16_t schema_id, std::string_view topic, std::string_view message_encoding,
                                   const std::map<std::string, std::string>& metadata = {});
  // Appends a message of a channel from addChannel(). Messages need not come in log-time order.
  Status write(const Message& message);
  Status writeAttachment(const Attachment& attachment);
  Status writeMetadata(const Metadata& metadata);

  // Writes the open chunk and hands everything written so far to the operating system: after a crash the file
  // reads up to here.
  Status flush();
  // Finishes the file (last chunk, DataEnd, summary, Footer, magic) and closes it. Further calls fail.
  Status close();

  [[nodiscard]] const Statistics& statistics() const;
  // An in-memory writer's bytes (complete after close()); empty for a file.
  [[nodiscard]] const std::vector<std::uint8_t>& memoryBytes() const;

 private:
  struct Impl;
  explicit Writer(std::unique_ptr<Impl> impl);
  static Result<Writer> start(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace cvislam::mcap

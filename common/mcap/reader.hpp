// Reading MCAP files (ROS 2 bags among them) message by message, in file order.
//
// open() checks the magic at the start, reads the Header and, when the file ends with the magic, the Footer and the
// summary section (its CRC checked). next() then scans the data section forward: Schema and Channel records define
// what messages refer to, Chunks ("", "zstd", "lz4") are decompressed and their CRC checked, and the DataEnd's
// data_section_crc is checked against everything before it. A file without a summary, or still being written, is read
// the same way; its messages come out until the point where the file stops, which is then reported as an error.
//
// Hostile input gives an Error naming the file, the record and its byte offset, never a crash: every length is
// checked against the file before anything is read or allocated, and nothing larger than
// ReaderOptions::max_record_bytes (one record, one chunk's compressed or uncompressed records, or the summary
// section) is ever held in memory.
#pragma once

#include <array>
#include <cstdint>
#include <filesystem>
#include <map>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <vector>

#include "common/core/result.hpp"
#include "common/mcap/records.hpp"

namespace cvislam::mcap {

struct ReaderOptions {
  // The largest record content, compressed chunk or uncompressed chunk, and summary section loaded into memory. A
  // larger one is an error (kResourceExhausted), not an allocation. Attachments and unknown records of any size
  // are streamed through, not loaded.
  std::uint64_t max_record_bytes = std::uint64_t{256} << 20;
  // The most bytes of schemas, channels and metadata kept for the whole file: compressed chunks can repeat
  // definitions far beyond the file's size.
  std::uint64_t max_definition_bytes = std::uint64_t{64} << 20;
  // Check the chunk, data section, summary and attachment CRCs (those stored as 0 were not computed and are not
  // checked).
  bool check_crcs = true;
  // Read the summary section at open(). Off: schemas and channels are known only as the scan meets them.
  bool read_summary = true;

  [[nodiscard]] Status validate() const;
};

// The summary section, as far as the file has one.
struct Summary {
  std::optional<Statistics> statistics;
  std::vector<ChunkIndex> chunk_indexes;
  std::vector<AttachmentIndex> attachment_indexes;
  std::vector<MetadataIndex> metadata_indexes;
  std::vector<SummaryOffset> summary_offsets;
};

// One message. `data` points into the reader's buffers and, like `channel` and `schema`, stays valid until the next
// call to next() (the pointers until the reader is destroyed).
struct MessageView : Message {
  const Channel* channel = nullptr;
  const Schema* schema = nullptr;   // nullptr when the channel has no schema (schema_id 0)
  std::uint64_t record_offset = 0;  // the Message record's file offset, or its chunk's
};

// How many records of each kind the scan has met so far (inside chunks included).
struct RecordCounts {
  std::array<std::uint64_t, 256> by_opcode{};
  std::uint64_t messages = 0;
  std::uint64_t chunks = 0;
  std::uint64_t crcs_checked = 0;  // chunk, data section, summary and attachment CRCs that were checked and matched

  [[nodiscard]] std::uint64_t of(Opcode op) const { return by_opcode[static_cast<std::uint8_t>(op)]; }
};

class Reader {
 public:
  // Opens a file. Errors: kNotFound / kIoError for the file itself, kParseError for what is not MCAP or is
  // malformed, kDataError for a CRC mismatch, kResourceExhausted for a record over the limits.
  static Result<Reader> open(const std::filesystem::path& path, ReaderOptions options = {});
  // Reads a file already in memory (tests, fuzzing, a file received over the network); `name` is used in errors.
  static Result<Reader> openBytes(std::vector<std::uint8_t> bytes, ReaderOptions options = {},
                                  std::string name = "<memory>");

  Reader(Reader&&) noexcept;
  Reader& operator=(Reader&&) noexcept;
  ~Reader();

  // The next message in file order: true and `out` filled, false at the end of the data section. An error stops
  // the scan; every later call returns the same error.
  Result<bool> next(MessageView& out);

  [[nodiscard]] const Header& header() const;
  // The file's summary section, if it ends with one and ReaderOptions::read_summary is on.
  [[nodiscard]] const std::optional<Summary>& summary() const;
  // Schemas and channels known so far (from the summary, then as the scan meets them), by id.
  [[nodiscard]] const std::map<std::uint16_t, Schema>& schemas() const;
  [[nodiscard]] const std::map<std::uint16_t, Channel>& channels() const;
  // Metadata records and attachments the scan has met, in file order.
  [[nodiscard]] const std::vector<Metadata>& metadata() const;
  [[nodiscard]] const std::vector<AttachmentInfo>& attachments() const;
  [[nodiscard]] const RecordCounts& counts() const;
  [[nodiscard]] std::uint64_t fileSize() const;

 private:
  struct Impl;
  explicit Reader(std::unique_ptr<Impl> impl);
  static Result<Reader> start(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace cvislam::mcap

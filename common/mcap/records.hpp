// The MCAP records the reader and the writer share (MCAP format version 0, https://mcap.dev/spec).
//
// A file is the magic, a Header, the data section (Schema, Channel, Message, Chunk, MessageIndex, Attachment,
// Metadata records), a DataEnd, an optional summary section (Schema, Channel, Statistics, ChunkIndex,
// AttachmentIndex, MetadataIndex), optional SummaryOffset records, a Footer and the magic again. Every record is an
// opcode byte, a little-endian u64 content length and the content; records may grow new trailing fields, so readers
// skip what follows the fields they know. All times are nanoseconds (the spec leaves the epoch to the writer; ROS 2
// bags use the Unix epoch).
#pragma once

#include <array>
#include <cstdint>
#include <map>
#include <span>
#include <string>
#include <string_view>

namespace cvislam::mcap {

inline constexpr std::array<std::uint8_t, 8> kMagic = {0x89, 'M', 'C', 'A', 'P', '0', '\r', '\n'};
// Opcode byte and u64 content length in front of every record.
inline constexpr std::uint64_t kRecordPrefixBytes = 9;

enum class Opcode : std::uint8_t {
  kHeader = 0x01,
  kFooter = 0x02,
  kSchema = 0x03,
  kChannel = 0x04,
  kMessage = 0x05,
  kChunk = 0x06,
  kMessageIndex = 0x07,
  kChunkIndex = 0x08,
  kAttachment = 0x09,
  kAttachmentIndex = 0x0A,
  kStatistics = 0x0B,
  kMetadata = 0x0C,
  kMetadataIndex = 0x0D,
  kSummaryOffset = 0x0E,
  kDataEnd = 0x0F,
};

// "Schema", "Chunk", ... or "opcode 0x42" for one the spec does not define.
std::string opcodeName(std::uint8_t opcode);

// Chunk compression. The names in the file are "", "zstd" and "lz4" (the LZ4 frame format).
enum class Compression : std::uint8_t { kNone, kZstd, kLz4 };
std::string_view compressionName(Compression compression);

struct Header {
  std::string profile;  // "ros2" for ROS 2 bags; "" when the writer names none
  std::string library;  // the writing library, free text
};

// A message type. id 0 is reserved: a channel with schema_id 0 has no schema.
struct Schema {
  std::uint16_t id = 0;
  std::string name;      // e.g. "sensor_msgs/msg/Image"
  std::string encoding;  // e.g. "ros2msg"; "" only with empty data
  std::string data;      // the definition's bytes (text for ros2msg)

  bool operator==(const Schema&) const = default;
};

// A topic. Channel id 0 is valid (the npm writer starts there).
struct Channel {
  std::uint16_t id = 0;
  std::uint16_t schema_id = 0;  // 0: no schema
  std::string topic;
  std::string message_encoding;  // e.g. "cdr"
  std::map<std::string, std::string> metadata;

  bool operator==(const Channel&) const = default;
};

// One message as written: the data is not owned.
struct Message {
  std::uint16_t channel_id = 0;
  std::uint32_t sequence = 0;
  std::uint64_t log_time_ns = 0;      // when it was recorded
  std::uint64_t publish_time_ns = 0;  // when it was published (ROS 2: the same as log_time unless the sender says)
  std::span<const std::uint8_t> data;
};

// An attachment as written (a file carried along: a calibration, a config).
struct Attachment {
  std::uint64_t log_time_ns = 0;
  std::uint64_t create_time_ns = 0;
  std::string name;
  std::string media_type;
  std::span<const std::uint8_t> data;
};

// An attachment as found by the reader; its bytes stay in the file.
struct AttachmentInfo {
  std::uint64_t record_offset = 0;  // where its record starts
  std::uint64_t log_time_ns = 0;
  std::uint64_t create_time_ns = 0;
  std::string name;
  std::string media_type;
  std::uint64_t data_offset = 0;  // the data's first byte in the file
  std::uint64_t data_size = 0;
};

struct Metadata {
  std::string name;
  std::map<std::string, std::string> entries;

  bool operator==(const Metadata&) const = default;
};

struct Statistics {
  std::uint64_t message_count = 0;
  std::uint16_t schema_count = 0;
  std::uint32_t channel_count = 0;
  std::uint32_t attachment_count = 0;
  std::uint32_t metadata_count = 0;
  std::uint32_t chunk_count = 0;
  std::uint64_t message_start_time_ns = 0;  // earliest log time; 0 without messages
  std::uint64_t message_end_time_ns = 0;    // latest log time
  std::map<std::uint16_t, std::uint64_t> channel_message_counts;

  bool operator==(const Statistics&) const = default;
};

// Where a chunk and its message indexes are (summary section).
struct ChunkIndex {
  std::uint64_t message_start_time_ns = 0;
  std::uint64_t message_end_time_ns = 0;
  std::uint64_t chunk_start_offset = 0;                          // the Chunk record's opcode byte
  std::uint64_t chunk_length = 0;                                // the whole Chunk record, prefix included
  std::map<std::uint16_t, std::uint64_t> message_index_offsets;  // channel -> its MessageIndex record
  std::uint64_t message_index_length = 0;                        // all MessageIndex records after the chunk
  std::string compression;
  std::uint64_t compressed_size = 0;
  std::uint64_t uncompressed_size = 0;

  bool operator==(const ChunkIndex&) const = default;
};

struct AttachmentIndex {
  std::uint64_t offset = 0;  // the Attachment record
  std::uint64_t length = 0;  // the whole record, prefix included
  std::uint64_t log_time_ns = 0;
  std::uint64_t create_time_ns = 0;
  std::uint64_t data_size = 0;
  std::string name;
  std::string media_type;

  bool operator==(const AttachmentIndex&) const = default;
};

struct MetadataIndex {
  std::uint64_t offset = 0;  // the Metadata record
  std::uint64_t length = 0;
  std::string name;

  bool operator==(const MetadataIndex&) const = default;
};

// Where the records of one opcode sit in the summary section.
struct SummaryOffset {
  std::uint8_t group_opcode = 0;
  std::uint64_t group_start = 0;
  std::uint64_t group_length = 0;

  bool operator==(const SummaryOffset&) const = default;
};

struct Footer {
  std::uint64_t summary_start = 0;         // 0: no summary section
  std::uint64_t summary_offset_start = 0;  // 0: no SummaryOffset records
  std::uint32_t summary_crc = 0;           // 0: not computed
};

}  // namespace cvislam::mcap

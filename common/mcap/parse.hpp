// Parsing one record's content into its fields (the reader's only way in). Each function checks that every field
// fits inside the content and ignores bytes after the last field it knows (newer writers may add fields). Errors
// name the field; the reader adds the file, the record and its offset.
#pragma once

#include <cstdint>
#include <span>
#include <string_view>

#include "common/core/result.hpp"
#include "common/mcap/records.hpp"

namespace cvislam::mcap::parse {

using Bytes = std::span<const std::uint8_t>;

// A Chunk's fields; `records` points into the content.
struct ChunkFields {
  std::uint64_t message_start_time_ns = 0;
  std::uint64_t message_end_time_ns = 0;
  std::uint64_t uncompressed_size = 0;
  std::uint32_t uncompressed_crc = 0;
  std::string_view compression;
  Bytes records;
};

// An Attachment's fields; `data` points into the content, and `crc_covered` is what its crc covers.
struct AttachmentFields {
  std::uint64_t log_time_ns = 0;
  std::uint64_t create_time_ns = 0;
  std::string_view name;
  std::string_view media_type;
  Bytes data;
  std::uint32_t crc = 0;
  Bytes crc_covered;
};

// A MessageIndex's fields; `entries` is the raw array, 16 bytes per (log time, offset).
struct MessageIndexFields {
  std::uint16_t channel_id = 0;
  Bytes entries;
};

Result<Header> header(Bytes content);
Result<Footer> footer(Bytes content);
Result<Schema> schema(Bytes content);
Result<Channel> channel(Bytes content);
Result<Message> message(Bytes content);
Result<ChunkFields> chunk(Bytes content);
Result<MessageIndexFields> messageIndex(Bytes content);
Result<ChunkIndex> chunkIndex(Bytes content);
Result<AttachmentFields> attachment(Bytes content);
Result<AttachmentIndex> attachmentIndex(Bytes content);
Result<Statistics> statistics(Bytes content);
Result<Metadata> metadata(Bytes content);
Result<MetadataIndex> metadataIndex(Bytes content);
Result<SummaryOffset> summaryOffset(Bytes content);
// DataEnd: data_section_crc.
Result<std::uint32_t> dataEnd(Bytes content);

}  // namespace cvislam::mcap::parse

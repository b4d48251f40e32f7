#include "common/mcap/parse.hpp"

#include <string>

#include "common/mcap/wire.hpp"

namespace cvislam::mcap::parse {
namespace {

Error cutOff(const wire::Cursor& c) {
  return Error(ErrorCode::kParseError, std::string("field '") + c.failedField() + "' runs past the end of the record");
}

// Map<String, String>: a u32 byte length, then key/value pairs filling exactly that many bytes.
void stringMap(wire::Cursor& c, const char* field, std::map<std::string, std::string>& out) {
  wire::Cursor entries(c.bytes32(field));
  while (c.ok() && entries.remaining() > 0) {
    const std::string_view key = entries.string(field);
    const std::string_view value = entries.string(field);
    if (!entries.ok()) break;
    out.insert_or_assign(std::string(key), std::string(value));
  }
  if (!entries.ok()) c.fail(field);  // an entry cut off inside the map fails the record
}

// Map<u16, u64>: 10 bytes an entry.
void u16Map(wire::Cursor& c, const char* field, std::map<std::uint16_t, std::uint64_t>& out) {
  wire::Cursor entries(c.bytes32(field));
  while (c.ok() && entries.remaining() > 0) {
    const std::uint16_t key = entries.u16(field);
    const std::uint64_t value = entries.u64(field);
    if (!entries.ok()) break;
    out.insert_or_assign(key, value);
  }
  if (!entries.ok()) c.fail(field);
}

}  // namespace

Result<Header> header(Bytes content) {
  wire::Cursor c(content);
  Header h;
  h.profile = c.string("profile");
  h.library = c.string("library");
  if (!c.ok()) return cutOff(c);
  return h;
}

Result<Footer> footer(Bytes content) {
  wire::Cursor c(content);
  Footer f;
  f.summary_start = c.u64("summary_start");
  f.summary_offset_start = c.u64("summary_offset_start");
  f.summary_crc = c.u32("summary_crc");
  if (!c.ok()) return cutOff(c);
  return f;
}

Result<Schema> schema(Bytes content) {
  wire::Cursor c(content);
  Schema s;
  s.id = c.u16("id");
  s.name = c.string("name");
  s.encoding = c.string("encoding");
  const Bytes data = c.bytes32("data");
  if (!c.ok()) return cutOff(c);
  s.data.assign(reinterpret_cast<const char*>(data.data()), data.size());
  if (s.id == 0) return Error(ErrorCode::kParseError, "schema id 0 is reserved");
  return s;
}

Result<Channel> channel(Bytes content) {
  wire::Cursor c(content);
  Channel ch;
  ch.id = c.u16("id");
  ch.schema_id = c.u16("schema_id");
  ch.topic = c.string("topic");
  ch.message_encoding = c.string("message_encoding");
  stringMap(c, "metadata", ch.metadata);
  if (!c.ok()) return cutOff(c);
  return ch;
}

Result<Message> message(Bytes content) {
  wire::Cursor c(content);
  Message m;
  m.channel_id = c.u16("channel_id");
  m.sequence = c.u32("sequence");
  m.log_time_ns = c.u64("log_time");
  m.publish_time_ns = c.u64("publish_time");
  if (!c.ok()) return cutOff(c);
  m.data = c.rest();
  return m;
}

Result<ChunkFields> chunk(Bytes content) {
  wire::Cursor c(content);
  ChunkFields f;
  f.message_start_time_ns = c.u64("message_start_time");
  f.message_end_time_ns = c.u64("message_end_time");
  f.uncompressed_size = c.u64("uncompressed_size");
  f.uncompressed_crc = c.u32("uncompressed_crc");
  f.compression = c.string("compression");
  f.records = c.bytes64("records");
  if (!c.ok()) return cutOff(c);
  return f;
}

Result<MessageIndexFields> messageIndex(Bytes content) {
  wire::Cursor c(content);
  MessageIndexFields f;
  f.channel_id = c.u16("channel_id");
  f.entries = c.bytes32("records");
  if (!c.ok()) return cutOff(c);
  if (f.entries.size() % 16 != 0) {
    return Error(ErrorCode::kParseError,
                 "records array of " + std::to_string(f.entries.size()) + " bytes is not a whole number of entries");
  }
  return f;
}

Result<ChunkIndex> chunkIndex(Bytes content) {
  wire::Cursor c(content);
  ChunkIndex i;
  i.message_start_time_ns = c.u64("message_start_time");
  i.message_end_time_ns = c.u64("message_end_time");
  i.chunk_start_offset = c.u64("chunk_start_offset");
  i.chunk_length = c.u64("chunk_length");
  u16Map(c, "message_index_offsets", i.message_index_offsets);
  i.message_index_length = c.u64("message_index_length");
  i.compression = c.string("compression");
  i.compressed_size = c.u64("compressed_size");
  i.uncompressed_size = c.u64("uncompressed_size");
  if (!c.ok()) return cutOff(c);
  return i;
}

Result<AttachmentFields> attachment(Bytes content) {
  wire::Cursor c(content);
  AttachmentFields f;
  f.log_time_ns = c.u64("log_time");
  f.create_time_ns = c.u64("create_time");
  f.name = c.string("name");
  f.media_type = c.string("media_type");
  f.data = c.bytes64("data");
  const std::size_t covered = c.position();
  f.crc = c.u32("crc");
  if (!c.ok()) return cutOff(c);
  f.crc_covered = content.first(covered);
  return f;
}

Result<AttachmentIndex> attachmentIndex(Bytes content) {
  wire::Cursor c(content);
  AttachmentIndex i;
  i.offset = c.u64("offset");
  i.length = c.u64("length");
  i.log_time_ns = c.u64("log_time");
  i.create_time_ns = c.u64("create_time");
  i.data_size = c.u64("data_size");
  i.name = c.string("name");
  i.media_type = c.string("media_type");
  if (!c.ok()) return cutOff(c);
  return i;
}

Result<Statistics> statistics(Bytes content) {
  wire::Cursor c(content);
  Statistics s;
  s.message_count = c.u64("message_count");
  s.schema_count = c.u16("schema_count");
  s.channel_count = c.u32("channel_count");
  s.attachment_count = c.u32("attachment_count");
  s.metadata_count = c.u32("metadata_count");
  s.chunk_count = c.u32("chunk_count");
  s.message_start_time_ns = c.u64("message_start_time");
  s.message_end_time_ns = c.u64("message_end_time");
  u16Map(c, "channel_message_counts", s.channel_message_counts);
  if (!c.ok()) return cutOff(c);
  return s;
}

Result<Metadata> metadata(Bytes content) {
  wire::Cursor c(content);
  Metadata m;
  m.name = c.string("name");
  stringMap(c, "metadata", m.entries);
  if (!c.ok()) return cutOff(c);
  return m;
}

Result<MetadataIndex> metadataIndex(Bytes content) {
  wire::Cursor c(content);
  MetadataIndex i;
  i.offset = c.u64("offset");
  i.length = c.u64("length");
  i.name = c.string("name");
  if (!c.ok()) return cutOff(c);
  return i;
}

Result<SummaryOffset> summaryOffset(Bytes content) {
  wire::Cursor c(content);
  SummaryOffset s;
  s.group_opcode = c.u8("group_opcode");
  s.group_start = c.u64("group_start");
  s.group_length = c.u64("group_length");
  if (!c.ok()) return cutOff(c);
  return s;
}

Result<std::uint32_t> dataEnd(Bytes content) {
  wire::Cursor c(content);
  const std::uint32_t crc = c.u32("data_section_crc");
  if (!c.ok()) return cutOff(c);
  return crc;
}

}  // namespace cvislam::mcap::parse

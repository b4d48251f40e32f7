#include "common/mcap/writer.hpp"

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <limits>
#include <optional>
#include <utility>

#include "common/mcap/codec.hpp"
#include "common/mcap/wire.hpp"

namespace cvislam::mcap {

Status WriterOptions::validate() const {
  if (chunk_bytes == 0) return Error(ErrorCode::kInvalidArgument, "mcap writer: chunk_bytes must be positive");
  if (zstd_level < 1 || zstd_level > 19) {
    return Error(ErrorCode::kInvalidArgument,
                 "mcap writer: zstd_level " + std::to_string(zstd_level) + " is outside 1..19");
  }
  if (profile.size() > std::numeric_limits<std::uint32_t>::max() ||
      library.size() > std::numeric_limits<std::uint32_t>::max()) {
    return Error(ErrorCode::kInvalidArgument, "mcap writer: profile or library too long");
  }
  return {};
}

namespace {

using Bytes = std::span<const std::uint8_t>;

constexpr std::uint64_t kMaxString = std::numeric_limits<std::uint32_t>::max();

// Schema and Channel records: written into the data section when added, and again in the summary.
void encodeSchema(wire::Encoder& e, const Schema& s) {
  const std::size_t at = e.beginRecord(Opcode::kSchema);
  e.u16(s.id);
  e.string(s.name);
  e.string(s.encoding);
  e.string(s.data);
  e.endRecord(at);
}

void encodeChannel(wire::Encoder& e, const Channel& c) {
  const std::size_t at = e.beginRecord(Opcode::kChannel);
  e.u16(c.id);
  e.u16(c.schema_id);
  e.string(c.topic);
  e.string(c.message_encoding);
  e.stringMap(c.metadata);
  e.endRecord(at);
}

// A group of summary records of one opcode, for its SummaryOffset.
struct Group {
  Opcode opcode;
  std::uint64_t start;
  std::uint64_t length;
};

}  // namespace

struct Writer::Impl {
  std::string name;
  WriterOptions options;
  std::FILE* file = nullptr;         // nullptr: in memory
  std::vector<std::uint8_t> memory;  // the in-memory file
  std::uint64_t offset = 0;          // bytes written so far
  bool in_data_section = true;       // until the DataEnd: everything written feeds data_crc
  std::uint32_t data_crc = 0;
  bool closed = false;
  std::optional<Error> failure;  // the first write error: every later call returns it

  std::vector<std::uint8_t> scratch;  // one record being encoded
  codec::Compressor compressor;
  std::vector<std::uint8_t> compressed;

  // The open chunk.
  std::vector<std::uint8_t> chunk_records;
  std::uint64_t chunk_start_ns = 0;
  std::uint64_t chunk_end_ns = 0;
  std::map<std::uint16_t, std::vector<std::pair<std::uint64_t, std::uint64_t>>> message_index;  // (log time, offset)

  // For the summary.
  std::vector<Schema> schemas;
  std::vector<Channel> channels;
  std::vector<bool> channel_defined = std::vector<bool>(65536, false);
  std::vector<ChunkIndex> chunk_indexes;
  std::vector<AttachmentIndex> attachment_indexes;
  std::vector<MetadataIndex> metadata_indexes;
  Statistics statistics;

  ~Impl() {
    if (file != nullptr) std::fclose(file);
  }

  Status usable() const {
    if (failure) return *failure;
    if (closed) return Error(ErrorCode::kFailedPrecondition, "mcap writer: " + name + " is closed");
    return {};
  }
  Error invalid(const std::string& what) const {
    return Error(ErrorCode::kInvalidArgument, "mcap writer: " + name + ": " + what);
  }

  Status emit(Bytes bytes) {
    if (failure) return *failure;
    if (file != nullptr) {
      if (std::fwrite(bytes.data(), 1, bytes.size(), file) != bytes.size()) {
        failure = Error(ErrorCode::kIoError, "mcap writer: " + name + ": write failed at offset " +
                                                 std::to_string(offset) + ": " + std::strerror(errno));
        return *failure;
      }
    } else {
      memory.insert(memory.end(), bytes.begin(), bytes.end());
    }
    offset += bytes.size();
    if (in_data_section && options.write_crcs) data_crc = codec::crc32(data_crc, bytes);
    return {};
  }

  Status writeChunk();
  Status finish();
};

Status Writer::Impl::writeChunk() {
  if (chunk_records.empty()) return {};
  const std::uint32_t crc = options.write_crcs ? codec::crc32(0, chunk_records) : 0;
  Bytes payload = chunk_records;
  if (options.compression != Compression::kNone) {
    if (Status s = compressor.compress(options.compression, options.zstd_level, chunk_records, compressed); !s.ok()) {
      failure = Error(s.error().code(), "mcap writer: " + name + ": " + s.error().message());
      return *failure;
    }
    payload = compressed;
  }
  const std::uint64_t chunk_start = offset;
  scratch.clear();
  wire::Encoder e(scratch);
  const std::size_t length_at = e.beginRecord(Opcode::kChunk);
  e.u64(chunk_start_ns);
  e.u64(chunk_end_ns);
  e.u64(chunk_records.size());
  e.u32(crc);
  e.string(compressionName(options.compression));
  e.u64(payload.size());
  // The records follow the encoded fields straight from their buffer: the length counts them too.
  e.endRecord(length_at, payload.size());
  if (Status s = emit(scratch); !s.ok()) return s;
  if (Status s = emit(payload); !s.ok()) return s;

  ChunkIndex index;
  index.message_start_time_ns = chunk_start_ns;
  index.message_end_time_ns = chunk_end_ns;
  index.chunk_start_offset = chunk_start;
  index.chunk_length = offset - chunk_start;
  index.compression = std::string(compressionName(options.compression));
  index.compressed_size = payload.size();
  index.uncompressed_size = chunk_records.size();
  const std::uint64_t indexes_start = offset;
  for (auto& [channel_id, entries] : message_index) {
    if (entries.empty()) continue;
    if (options.write_message_indexes) {
      // Readers look messages up by time: keep each channel's entries in log-time order.
      if (!std::is_sorted(entries.begin(), entries.end())) std::sort(entries.begin(), entries.end());
      index.message_index_offsets[channel_id] = offset;
      scratch.clear();
      const std::size_t at = e.beginRecord(Opcode::kMessageIndex);
      e.u16(channel_id);
      const std::size_t array_at = e.beginLength32();
      for (const auto& [log_time_ns, record_offset] : entries) {
        e.u64(log_time_ns);
        e.u64(record_offset);
      }
      e.endLength32(array_at);
      e.endRecord(at);
      if (Status s = emit(scratch); !s.ok()) return s;
    }
    entries.clear();
  }
  index.message_index_length = offset - indexes_start;
  chunk_indexes.push_back(std::move(index));
  statistics.chunk_count++;
  chunk_records.clear();
  return {};
}

Status Writer::Impl::finish() {
  if (Status s = writeChunk(); !s.ok()) return s;

  // DataEnd: its CRC covers every byte before it.
  const std::uint32_t data_section_crc = options.write_crcs ? data_crc : 0;
  in_data_section = false;
  scratch.clear();
  wire::Encoder e(scratch);
  std::size_t at = e.beginRecord(Opcode::kDataEnd);
  e.u32(data_section_crc);
  e.endRecord(at);
  if (Status s = emit(scratch); !s.ok()) return s;

  // The summary section, its offsets and the Footer are encoded in one buffer: the summary CRC covers them.
  const std::uint64_t summary_start = offset;
  std::vector<std::uint8_t> summary;
  wire::Encoder out(summary);
  std::vector<Group> groups;
  const auto group = [&](Opcode op, const auto& encode_all) {
    const std::size_t begin = summary.size();
    encode_all();
    if (summary.size() > begin) groups.push_back({op, summary_start + begin, summary.size() - begin});
  };
  if (options.write_summary) {
    group(Opcode::kSchema, [&] {
      for (const Schema& s : schemas) encodeSchema(out, s);
    });
    group(Opcode::kChannel, [&] {
      for (const Channel& c : channels) encodeChannel(out, c);
    });
    group(Opcode::kStatistics, [&] {
      const Statistics& s = statistics;
      const std::size_t r = out.beginRecord(Opcode::kStatistics);
      out.u64(s.message_count);
      out.u16(s.schema_count);
      out.u32(s.channel_count);
      out.u32(s.attachment_count);
      out.u32(s.metadata_count);
      out.u32(s.chunk_count);
      out.u64(s.message_start_time_ns);
      out.u64(s.message_end_time_ns);
      out.u16Map(s.channel_message_counts);
      out.endRecord(r);
    });
    group(Opcode::kChunkIndex, [&] {
      for (const ChunkIndex& i : chunk_indexes) {
        const std::size_t r = out.beginRecord(Opcode::kChunkIndex);
        out.u64(i.message_start_time_ns);
        out.u64(i.message_end_time_ns);
        out.u64(i.chunk_start_offset);
        out.u64(i.chunk_length);
        out.u16Map(i.message_index_offsets);
        out.u64(i.message_index_length);
        out.string(i.compression);
        out.u64(i.compressed_size);
        out.u64(i.uncompressed_size);
        out.endRecord(r);
      }
    });
    group(Opcode::kAttachmentIndex, [&] {
      for (const AttachmentIndex& i : attachment_indexes) {
        const std::size_t r = out.beginRecord(Opcode::kAttachmentIndex);
        out.u64(i.offset);
        out.u64(i.length);
        out.u64(i.log_time_ns);
        out.u64(i.create_time_ns);
        out.u64(i.data_size);
        out.string(i.name);
        out.string(i.media_type);
        out.endRecord(r);
      }
    });
    group(Opcode::kMetadataIndex, [&] {
      for (const MetadataIndex& i : metadata_indexes) {
        const std::size_t r = out.beginRecord(Opcode::kMetadataIndex);
        out.u64(i.offset);
        out.u64(i.length);
        out.string(i.name);
        out.endRecord(r);
      }
    });
  }
  std::uint64_t summary_offset_start = 0;
  if (options.write_summary_offsets && !groups.empty()) {
    summary_offset_start = summary_start + summary.size();
    for (const Group& g : groups) {
      const std::size_t r = out.beginRecord(Opcode::kSummaryOffset);
      out.u8(static_cast<std::uint8_t>(g.opcode));
      out.u64(g.start);
      out.u64(g.length);
      out.endRecord(r);
    }
  }
  const bool has_summary = !summary.empty();
  // The Footer's length is written directly, not patched: the summary CRC covers it.
  out.u8(static_cast<std::uint8_t>(Opcode::kFooter));
  out.u64(8 + 8 + 4);
  out.u64(has_summary ? summary_start : 0);
  out.u64(summary_offset_start);
  // The CRC covers the summary and the Footer's fields before it; without a summary there is nothing to cover.
  const std::uint32_t summary_crc = options.write_crcs && has_summary ? codec::crc32(0, summary) : 0;
  out.u32(summary_crc);
  out.raw(Bytes(kMagic));
  if (Status s = emit(summary); !s.ok()) return s;

  if (file != nullptr) {
    std::FILE* f = std::exchange(file, nullptr);
    if (std::fclose(f) != 0) {
      failure = Error(ErrorCode::kIoError, "mcap writer: " + name + ": closing failed: " + std::strerror(errno));
      return *failure;
    }
  }
  return {};
}

Writer::Writer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Writer::Writer(Writer&&) noexcept = default;
Writer& Writer::operator=(Writer&&) noexcept = default;
Writer::~Writer() {
  if (impl_ && !impl_->closed) (void)close();
}

Result<Writer> Writer::start(std::unique_ptr<Impl> impl) {
  if (Status s = impl->options.validate(); !s.ok()) return s.error();
  if (Status s = impl->emit(Bytes(kMagic)); !s.ok()) return s.error();
  impl->scratch.clear();
  wire::Encoder e(impl->scratch);
  const std::size_t at = e.beginRecord(Opcode::kHeader);
  e.string(impl->options.profile);
  e.string(impl->options.library);
  e.endRecord(at);
  if (Status s = impl->emit(impl->scratch); !s.ok()) return s.error();
  return Writer(std::move(impl));
}

Result<Writer> Writer::create(const std::filesystem::path& path, WriterOptions options) {
  auto impl = std::make_unique<Impl>();
  impl->name = path.string();
  impl->options = std::move(options);
  if (Status s = impl->options.validate(); !s.ok()) return s.error();
  impl->file = std::fopen(path.c_str(), "wb");
  if (impl->file == nullptr) {
    return Error(ErrorCode::kIoError, "mcap writer: cannot create " + path.string() + ": " + std::strerror(errno));
  }
  return start(std::move(impl));
}

Result<Writer> Writer::createInMemory(WriterOptions options) {
  auto impl = std::make_unique<Impl>();
  impl->name = "<memory>";
  impl->options = std::move(options);
  return start(std::move(impl));
}

Result<std::uint16_t> Writer::addSchema(std::string_view name, std::string_view encoding, std::string_view data) {
  Impl& m = *impl_;
  if (Status s = m.usable(); !s.ok()) return s.error();
  for (const Schema& s : m.schemas) {
    if (s.name == name && s.encoding == encoding && s.data == data) return s.id;
  }
  if (m.schemas.size() >= 65535) return m.invalid("no schema id left (65535 in use)");
  if (name.size() > kMaxString || encoding.size() > kMaxString || data.size() > kMaxString) {
    return m.invalid("schema '" + std::string(name.substr(0, 64)) + "' has a field over 4 GiB");
  }
  Schema s;
  s.id = static_cast<std::uint16_t>(m.schemas.size() + 1);
  s.name = name;
  s.encoding = encoding;
  s.data = data;
  m.scratch.clear();
  wire::Encoder e(m.scratch);
  encodeSchema(e, s);
  if (Status st = m.emit(m.scratch); !st.ok()) return st.error();
  m.statistics.schema_count++;
  m.schemas.push_back(std::move(s));
  return m.schemas.back().id;
}

Result<std::uint16_t> Writer::addChannel(std::uint16_t schema_id, std::string_view topic,
                                         std::string_view message_encoding,
                                         const std::map<std::string, std::string>& metadata) {
  Impl& m = *impl_;
  if (Status s = m.usable(); !s.ok()) return s.error();
  if (schema_id > m.schemas.size()) {
    return m.invalid("channel '" + std::string(topic) + "': schema " + std::to_string(schema_id) + " was not added");
  }
  if (m.channels.size() >= 65535) return m.invalid("no channel id left (65535 in use)");
  std::uint64_t metadata_bytes = 0;
  for (const auto& [key, value] : metadata) metadata_bytes += 8 + key.size() + value.size();
  if (topic.size() > kMaxString || message_encoding.size() > kMaxString || metadata_bytes > kMaxString) {
    return m.invalid("channel '" + std::string(topic.substr(0, 64)) + "' has a field over 4 GiB");
  }
  Channel c;
  c.id = static_cast<std::uint16_t>(m.channels.size() + 1);
  c.schema_id = schema_id;
  c.topic = topic;
  c.message_encoding = message_encoding;
  c.metadata = metadata;
  m.scratch.clear();
  wire::Encoder e(m.scratch);
  encodeChannel(e, c);
  if (Status st = m.emit(m.scratch); !st.ok()) return st.error();
  m.statistics.channel_count++;
  m.channel_defined[c.id] = true;
  m.channels.push_back(std::move(c));
  return m.channels.back().id;
}

Status Writer::write(const Message& message) {
  Impl& m = *impl_;
  if (Status s = m.usable(); !s.ok()) return s;
  if (!m.channel_defined[message.channel_id]) {
    return m.invalid("message on channel " + std::to_string(message.channel_id) + ", which was not added");
  }
  Statistics& stats = m.statistics;
  if (stats.message_count == 0) {
    stats.message_start_time_ns = stats.message_end_time_ns = message.log_time_ns;
  } else {
    stats.message_start_time_ns = std::min(stats.message_start_time_ns, message.log_time_ns);
    stats.message_end_time_ns = std::max(stats.message_end_time_ns, message.log_time_ns);
  }
  stats.message_count++;
  stats.channel_message_counts[message.channel_id]++;

  std::vector<std::uint8_t>& out = m.options.use_chunks ? m.chunk_records : m.scratch;
  if (!m.options.use_chunks) m.scratch.clear();
  const std::uint64_t offset_in_chunk = out.size();
  wire::Encoder e(out);
  const std::size_t at = e.beginRecord(Opcode::kMessage);
  e.u16(message.channel_id);
  e.u32(message.sequence);
  e.u64(message.log_time_ns);
  e.u64(message.publish_time_ns);
  e.raw(message.data);
  e.endRecord(at);
  if (!m.options.use_chunks) return m.emit(m.scratch);

  if (offset_in_chunk == 0) {
    m.chunk_start_ns = m.chunk_end_ns = message.log_time_ns;
  } else {
    m.chunk_start_ns = std::min(m.chunk_start_ns, message.log_time_ns);
    m.chunk_end_ns = std::max(m.chunk_end_ns, message.log_time_ns);
  }
  m.message_index[message.channel_id].emplace_back(message.log_time_ns, offset_in_chunk);
  if (m.chunk_records.size() >= m.options.chunk_bytes) return m.writeChunk();
  return {};
}

Status Writer::writeAttachment(const Attachment& attachment) {
  Impl& m = *impl_;
  if (Status s = m.usable(); !s.ok()) return s;
  if (attachment.name.size() > kMaxString || attachment.media_type.size() > kMaxString) {
    return m.invalid("attachment '" + attachment.name.substr(0, 64) + "' has a name or media type over 4 GiB");
  }
  AttachmentIndex index;
  index.offset = m.offset;
  index.log_time_ns = attachment.log_time_ns;
  index.create_time_ns = attachment.create_time_ns;
  index.data_size = attachment.data.size();
  index.name = attachment.name;
  index.media_type = attachment.media_type;
  m.scratch.clear();
  wire::Encoder e(m.scratch);
  const std::size_t at = e.beginRecord(Opcode::kAttachment);
  e.u64(attachment.log_time_ns);
  e.u64(attachment.create_time_ns);
  e.string(attachment.name);
  e.string(attachment.media_type);
  e.u64(attachment.data.size());
  // The data is written from the caller's buffer; its crc (over every field before it) follows.
  std::uint32_t crc = 0;
  if (m.options.write_crcs) {
    crc = codec::crc32(codec::crc32(0, Bytes(m.scratch).subspan(at + 8)), attachment.data);
  }
  e.endRecord(at, attachment.data.size() + 4);
  if (Status s = m.emit(m.scratch); !s.ok()) return s;
  if (Status s = m.emit(attachment.data); !s.ok()) return s;
  m.scratch.clear();
  e.u32(crc);
  if (Status s = m.emit(m.scratch); !s.ok()) return s;
  index.length = m.offset - index.offset;
  m.attachment_indexes.push_back(std::move(index));
  m.statistics.attachment_count++;
  return {};
}

Status Writer::writeMetadata(const Metadata& metadata) {
  Impl& m = *impl_;
  if (Status s = m.usable(); !s.ok()) return s;
  std::uint64_t bytes = 0;
  for (const auto& [key, value] : metadata.entries) bytes += 8 + key.size() + value.size();
  if (metadata.name.size() > kMaxString || bytes > kMaxString) {
    return m.invalid("metadata '" + metadata.name.substr(0, 64) + "' is over 4 GiB");
  }
  MetadataIndex index;
  index.offset = m.offset;
  index.name = metadata.name;
  m.scratch.clear();
  wire::Encoder e(m.scratch);
  const std::size_t at = e.beginRecord(Opcode::kMetadata);
  e.string(metadata.name);
  e.stringMap(metadata.entries);
  e.endRecord(at);
  if (Status s = m.emit(m.scratch); !s.ok()) return s;
  index.length = m.offset - index.offset;
  m.metadata_indexes.push_back(std::move(index));
  m.statistics.metadata_count++;
  return {};
}

Status Writer::flush() {
  Impl& m = *impl_;
  if (Status s = m.usable(); !s.ok()) return s;
  if (Status s = m.writeChunk(); !s.ok()) return s;
  if (m.file != nullptr && std::fflush(m.file) != 0) {
    m.failure = Error(ErrorCode::kIoError, "mcap writer: " + m.name + ": flush failed: " + std::strerror(errno));
    return *m.failure;
  }
  return {};
}

Status Writer::close() {
  Impl& m = *impl_;
  if (Status s = m.usable(); !s.ok()) return s;
  Status s = m.finish();
  m.closed = true;
  return s;
}

const Statistics& Writer::statistics() const {
  return impl_->statistics;
}
const std::vector<std::uint8_t>& Writer::memoryBytes() const {
  return impl_->memory;
}

}  // namespace cvislam::mcap

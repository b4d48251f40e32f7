#include "common/mcap/reader.hpp"

#include <algorithm>
#include <cstdio>
#include <cstring>
#include <utility>

#include "common/mcap/byte_source.hpp"
#include "common/mcap/codec.hpp"
#include "common/mcap/parse.hpp"
#include "common/mcap/wire.hpp"

namespace cvislam::mcap {

Status ReaderOptions::validate() const {
  if (max_record_bytes == 0) return Error(ErrorCode::kInvalidArgument, "mcap: max_record_bytes must be positive");
  return {};
}

namespace {

using Bytes = std::span<const std::uint8_t>;

std::string hex32(std::uint32_t v) {
  char text[16];
  std::snprintf(text, sizeof text, "0x%08x", v);
  return text;
}

enum class Phase { kData, kSummary, kDone, kFailed };

// Where a record is, for errors. Kept as numbers and turned into text only when an error is reported: a scan
// meets a record per message.
struct Place {
  std::uint8_t op = 0;
  std::uint64_t offset = 0;                   // the record's file offset, or its byte in the chunk's records
  std::optional<std::uint64_t> chunk_offset;  // set for a record inside a chunk
};

std::string describe(const Place& p) {
  if (p.chunk_offset) {
    return opcodeName(p.op) + " at byte " + std::to_string(p.offset) + " of the chunk at offset " +
           std::to_string(*p.chunk_offset);
  }
  return opcodeName(p.op) + " at offset " + std::to_string(p.offset);
}

Place topLevel(Opcode op, std::uint64_t offset) {
  return {static_cast<std::uint8_t>(op), offset, std::nullopt};
}

}  // namespace

struct Reader::Impl {
  std::unique_ptr<Source> source;
  std::string file_name;
  ReaderOptions options;

  Header header;
  std::optional<Summary> summary;
  std::map<std::uint16_t, Schema> schemas;
  std::map<std::uint16_t, Channel> channels;
  std::vector<Metadata> metadata;
  std::vector<AttachmentInfo> attachments;
  std::uint64_t definition_bytes = 0;
  RecordCounts counts;

  // The Footer's offset when the file ends with the magic (found at open), else nullopt.
  std::optional<std::uint64_t> footer_offset;

  // The forward scan.
  Phase phase = Phase::kData;
  std::optional<Error> error;
  std::uint64_t position = 0;                // the next top-level record
  std::uint32_t data_crc = 0;                // CRC of [0, position) while in the data section
  std::uint32_t data_crc_before_record = 0;  // the same before the current record's prefix
  std::vector<std::uint8_t> block;           // streaming buffer
  std::vector<std::uint8_t> field;           // an attachment's field
  std::vector<std::uint8_t> record;          // the current top-level record's content
  std::vector<std::uint8_t> chunk;           // a compressed chunk's records, decompressed
  Bytes chunk_records;                       // the records of the chunk being iterated (in `record` or `chunk`)
  std::size_t chunk_position = 0;
  std::uint64_t chunk_offset = 0;
  bool in_chunk = false;
  codec::Decompressor decompressor;

  Error fail(ErrorCode code, const std::string& what) const { return Error(code, "mcap: " + file_name + ": " + what); }
  // `what` follows the record's description: ": ..." or " has ...".
  Error fail(ErrorCode code, const Place& place, const std::string& what) const {
    return fail(code, describe(place) + what);
  }

  Status readAt(std::uint64_t offset, std::span<std::uint8_t> out) {
    if (Status s = source->read(offset, out); !s.ok()) return fail(s.error().code(), s.error().message());
    return {};
  }

  // The opcode and content length of the record at `offset`, checked against the end of the file.
  Result<std::pair<std::uint8_t, std::uint64_t>> recordPrefix(std::uint64_t offset) {
    const std::uint64_t size = source->size();
    if (offset > size || size - offset < kRecordPrefixBytes) {
      return fail(ErrorCode::kParseError, "record at offset " + std::to_string(offset) +
                                              " is cut off: the file ends at " + std::to_string(size));
    }
    std::array<std::uint8_t, kRecordPrefixBytes> prefix{};
    if (Status s = readAt(offset, prefix); !s.ok()) return s.error();
    wire::Cursor c(prefix);
    const std::uint8_t op = c.u8("opcode");
    const std::uint64_t length = c.u64("length");
    if (length > size - offset - kRecordPrefixBytes) {
      return fail(ErrorCode::kParseError, Place{op, offset, {}},
                  " has length " + std::to_string(length) + ", which runs past the end of the file (" +
                      std::to_string(size) + " bytes)");
    }
    data_crc_before_record = data_crc;
    if (inDataSection()) data_crc = codec::crc32(data_crc, prefix);
    return std::pair{op, length};
  }

  [[nodiscard]] bool inDataSection() const { return phase == Phase::kData && options.check_crcs; }

  // Loads a record's content into `record`, bounded by max_record_bytes.
  Status load(std::uint8_t op, std::uint64_t offset, std::uint64_t length) {
    if (length > options.max_record_bytes) {
      return fail(ErrorCode::kResourceExhausted, Place{op, offset, {}},
                  " has " + std::to_string(length) + " bytes, over max_record_bytes (" +
                      std::to_string(options.max_record_bytes) + ")");
    }
    record.resize(static_cast<std::size_t>(length));
    if (Status s = readAt(offset + kRecordPrefixBytes, record); !s.ok()) return s;
    if (inDataSection()) data_crc = codec::crc32(data_crc, record);
    return {};
  }

  // Reads through a record without keeping it (attachments, unknown records: they may be of any size), feeding the
  // data section CRC and `crc` over the first `crc_bytes` bytes of the content.
  Status stream(std::uint64_t offset, std::uint64_t length, std::uint64_t crc_bytes, std::uint32_t& crc) {
    if (!inDataSection() && (crc_bytes == 0 || !options.check_crcs)) return {};  // nothing to compute
    constexpr std::uint64_t kBlock = std::uint64_t{64} << 10;
    block.resize(static_cast<std::size_t>(std::min(kBlock, length)));
    for (std::uint64_t done = 0; done < length;) {
      const auto n = static_cast<std::size_t>(std::min(kBlock, length - done));
      const std::span<std::uint8_t> piece(block.data(), n);
      if (Status s = readAt(offset + kRecordPrefixBytes + done, piece); !s.ok()) return s;
      if (inDataSection()) data_crc = codec::crc32(data_crc, piece);
      if (done < crc_bytes) {
        crc = codec::crc32(crc, piece.first(static_cast<std::size_t>(std::min<std::uint64_t>(n, crc_bytes - done))));
      }
      done += n;
    }
    return {};
  }

  Status addDefinitionBytes(std::uint64_t n, const Place& place) {
    definition_bytes += n;
    if (definition_bytes > options.max_definition_bytes) {
      return fail(ErrorCode::kResourceExhausted, place,
                  ": schemas, channels and metadata exceed max_definition_bytes (" +
                      std::to_string(options.max_definition_bytes) + ")");
    }
    return {};
  }

  // Turns a parser's error into one that names the record.
  template <typename T>
  Result<T> parsed(Result<T> r, const Place& place) const {
    if (!r.ok()) return fail(r.error().code(), place, ": " + r.error().message());
    return r;
  }

  // A Schema record: defined once; the same again is fine, a different one under the same id is not.
  Status schemaRecord(Bytes content, const Place& place) {
    auto s = parsed(parse::schema(content), place);
    if (!s.ok()) return s.error();
    const auto found = schemas.find(s->id);
    if (found != schemas.end()) {
      if (found->second == s.value()) return {};
      return fail(ErrorCode::kParseError, place,
                  ": schema " + std::to_string(s->id) + " differs from its earlier definition");
    }
    if (Status st = addDefinitionBytes(s->name.size() + s->encoding.size() + s->data.size() + 64, place); !st.ok()) {
      return st;
    }
    const std::uint16_t id = s->id;
    schemas.emplace(id, std::move(s).value());
    return {};
  }

  // A Channel record: as a schema, and its schema must be known already.
  Status channelRecord(Bytes content, const Place& place) {
    auto c = parsed(parse::channel(content), place);
    if (!c.ok()) return c.error();
    const auto found = channels.find(c->id);
    if (found != channels.end()) {
      if (found->second == c.value()) return {};
      return fail(ErrorCode::kParseError, place,
                  ": channel " + std::to_string(c->id) + " differs from its earlier definition");
    }
    if (c->schema_id != 0 && schemas.count(c->schema_id) == 0) {
      return fail(ErrorCode::kParseError, place,
                  ": channel " + std::to_string(c->id) + " refers to schema " + std::to_string(c->schema_id) +
                      ", which is not defined before it");
    }
    std::uint64_t bytes = c->topic.size() + c->message_encoding.size() + 64;
    for (const auto& [key, value] : c->metadata) bytes += key.size() + value.size() + 64;
    if (Status st = addDefinitionBytes(bytes, place); !st.ok()) return st;
    const std::uint16_t id = c->id;
    channels.emplace(id, std::move(c).value());
    return {};
  }

  // A Message record into `out`; its channel must be known.
  Status messageRecord(Bytes content, const Place& place, std::uint64_t record_offset, MessageView& out) {
    auto m = parsed(parse::message(content), place);
    if (!m.ok()) return m.error();
    const auto channel = channels.find(m->channel_id);
    if (channel == channels.end()) {
      return fail(ErrorCode::kParseError, place, ": channel " + std::to_string(m->channel_id) + " is not defined");
    }
    static_cast<Message&>(out) = m.value();
    out.channel = &channel->second;
    const auto schema = schemas.find(channel->second.schema_id);
    out.schema = schema == schemas.end() ? nullptr : &schema->second;
    out.record_offset = record_offset;
    counts.messages++;
    return {};
  }

  Status openFile();
  Status readSummary(const Footer& footer, std::uint64_t footer_offset);
  Result<bool> nextInChunk(MessageView& out);
  Result<bool> nextTopLevel(MessageView& out);
  Status startChunk(std::uint64_t offset);
  Status endOfData(std::uint64_t offset, std::uint64_t length);
  Status footerReached(std::uint64_t offset, std::uint64_t length);
  Status readAttachment(std::uint64_t offset, std::uint64_t length);
};

Status Reader::Impl::openFile() {
  const std::uint64_t size = source->size();
  std::array<std::uint8_t, kMagic.size()> magic{};
  if (size < kMagic.size()) {
    return fail(ErrorCode::kParseError, "not an MCAP file: " + std::to_string(size) + " bytes, shorter than the magic");
  }
  if (Status s = readAt(0, magic); !s.ok()) return s;
  if (magic != kMagic) return fail(ErrorCode::kParseError, "not an MCAP file: the magic at offset 0 is missing");
  if (options.check_crcs) data_crc = codec::crc32(0, magic);
  position = kMagic.size();

  // The Header must come first.
  auto prefix = recordPrefix(position);
  if (!prefix.ok()) return prefix.error();
  const auto [op, length] = prefix.value();
  if (op != static_cast<std::uint8_t>(Opcode::kHeader)) {
    return fail(ErrorCode::kParseError, "the first record (offset 8) is " + opcodeName(op) + ", not a Header");
  }
  if (Status s = load(op, position, length); !s.ok()) return s;
  auto h = parsed(parse::header(record), topLevel(Opcode::kHeader, position));
  if (!h.ok()) return h.error();
  header = std::move(h).value();
  counts.by_opcode[op]++;
  position += kRecordPrefixBytes + length;

  // The end: magic, and a Footer just before it (its content is 20 bytes). Without them the file was cut short
  // or is still being written; the scan finds out where.
  constexpr std::uint64_t kFooterRecordBytes = kRecordPrefixBytes + 20;
  if (size < 2 * kMagic.size() + kFooterRecordBytes) return {};
  if (Status s = readAt(size - kMagic.size(), magic); !s.ok()) return s;
  if (magic != kMagic) return {};
  const std::uint64_t offset = size - kMagic.size() - kFooterRecordBytes;
  if (offset < position) return {};  // the closing magic overlaps the Header: the scan reports the file as cut off
  std::array<std::uint8_t, kFooterRecordBytes> footer_record{};
  if (Status s = readAt(offset, footer_record); !s.ok()) return s;
  wire::Cursor c(footer_record);
  const std::uint8_t footer_op = c.u8("opcode");
  const std::uint64_t footer_length = c.u64("length");
  if (footer_op != static_cast<std::uint8_t>(Opcode::kFooter) || footer_length != 20) {
    return fail(ErrorCode::kParseError, "the file ends with the magic but has no Footer at offset " +
                                            std::to_string(offset) + " (found " + opcodeName(footer_op) +
                                            " of length " + std::to_string(footer_length) + ")");
  }
  auto footer =
      parsed(parse::footer(Bytes(footer_record).subspan(kRecordPrefixBytes)), topLevel(Opcode::kFooter, offset));
  if (!footer.ok()) return footer.error();
  footer_offset = offset;
  if (options.read_summary && footer->summary_start != 0) return readSummary(footer.value(), offset);
  return {};
}

Status Reader::Impl::readSummary(const Footer& footer, std::uint64_t offset) {
  const Place place = topLevel(Opcode::kFooter, offset);
  if (footer.summary_start < position || footer.summary_start > offset) {
    return fail(ErrorCode::kParseError, place,
                ": summary_start " + std::to_string(footer.summary_start) + " lies outside the file's records");
  }
  if (footer.summary_offset_start != 0 &&
      (footer.summary_offset_start < footer.summary_start || footer.summary_offset_start > offset)) {
    return fail(
        ErrorCode::kParseError, place,
        ": summary_offset_start " + std::to_string(footer.summary_offset_start) + " lies outside the summary section");
  }
  const std::uint64_t summary_bytes = offset - footer.summary_start;
  if (summary_bytes > options.max_record_bytes) {
    return fail(ErrorCode::kResourceExhausted, "summary section at offset " + std::to_string(footer.summary_start) +
                                                   " has " + std::to_string(summary_bytes) +
                                                   " bytes, over max_record_bytes (" +
                                                   std::to_string(options.max_record_bytes) + ")");
  }
  // The summary CRC covers the summary section and the Footer up to its own field.
  std::vector<std::uint8_t> bytes(static_cast<std::size_t>(summary_bytes + kRecordPrefixBytes + 16));
  if (Status s = readAt(footer.summary_start, bytes); !s.ok()) return s;
  if (options.check_crcs && footer.summary_crc != 0) {
    const std::uint32_t crc = codec::crc32(0, bytes);
    if (crc != footer.summary_crc) {
      return fail(ErrorCode::kDataError, place,
                  ": summary_crc mismatch (stored " + hex32(footer.summary_crc) + ", computed " + hex32(crc) + ")");
    }
    counts.crcs_checked++;
  }
  Summary out;
  const Bytes records = Bytes(bytes).first(static_cast<std::size_t>(summary_bytes));
  std::size_t at_byte = 0;
  while (at_byte < records.size()) {
    wire::Cursor c(records.subspan(at_byte));
    const std::uint8_t op = c.u8("opcode");
    const std::uint64_t length = c.u64("length");
    const Place here{op, footer.summary_start + at_byte, std::nullopt};
    if (!c.ok() || length > c.remaining()) {
      return fail(ErrorCode::kParseError, here, " runs past the end of the summary section");
    }
    const Bytes content = c.take(length, "content");
    switch (static_cast<Opcode>(op)) {
      case Opcode::kSchema:
        if (Status st = schemaRecord(content, here); !st.ok()) return st;
        break;
      case Opcode::kChannel:
        if (Status st = channelRecord(content, here); !st.ok()) return st;
        break;
      case Opcode::kStatistics: {
        auto st = parsed(parse::statistics(content), here);
        if (!st.ok()) return st.error();
        out.statistics = std::move(st).value();
        break;
      }
      case Opcode::kChunkIndex: {
        auto i = parsed(parse::chunkIndex(content), here);
        if (!i.ok()) return i.error();
        if (i->chunk_start_offset < kMagic.size() || i->chunk_start_offset > footer.summary_start ||
            i->chunk_length > footer.summary_start - i->chunk_start_offset) {
          return fail(ErrorCode::kParseError, here, ": the chunk it points to lies outside the data section");
        }
        out.chunk_indexes.push_back(std::move(i).value());
        break;
      }
      case Opcode::kAttachmentIndex: {
        auto i = parsed(parse::attachmentIndex(content), here);
        if (!i.ok()) return i.error();
        out.attachment_indexes.push_back(std::move(i).value());
        break;
      }
      case Opcode::kMetadataIndex: {
        auto i = parsed(parse::metadataIndex(content), here);
        if (!i.ok()) return i.error();
        out.metadata_indexes.push_back(std::move(i).value());
        break;
      }
      case Opcode::kSummaryOffset: {
        auto so = parsed(parse::summaryOffset(content), here);
        if (!so.ok()) return so.error();
        if (so->group_start < footer.summary_start || so->group_start > offset ||
            so->group_length > offset - so->group_start) {
          return fail(ErrorCode::kParseError, here, ": its group lies outside the summary section");
        }
        out.summary_offsets.push_back(so.value());
        break;
      }
      case Opcode::kHeader:
      case Opcode::kFooter:
      case Opcode::kMessage:
      case Opcode::kChunk:
      case Opcode::kMessageIndex:
      case Opcode::kAttachment:
      case Opcode::kMetadata:
      case Opcode::kDataEnd:
        return fail(ErrorCode::kParseError, here, ": this record does not belong in the summary section");
      default:
        break;  // a record a newer version of the format added
    }
    at_byte += static_cast<std::size_t>(kRecordPrefixBytes + length);
  }
  summary = std::move(out);
  return {};
}

Status Reader::Impl::startChunk(std::uint64_t offset) {
  const Place here = topLevel(Opcode::kChunk, offset);
  auto fields = parsed(parse::chunk(record), here);
  if (!fields.ok()) return fields.error();
  const parse::ChunkFields& f = fields.value();
  if (f.uncompressed_size > options.max_record_bytes) {
    return fail(ErrorCode::kResourceExhausted, here,
                ": uncompressed_size " + std::to_string(f.uncompressed_size) + " is over max_record_bytes (" +
                    std::to_string(options.max_record_bytes) + ")");
  }
  if (f.compression.empty()) {
    if (f.records.size() != f.uncompressed_size) {
      return fail(ErrorCode::kParseError, here,
                  ": " + std::to_string(f.records.size()) + " bytes of uncompressed records, uncompressed_size says " +
                      std::to_string(f.uncompressed_size));
    }
    chunk_records = f.records;
  } else {
    chunk.resize(static_cast<std::size_t>(f.uncompressed_size));
    if (Status s = decompressor.decompress(f.compression, f.records, chunk); !s.ok()) {
      return fail(s.error().code(), here, ": " + s.error().message());
    }
    chunk_records = chunk;
  }
  if (options.check_crcs && f.uncompressed_crc != 0) {
    const std::uint32_t crc = codec::crc32(0, chunk_records);
    if (crc != f.uncompressed_crc) {
      return fail(
          ErrorCode::kDataError, here,
          ": uncompressed_crc mismatch (stored " + hex32(f.uncompressed_crc) + ", computed " + hex32(crc) + ")");
    }
    counts.crcs_checked++;
  }
  counts.chunks++;
  chunk_offset = offset;
  chunk_position = 0;
  in_chunk = true;
  return {};
}

Result<bool> Reader::Impl::nextInChunk(MessageView& out) {
  while (chunk_position < chunk_records.size()) {
    wire::Cursor c(chunk_records.subspan(chunk_position));
    const std::uint8_t op = c.u8("opcode");
    const std::uint64_t length = c.u64("length");
    const Place here{op, chunk_position, chunk_offset};
    if (!c.ok() || length > c.remaining()) {
      return fail(ErrorCode::kParseError, here, " runs past the end of the chunk's records");
    }
    const Bytes content = c.take(length, "content");
    chunk_position += static_cast<std::size_t>(kRecordPrefixBytes + length);
    counts.by_opcode[op]++;
    switch (static_cast<Opcode>(op)) {
      case Opcode::kMessage:
        if (Status s = messageRecord(content, here, chunk_offset, out); !s.ok()) return s.error();
        return true;
      case Opcode::kSchema:
        if (Status s = schemaRecord(content, here); !s.ok()) return s.error();
        break;
      case Opcode::kChannel:
        if (Status s = channelRecord(content, here); !s.ok()) return s.error();
        break;
      case Opcode::kHeader:
      case Opcode::kFooter:
      case Opcode::kChunk:
      case Opcode::kMessageIndex:
      case Opcode::kChunkIndex:
      case Opcode::kAttachment:
      case Opcode::kAttachmentIndex:
      case Opcode::kStatistics:
      case Opcode::kMetadata:
      case Opcode::kMetadataIndex:
      case Opcode::kSummaryOffset:
      case Opcode::kDataEnd:
        // Chunks hold Schema, Channel and Message records only; anything else (a chunk inside a chunk above all)
        // is a broken file.
        return fail(ErrorCode::kParseError, here, ": this record does not belong in a chunk");
      default:
        break;  // a record a newer version of the format added
    }
  }
  in_chunk = false;
  return false;
}

Status Reader::Impl::endOfData(std::uint64_t offset, std::uint64_t length) {
  const Place here = topLevel(Opcode::kDataEnd, offset);
  // The data section CRC covers everything before the DataEnd record: take the value before this record's bytes.
  const std::uint32_t computed = data_crc_before_record;
  const bool checking = inDataSection();
  phase = Phase::kSummary;
  if (Status s = load(here.op, offset, length); !s.ok()) return s;
  auto crc = parsed(parse::dataEnd(record), here);
  if (!crc.ok()) return crc.error();
  if (checking && crc.value() != 0) {
    if (crc.value() != computed) {
      return fail(ErrorCode::kDataError, here,
                  ": data_section_crc mismatch (stored " + hex32(crc.value()) + ", computed " + hex32(computed) + ")");
    }
    counts.crcs_checked++;
  }
  return {};
}

Status Reader::Impl::footerReached(std::uint64_t offset, std::uint64_t length) {
  const Place here = topLevel(Opcode::kFooter, offset);
  if (Status s = load(here.op, offset, length); !s.ok()) return s;
  auto footer = parsed(parse::footer(record), here);
  if (!footer.ok()) return footer.error();
  const std::uint64_t end = offset + kRecordPrefixBytes + length;
  const std::uint64_t size = source->size();
  if (size - end < kMagic.size()) {
    return fail(ErrorCode::kParseError, "the file ends at " + std::to_string(size) + " inside the closing magic");
  }
  std::array<std::uint8_t, kMagic.size()> magic{};
  if (Status s = readAt(end, magic); !s.ok()) return s;
  if (magic != kMagic) return fail(ErrorCode::kParseError, here, ": no closing magic follows it");
  if (size - end > kMagic.size()) {
    return fail(ErrorCode::kParseError, std::to_string(size - end - kMagic.size()) +
                                            " bytes follow the closing magic at offset " + std::to_string(end));
  }
  if (footer_offset && *footer_offset != offset) {
    return fail(ErrorCode::kParseError, here, ": not the Footer the end of the file points to");
  }
  phase = Phase::kDone;
  return {};
}

Status Reader::Impl::readAttachment(std::uint64_t offset, std::uint64_t length) {
  // Attachments can be of any size: their fields are read one by one and the data is streamed for the CRCs.
  const Place here = topLevel(Opcode::kAttachment, offset);
  const std::uint64_t content = offset + kRecordPrefixBytes;
  std::uint64_t used = 0;
  const auto next_field = [&](std::uint64_t n, const char* field_name) -> Status {
    if (n > length - used) {
      return fail(ErrorCode::kParseError, here,
                  std::string(": field '") + field_name + "' runs past the end of the record");
    }
    if (n > options.max_record_bytes) {
      return fail(ErrorCode::kResourceExhausted, here,
                  std::string(": field '") + field_name + "' is over max_record_bytes");
    }
    field.resize(static_cast<std::size_t>(n));
    if (Status s = readAt(content + used, field); !s.ok()) return s;
    used += n;
    return {};
  };
  const auto integer = [&](std::size_t n, const char* field_name) -> Result<std::uint64_t> {
    if (Status s = next_field(n, field_name); !s.ok()) return s.error();
    std::uint64_t v = 0;
    for (std::size_t i = 0; i < n; ++i) v |= std::uint64_t{field[i]} << (8 * i);
    return v;
  };
  const auto text = [&](const char* field_name) -> Result<std::string> {
    auto n = integer(4, field_name);
    if (!n.ok()) return n.error();
    if (Status s = next_field(n.value(), field_name); !s.ok()) return s.error();
    return std::string(field.begin(), field.end());
  };
  AttachmentInfo info;
  info.record_offset = offset;
  auto log_time = integer(8, "log_time");
  if (!log_time.ok()) return log_time.error();
  auto create_time = integer(8, "create_time");
  if (!create_time.ok()) return create_time.error();
  auto name = text("name");
  if (!name.ok()) return name.error();
  auto media_type = text("media_type");
  if (!media_type.ok()) return media_type.error();
  auto data_size = integer(8, "data");
  if (!data_size.ok()) return data_size.error();
  if (data_size.value() > length - used || length - used - data_size.value() < 4) {
    return fail(ErrorCode::kParseError, here,
                ": data of " + std::to_string(data_size.value()) + " bytes and the crc run past the end of the record");
  }
  info.log_time_ns = log_time.value();
  info.create_time_ns = create_time.value();
  info.name = std::move(name).value();
  info.media_type = std::move(media_type).value();
  info.data_size = data_size.value();
  info.data_offset = content + used;
  const std::uint64_t crc_at = used + info.data_size;
  std::uint32_t crc = 0;
  if (Status s = stream(offset, length, crc_at, crc); !s.ok()) return s;
  used = crc_at;
  auto stored = integer(4, "crc");
  if (!stored.ok()) return stored.error();
  if (options.check_crcs && stored.value() != 0) {
    if (stored.value() != crc) {
      return fail(ErrorCode::kDataError, here,
                  ": crc mismatch (stored " + hex32(static_cast<std::uint32_t>(stored.value())) + ", computed " +
                      hex32(crc) + ")");
    }
    counts.crcs_checked++;
  }
  if (Status s = addDefinitionBytes(info.name.size() + info.media_type.size() + 64, here); !s.ok()) return s;
  attachments.push_back(std::move(info));
  return {};
}

Result<bool> Reader::Impl::nextTopLevel(MessageView& out) {
  while (phase == Phase::kData || phase == Phase::kSummary) {
    if (in_chunk) {
      auto r = nextInChunk(out);
      if (!r.ok() || r.value()) return r;
      continue;
    }
    const std::uint64_t offset = position;
    if (offset == source->size()) {
      return fail(ErrorCode::kParseError, "the file ends at offset " + std::to_string(offset) +
                                              " without a Footer (cut short, or still being written)");
    }
    auto prefix = recordPrefix(offset);
    if (!prefix.ok()) return prefix.error();
    const auto [op, length] = prefix.value();
    position = offset + kRecordPrefixBytes + length;
    counts.by_opcode[op]++;
    const Place here{op, offset, std::nullopt};

    if (static_cast<Opcode>(op) == Opcode::kFooter) {
      if (Status s = footerReached(offset, length); !s.ok()) return s.error();
      return false;
    }
    // The summary was read at open (or is not wanted): step over it to the Footer. Its length is inside the file.
    if (phase == Phase::kSummary) continue;
    // Records read whole: loaded first (bounded by max_record_bytes), then parsed.
    switch (static_cast<Opcode>(op)) {
      case Opcode::kMessage:
      case Opcode::kChunk:
      case Opcode::kSchema:
      case Opcode::kChannel:
      case Opcode::kMessageIndex:
      case Opcode::kMetadata:
        if (Status s = load(op, offset, length); !s.ok()) return s.error();
        break;
      default:
        break;
    }
    switch (static_cast<Opcode>(op)) {
      case Opcode::kMessage:
        if (Status s = messageRecord(record, here, offset, out); !s.ok()) return s.error();
        return true;
      case Opcode::kChunk:
        if (Status s = startChunk(offset); !s.ok()) return s.error();
        break;
      case Opcode::kSchema:
        if (Status s = schemaRecord(record, here); !s.ok()) return s.error();
        break;
      case Opcode::kChannel:
        if (Status s = channelRecord(record, here); !s.ok()) return s.error();
        break;
      case Opcode::kMessageIndex: {
        // Not needed for a forward scan, but a malformed one is a broken file.
        auto i = parsed(parse::messageIndex(record), here);
        if (!i.ok()) return i.error();
        break;
      }
      case Opcode::kMetadata: {
        auto m = parsed(parse::metadata(record), here);
        if (!m.ok()) return m.error();
        std::uint64_t bytes = m->name.size() + 64;
        for (const auto& [key, value] : m->entries) bytes += key.size() + value.size() + 64;
        if (Status st = addDefinitionBytes(bytes, here); !st.ok()) return st.error();
        metadata.push_back(std::move(m).value());
        break;
      }
      case Opcode::kAttachment:
        if (Status s = readAttachment(offset, length); !s.ok()) return s.error();
        break;
      case Opcode::kDataEnd:
        if (Status s = endOfData(offset, length); !s.ok()) return s.error();
        break;
      case Opcode::kHeader:
        return fail(ErrorCode::kParseError, here, ": a second Header");
      default: {
        // ChunkIndex, the other summary records and unknown opcodes: not needed to read the messages.
        std::uint32_t unused = 0;
        if (Status s = stream(offset, length, 0, unused); !s.ok()) return s.error();
        break;
      }
    }
  }
  return false;
}

Reader::Reader(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
Reader::Reader(Reader&&) noexcept = default;
Reader& Reader::operator=(Reader&&) noexcept = default;
Reader::~Reader() = default;

Result<Reader> Reader::start(std::unique_ptr<Impl> impl) {
  if (Status s = impl->options.validate(); !s.ok()) return s.error();
  if (Status s = impl->openFile(); !s.ok()) return s.error();
  return Reader(std::move(impl));
}

Result<Reader> Reader::open(const std::filesystem::path& path, ReaderOptions options) {
  auto source = openFileSource(path);
  if (!source.ok()) return source.error();
  auto impl = std::make_unique<Impl>();
  impl->source = std::move(source).value();
  impl->file_name = path.string();
  impl->options = options;
  return start(std::move(impl));
}

Result<Reader> Reader::openBytes(std::vector<std::uint8_t> bytes, ReaderOptions options, std::string name) {
  auto impl = std::make_unique<Impl>();
  impl->source = memorySource(std::move(bytes));
  impl->file_name = std::move(name);
  impl->options = options;
  return start(std::move(impl));
}

Result<bool> Reader::next(MessageView& out) {
  Impl& m = *impl_;
  if (m.error) return *m.error;
  if (m.phase == Phase::kDone) return false;
  auto r = m.nextTopLevel(out);
  if (!r.ok()) {
    m.error = r.error();
    m.phase = Phase::kFailed;
    m.in_chunk = false;
  }
  return r;
}

const Header& Reader::header() const {
  return impl_->header;
}
const std::optional<Summary>& Reader::summary() const {
  return impl_->summary;
}
const std::map<std::uint16_t, Schema>& Reader::schemas() const {
  return impl_->schemas;
}
const std::map<std::uint16_t, Channel>& Reader::channels() const {
  return impl_->channels;
}
const std::vector<Metadata>& Reader::metadata() const {
  return impl_->metadata;
}
const std::vector<AttachmentInfo>& Reader::attachments() const {
  return impl_->attachments;
}
const RecordCounts& Reader::counts() const {
  return impl_->counts;
}
std::uint64_t Reader::fileSize() const {
  return impl_->source->size();
}

}  // namespace cvislam::mcap

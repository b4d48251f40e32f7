// The reader on broken and hostile files: every truncation, flipped CRC-covered bytes, lengths that point past the
// file, chunks that lie about their size or compression, records where they do not belong. Each must give an Error
// that names the problem and the offset, never a crash or an unbounded allocation.
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "common/mcap/reader.hpp"
#include "common/mcap/wire.hpp"
#include "common/mcap/writer.hpp"
#include "test/common/mcap/sample_bag.hpp"

namespace cvislam::mcap {
namespace {

using Bytes = std::vector<std::uint8_t>;

// Reads the whole file; the error if there is one, else an empty string.
std::string readAll(Bytes bytes, ReaderOptions options = {}) {
  auto reader = Reader::openBytes(std::move(bytes), options);
  if (!reader.ok()) return reader.error().message();
  auto listing = test::listMessages(reader.value());
  if (!listing.ok()) return listing.error().message();
  return {};
}

ErrorCode readAllCode(Bytes bytes, ReaderOptions options = {}) {
  auto reader = Reader::openBytes(std::move(bytes), options);
  if (!reader.ok()) return reader.error().code();
  auto listing = test::listMessages(reader.value());
  if (!listing.ok()) return listing.error().code();
  return ErrorCode::kInternal;  // stands for "no error" in these tests
}

Bytes sample(Compression compression, bool use_chunks = true, bool write_summary = true) {
  WriterOptions o;
  o.compression = compression;
  o.use_chunks = use_chunks;
  o.write_summary = write_summary;
  o.chunk_bytes = 2048;
  auto bytes = test::sampleBytes(o, {.imu_messages = 12, .imu_per_image = 6, .width = 8, .height = 6});
  EXPECT_TRUE(bytes.ok());
  return bytes.value();
}

// The offset of the n-th top-level record with opcode `op` (from 0).
std::uint64_t findRecord(const Bytes& file, Opcode op, int n = 0) {
  wire::Cursor c(file);
  c.take(kMagic.size(), "magic");
  while (c.ok() && c.remaining() > kMagic.size()) {
    const std::uint64_t at = c.position();
    const std::uint8_t found = c.u8("opcode");
    c.bytes64("content");
    if (found == static_cast<std::uint8_t>(op) && n-- == 0) return at;
  }
  ADD_FAILURE() << "no " << opcodeName(static_cast<std::uint8_t>(op)) << " record";
  return 0;
}

// Hand-made files: magic, Header, the given records, DataEnd, Footer, magic (CRCs 0: not computed).
class FileBuilder {
 public:
  FileBuilder() {
    e_.raw(std::span<const std::uint8_t>(kMagic));
    const auto at = e_.beginRecord(Opcode::kHeader);
    e_.string("ros2");
    e_.string("hand-made");
    e_.endRecord(at);
  }
  FileBuilder& record(std::uint8_t op, const Bytes& content) {
    e_.u8(op);
    e_.bytes64(content);
    return *this;
  }
  FileBuilder& record(Opcode op, const Bytes& content) { return record(static_cast<std::uint8_t>(op), content); }
  Bytes finish() {
    record(Opcode::kDataEnd, {0, 0, 0, 0});
    record(Opcode::kFooter, Bytes(20, 0));
    e_.raw(std::span<const std::uint8_t>(kMagic));
    return out_;
  }

 private:
  Bytes out_;
  wire::Encoder e_{out_};
};

Bytes schemaContent(std::uint16_t id, const std::string& name) {
  Bytes out;
  wire::Encoder e(out);
  e.u16(id);
  e.string(name);
  e.string("ros2msg");
  e.string("int32 x");
  return out;
}

Bytes channelContent(std::uint16_t id, std::uint16_t schema_id, const std::string& topic) {
  Bytes out;
  wire::Encoder e(out);
  e.u16(id);
  e.u16(schema_id);
  e.string(topic);
  e.string("cdr");
  e.stringMap({});
  return out;
}

Bytes messageContent(std::uint16_t channel_id, std::uint64_t t_ns) {
  Bytes out;
  wire::Encoder e(out);
  e.u16(channel_id);
  e.u32(0);
  e.u64(t_ns);
  e.u64(t_ns);
  e.raw(std::string_view("payload"));
  return out;
}

Bytes withPrefix(Opcode op, const Bytes& content) {
  Bytes out;
  wire::Encoder e(out);
  e.u8(static_cast<std::uint8_t>(op));
  e.bytes64(content);
  return out;
}

Bytes chunkContent(const std::string& compression, const Bytes& records, std::uint64_t uncompressed_size) {
  Bytes out;
  wire::Encoder e(out);
  e.u64(0);
  e.u64(0);
  e.u64(uncompressed_size);
  e.u32(0);
  e.string(compression);
  e.bytes64(records);
  return out;
}

bool contains(const std::string& text, const std::string& part) {
  return text.find(part) != std::string::npos;
}

TEST(Hostile, TruncationAtEveryByteIsAnErrorInEveryLayout) {
  for (const auto& [compression, use_chunks, write_summary] :
       {std::tuple{Compression::kZstd, true, true}, std::tuple{Compression::kLz4, true, true},
        std::tuple{Compression::kNone, true, false}, std::tuple{Compression::kNone, false, true}}) {
    const Bytes file = sample(compression, use_chunks, write_summary);
    ASSERT_EQ(readAll(file), "");
    ASSERT_LT(file.size(), 16000U) << "keep the sample small: every prefix is read";
    for (std::size_t n = 0; n < file.size(); ++n) {
      const std::string error = readAll(Bytes(file.begin(), file.begin() + static_cast<std::ptrdiff_t>(n)));
      EXPECT_NE(error, "") << "a file cut to " << n << " of " << file.size() << " bytes read without error";
      EXPECT_TRUE(contains(error, "mcap: <memory>: ")) << error;
    }
  }
}

TEST(Hostile, ARecordLengthPastTheFileNamesTheLengthAndTheOffset) {
  Bytes file = FileBuilder().finish();
  const std::uint64_t at = findRecord(file, Opcode::kDataEnd);
  const std::uint64_t length = std::uint64_t{1} << 60;
  for (int i = 0; i < 8; ++i) file[at + 1 + i] = static_cast<std::uint8_t>(length >> (8 * i));

  const std::string error = readAll(file);

  EXPECT_TRUE(contains(error, "DataEnd at offset " + std::to_string(at) + " has length 1152921504606846976")) << error;
  EXPECT_TRUE(contains(error, "runs past the end of the file")) << error;
}

TEST(Hostile, AFlippedByteInAnUncompressedChunkFailsItsCrc) {
  Bytes file = sample(Compression::kNone);
  const std::uint64_t chunk = findRecord(file, Opcode::kChunk);
  file[chunk + 80] ^= 0x01;  // inside the first message record

  const std::string error = readAll(file);

  EXPECT_TRUE(contains(error, "Chunk at offset " + std::to_string(chunk) + ": uncompressed_crc mismatch")) << error;
  EXPECT_EQ(readAllCode(file), ErrorCode::kDataError);
}

TEST(Hostile, AFlippedByteInACompressedChunkIsAnError) {
  for (const Compression compression : {Compression::kZstd, Compression::kLz4}) {
    Bytes file = sample(compression);
    const std::uint64_t chunk = findRecord(file, Opcode::kChunk);
    file[chunk + 90] ^= 0x10;

    const std::string error = readAll(file);

    EXPECT_TRUE(contains(error, "Chunk at offset " + std::to_string(chunk))) << error;
    EXPECT_EQ(readAllCode(file), ErrorCode::kDataError) << error;
  }
}

TEST(Hostile, WithCrcChecksOffAFlippedPayloadByteGoesThrough) {
  Bytes file = sample(Compression::kNone);
  file[findRecord(file, Opcode::kChunk) + 80] ^= 0x01;

  EXPECT_EQ(readAll(file, ReaderOptions{.check_crcs = false}), "");
}

TEST(Hostile, AFlippedByteOutsideChunksFailsTheDataSectionCrc) {
  Bytes file = sample(Compression::kNone, false);
  const std::uint64_t message = findRecord(file, Opcode::kMessage, 3);
  file[message + 40] ^= 0x01;

  const std::string error = readAll(file);

  EXPECT_TRUE(contains(
      error, "DataEnd at offset " + std::to_string(findRecord(file, Opcode::kDataEnd)) + ": data_section_crc mismatch"))
      << error;
}

TEST(Hostile, AFlippedByteInTheSummaryFailsTheSummaryCrcAtOpen) {
  Bytes file = sample(Compression::kZstd);
  const std::uint64_t statistics = findRecord(file, Opcode::kStatistics);
  file[statistics + 12] ^= 0x01;

  auto reader = Reader::openBytes(file);

  ASSERT_FALSE(reader.ok());
  EXPECT_TRUE(contains(reader.error().message(), ": summary_crc mismatch")) << reader.error().message();
  // Without the summary the file still reads by its data section.
  EXPECT_EQ(readAll(file, ReaderOptions{.read_summary = false}), "");
}

TEST(Hostile, AFlippedAttachmentByteFailsItsCrc) {
  Bytes file = sample(Compression::kZstd);
  const std::uint64_t attachment = findRecord(file, Opcode::kAttachment);
  file[attachment + 80] ^= 0x01;  // in the data

  const std::string error = readAll(file);

  EXPECT_TRUE(contains(error, "Attachment at offset " + std::to_string(attachment) + ": crc mismatch")) << error;
}

TEST(Hostile, AnUnknownCompressionIsNamed) {
  const Bytes records = withPrefix(Opcode::kMessage, messageContent(1, 5));
  const Bytes file = FileBuilder()
                         .record(Opcode::kChannel, channelContent(1, 0, "/x"))
                         .record(Opcode::kChunk, chunkContent("bz2", records, records.size()))
                         .finish();

  const std::string error = readAll(file);

  EXPECT_TRUE(contains(error, "compression 'bz2' is not supported")) << error;
}

TEST(Hostile, AHugeUncompressedSizeIsRefusedBeforeAllocating) {
  const Bytes file =
      FileBuilder().record(Opcode::kChunk, chunkContent("zstd", {1, 2, 3}, std::uint64_t{1} << 40)).finish();

  EXPECT_EQ(readAllCode(file), ErrorCode::kResourceExhausted);
  EXPECT_TRUE(contains(readAll(file), "over max_record_bytes")) << readAll(file);
}

TEST(Hostile, AChunkThatDecompressesToAnotherSizeIsAnError) {
  // A real zstd chunk whose uncompressed_size is changed by one, both ways.
  for (const int delta : {-1, 1}) {
    Bytes file = sample(Compression::kZstd);
    const std::uint64_t chunk = findRecord(file, Opcode::kChunk);
    file[chunk + kRecordPrefixBytes + 16] = static_cast<std::uint8_t>(file[chunk + kRecordPrefixBytes + 16] + delta);

    const std::string error = readAll(file);

    EXPECT_TRUE(contains(error, "Chunk at offset " + std::to_string(chunk) + ": zstd")) << error;
  }
}

TEST(Hostile, AnUncompressedChunkWhoseSizeDisagreesIsAnError) {
  const Bytes records = withPrefix(Opcode::kMessage, messageContent(1, 5));
  const Bytes file = FileBuilder()
                         .record(Opcode::kChannel, channelContent(1, 0, "/x"))
                         .record(Opcode::kChunk, chunkContent("", records, records.size() + 1))
                         .finish();

  EXPECT_TRUE(contains(readAll(file), "uncompressed_size says")) << readAll(file);
}

TEST(Hostile, AChunkInsideAChunkIsRefused) {
  const Bytes inner = withPrefix(Opcode::kChunk, chunkContent("", {}, 0));
  const Bytes file = FileBuilder().record(Opcode::kChunk, chunkContent("", inner, inner.size())).finish();

  const std::string error = readAll(file);

  EXPECT_TRUE(contains(error, "Chunk at byte 0 of the chunk at offset")) << error;
  EXPECT_TRUE(contains(error, "does not belong in a chunk")) << error;
}

TEST(Hostile, ARecordRunningPastItsChunkIsAnError) {
  Bytes records = withPrefix(Opcode::kMessage, messageContent(1, 5));
  records.resize(records.size() - 3);
  const Bytes file = FileBuilder()
                         .record(Opcode::kChannel, channelContent(1, 0, "/x"))
                         .record(Opcode::kChunk, chunkContent("", records, records.size()))
                         .finish();

  EXPECT_TRUE(contains(readAll(file), "runs past the end of the chunk's records")) << readAll(file);
}

TEST(Hostile, UnknownOpcodesAreSkippedInsideAndOutsideChunks) {
  Bytes records = withPrefix(Opcode::kMessage, messageContent(1, 5));
  Bytes unknown = {0x99, 3, 0, 0, 0, 0, 0, 0, 0, 'a', 'b', 'c'};
  records.insert(records.begin(), unknown.begin(), unknown.end());
  const Bytes file = FileBuilder()
                         .record(0x80, {1, 2, 3, 4})
                         .record(Opcode::kChannel, channelContent(1, 0, "/x"))
                         .record(Opcode::kChunk, chunkContent("", records, records.size()))
                         .finish();
  auto reader = Reader::openBytes(file);
  ASSERT_TRUE(reader.ok());

  auto listing = test::listMessages(reader.value());

  ASSERT_TRUE(listing.ok()) << listing.error().message();
  EXPECT_EQ(reader->counts().messages, 1U);
  EXPECT_EQ(reader->counts().by_opcode[0x80], 1U);
  EXPECT_EQ(reader->counts().by_opcode[0x99], 1U);
}

TEST(Hostile, AMessageOnAnUndefinedChannelIsAnError) {
  const Bytes file = FileBuilder().record(Opcode::kMessage, messageContent(9, 5)).finish();

  EXPECT_TRUE(contains(readAll(file), "channel 9 is not defined")) << readAll(file);
}

TEST(Hostile, AChannelOnAnUndefinedSchemaIsAnError) {
  const Bytes file = FileBuilder().record(Opcode::kChannel, channelContent(1, 4, "/x")).finish();

  EXPECT_TRUE(contains(readAll(file), "refers to schema 4")) << readAll(file);
}

TEST(Hostile, ASchemaRedefinedDifferentlyIsAnError) {
  const Bytes file = FileBuilder()
                         .record(Opcode::kSchema, schemaContent(1, "a/msg/A"))
                         .record(Opcode::kSchema, schemaContent(1, "a/msg/A"))
                         .record(Opcode::kSchema, schemaContent(1, "b/msg/B"))
                         .finish();

  EXPECT_TRUE(contains(readAll(file), "schema 1 differs from its earlier definition")) << readAll(file);
}

TEST(Hostile, SchemaIdZeroIsRefused) {
  const Bytes file = FileBuilder().record(Opcode::kSchema, schemaContent(0, "a/msg/A")).finish();

  EXPECT_TRUE(contains(readAll(file), "schema id 0 is reserved")) << readAll(file);
}

TEST(Hostile, AStringLongerThanItsRecordIsAnError) {
  Bytes content = channelContent(1, 0, "/x");
  content[4] = 0xFF;  // the topic's length
  const Bytes file = FileBuilder().record(Opcode::kChannel, content).finish();

  EXPECT_TRUE(contains(readAll(file), "field 'topic' runs past the end of the record")) << readAll(file);
}

TEST(Hostile, DefinitionsBeyondTheirBudgetAreRefused) {
  const Bytes file = sample(Compression::kZstd);

  EXPECT_EQ(readAllCode(file, ReaderOptions{.max_definition_bytes = 200}), ErrorCode::kResourceExhausted);
}

TEST(Hostile, ChunksBeyondMaxRecordBytesAreRefused) {
  const Bytes file = sample(Compression::kZstd, true, false);

  EXPECT_EQ(readAllCode(file, ReaderOptions{.max_record_bytes = 100}), ErrorCode::kResourceExhausted);
}

TEST(Hostile, NotAnMcapFile) {
  EXPECT_TRUE(contains(readAll({}), "not an MCAP file")) << readAll({});
  const std::string text = "just some text, not a bag";
  EXPECT_TRUE(contains(readAll(Bytes(text.begin(), text.end())), "not an MCAP file"));
  Bytes no_header = FileBuilder().finish();
  no_header[8] = static_cast<std::uint8_t>(Opcode::kSchema);
  EXPECT_TRUE(contains(readAll(no_header), "not a Header")) << readAll(no_header);
}

TEST(Hostile, ASecondHeaderIsAnError) {
  const Bytes file = FileBuilder().record(Opcode::kHeader, Bytes(8, 0)).finish();

  EXPECT_TRUE(contains(readAll(file), "a second Header")) << readAll(file);
}

TEST(Hostile, BytesAfterTheClosingMagicAreAnError) {
  Bytes file = sample(Compression::kZstd);
  file.push_back('x');
  file.push_back('y');

  EXPECT_TRUE(contains(readAll(file), "2 bytes follow the closing magic")) << readAll(file);
}

TEST(Hostile, AFooterPointingOutsideTheFileIsAnError) {
  Bytes file = sample(Compression::kZstd);
  const std::uint64_t footer = file.size() - kMagic.size() - kRecordPrefixBytes - 20;
  file[footer + kRecordPrefixBytes + 7] = 0x7F;  // summary_start's top byte

  auto reader = Reader::openBytes(file);

  ASSERT_FALSE(reader.ok());
  EXPECT_TRUE(contains(reader.error().message(), "summary_start")) << reader.error().message();
}

TEST(Hostile, ARecordThatDoesNotBelongInTheSummaryIsAnError) {
  // A file whose summary holds a Message: built by hand with a real summary CRC of 0.
  Bytes file = FileBuilder().finish();
  file.resize(file.size() - kMagic.size() - kRecordPrefixBytes - 20);  // drop the Footer and the magic
  const std::uint64_t summary_start = file.size();
  wire::Encoder e(file);
  e.u8(static_cast<std::uint8_t>(Opcode::kMessage));
  e.bytes64(messageContent(1, 5));
  e.u8(static_cast<std::uint8_t>(Opcode::kFooter));
  e.u64(20);
  e.u64(summary_start);
  e.u64(0);
  e.u32(0);
  e.raw(std::span<const std::uint8_t>(kMagic));

  auto reader = Reader::openBytes(file);

  ASSERT_FALSE(reader.ok());
  EXPECT_TRUE(contains(reader.error().message(), "does not belong in the summary section")) << reader.error().message();
}

TEST(Hostile, AnErrorStaysTheAnswerOnceTheScanFailed) {
  Bytes file = sample(Compression::kNone);
  file[findRecord(file, Opcode::kChunk) + 80] ^= 0x01;
  auto reader = Reader::openBytes(file);
  ASSERT_TRUE(reader.ok());
  MessageView m;

  const auto first = reader->next(m);
  const auto second = reader->next(m);

  ASSERT_FALSE(first.ok());
  ASSERT_FALSE(second.ok());
  EXPECT_EQ(first.error().message(), second.error().message());
}

TEST(Hostile, AMissingFileIsNotFound) {
  EXPECT_EQ(Reader::open("/nonexistent/bag.mcap").error().code(), ErrorCode::kNotFound);
}

TEST(Hostile, BadOptionsAreRefused) {
  EXPECT_EQ(Reader::openBytes(sample(Compression::kNone), ReaderOptions{.max_record_bytes = 0}).error().code(),
            ErrorCode::kInvalidArgument);
}

}  // namespace
}  // namespace cvislam::mcap

// Writer -> reader round trips in every layout the writer makes (chunks compressed with zstd, LZ4 or not at all,
// no chunks; with and without the summary), read from memory and from a file, with the indexes checked against
// the records they point to.
#include <algorithm>
#include <filesystem>
#include <fstream>
#include <string>
#include <tuple>
#include <vector>

#include <gtest/gtest.h>

#include "common/mcap/reader.hpp"
#include "common/mcap/wire.hpp"
#include "common/mcap/writer.hpp"
#include "common/ros2/messages.hpp"
#include "test/common/mcap/sample_bag.hpp"
#include "test/support/temp_dir.hpp"

namespace cvislam::mcap {
namespace {

using Bytes = std::vector<std::uint8_t>;

struct Layout {
  const char* name;
  bool use_chunks;
  Compression compression;
  bool write_summary;
};

WriterOptions optionsFor(const Layout& layout) {
  WriterOptions o;
  o.use_chunks = layout.use_chunks;
  o.compression = layout.compression;
  o.write_summary = layout.write_summary;
  o.write_summary_offsets = layout.write_summary;
  o.chunk_bytes = 4096;  // several chunks from the sample
  return o;
}

Reader openOrDie(Bytes bytes, ReaderOptions options = {}) {
  auto r = Reader::openBytes(std::move(bytes), options);
  EXPECT_TRUE(r.ok()) << r.error().message();
  return std::move(r).value();
}

// What the sample bag holds, built independently of the reader: one line per message in write order.
std::string expectedListing(const test::SampleOptions& sample) {
  auto bytes = test::sampleBytes(WriterOptions{.use_chunks = false, .write_summary = false}, sample);
  EXPECT_TRUE(bytes.ok());
  // An unchunked file is a plain sequence of records: walk it by hand.
  std::string out;
  std::map<std::uint16_t, std::string> topics;
  wire::Cursor c(bytes.value());
  c.take(kMagic.size(), "magic");
  while (c.remaining() > kMagic.size()) {
    const auto op = static_cast<Opcode>(c.u8("opcode"));
    wire::Cursor record(c.bytes64("record"));
    if (op == Opcode::kChannel) {
      const std::uint16_t id = record.u16("id");
      record.u16("schema_id");
      topics[id] = std::string(record.string("topic"));
    } else if (op == Opcode::kMessage) {
      MessageView m;
      m.channel_id = record.u16("channel_id");
      m.sequence = record.u32("sequence");
      m.log_time_ns = record.u64("log_time");
      m.publish_time_ns = record.u64("publish_time");
      m.data = record.rest();
      Channel channel;
      channel.topic = topics[m.channel_id];
      m.channel = &channel;
      out += test::messageLine(m) + "\n";
    }
  }
  EXPECT_TRUE(c.ok());
  return out;
}

class RoundTrip : public ::testing::TestWithParam<Layout> {};

TEST_P(RoundTrip, EveryMessageComesBackWithItsChannelAndSchema) {
  const test::SampleOptions sample;
  auto bytes = test::sampleBytes(optionsFor(GetParam()), sample);
  ASSERT_TRUE(bytes.ok()) << bytes.error().message();
  Reader sut = openOrDie(bytes.value());

  auto listing = test::listMessages(sut);

  ASSERT_TRUE(listing.ok()) << listing.error().message();
  EXPECT_EQ(listing.value(), expectedListing(sample));
  EXPECT_EQ(sut.counts().messages, 40U + 4U + 4U);
  EXPECT_EQ(sut.header().profile, "ros2");
  ASSERT_EQ(sut.channels().size(), 3U);
  const Channel& cam = sut.channels().at(2);
  EXPECT_EQ(cam.topic, "/cam0/image_raw");
  EXPECT_EQ(cam.message_encoding, "cdr");
  EXPECT_EQ(cam.metadata.at("offered_qos_profiles"), "");
  EXPECT_EQ(sut.schemas().at(cam.schema_id).name, "sensor_msgs/msg/Image");
  EXPECT_EQ(sut.schemas().at(cam.schema_id).data, ros2::kImageDefinition);
  EXPECT_EQ(sut.channels().at(3).schema_id, 0);
  ASSERT_EQ(sut.metadata().size(), 1U);
  EXPECT_EQ(sut.metadata()[0].entries.at("sequence"), "V1_01");
  ASSERT_EQ(sut.attachments().size(), 1U);
  const AttachmentInfo& a = sut.attachments()[0];
  EXPECT_EQ(a.name, "calibration.yaml");
  EXPECT_EQ(std::string(bytes->begin() + static_cast<std::ptrdiff_t>(a.data_offset),
                        bytes->begin() + static_cast<std::ptrdiff_t>(a.data_offset + a.data_size)),
            "cam0: {fx: 458.654, fy: 457.296}\n");
}

TEST_P(RoundTrip, TheMessagesDecodeAsTheRos2MessagesWritten) {
  auto bytes = test::sampleBytes(optionsFor(GetParam()));
  ASSERT_TRUE(bytes.ok());
  Reader sut = openOrDie(bytes.value());
  MessageView m;
  int images = 0;
  int imus = 0;

  for (auto more = sut.next(m); more.ok() && more.value(); more = sut.next(m)) {
    if (m.schema == nullptr) continue;
    if (m.schema->name == ros2::kImageType) {
      auto image = ros2::decodeImage(m.data);
      ASSERT_TRUE(image.ok()) << image.error().message();
      EXPECT_EQ(image->header.frame_id, "cam0");
      EXPECT_EQ(ros2::toNanoseconds(image->header.stamp), static_cast<std::int64_t>(m.log_time_ns));
      EXPECT_TRUE(ros2::checkImageLayout(image.value()).ok());
      EXPECT_EQ(image->data[1], static_cast<std::uint8_t>(7 + m.sequence * 31));
      ++images;
    } else {
      auto imu = ros2::decodeImu(m.data);
      ASSERT_TRUE(imu.ok()) << imu.error().message();
      EXPECT_DOUBLE_EQ(imu->angular_velocity_rad_s.x, 0.01 * m.sequence);
      EXPECT_EQ(imu->orientation_covariance[0], -1.0);
      ++imus;
    }
  }

  EXPECT_EQ(images, 4);
  EXPECT_EQ(imus, 40);
}

TEST_P(RoundTrip, TheSummaryMatchesWhatWasWritten) {
  auto writer = Writer::createInMemory(optionsFor(GetParam()));
  ASSERT_TRUE(writer.ok());
  ASSERT_TRUE(test::writeSample(writer.value()).ok());
  ASSERT_TRUE(writer->close().ok());
  Reader sut = openOrDie(writer->memoryBytes());

  const auto& summary = sut.summary();

  if (!GetParam().write_summary) {
    EXPECT_FALSE(summary.has_value());
    return;
  }
  ASSERT_TRUE(summary.has_value());
  ASSERT_TRUE(summary->statistics.has_value());
  const Statistics& stats = *summary->statistics;
  EXPECT_EQ(stats, writer->statistics());
  EXPECT_EQ(stats.message_count, 48U);
  EXPECT_EQ(stats.schema_count, 2U);
  EXPECT_EQ(stats.channel_count, 3U);
  EXPECT_EQ(stats.attachment_count, 1U);
  EXPECT_EQ(stats.metadata_count, 1U);
  EXPECT_EQ(stats.channel_message_counts.at(1), 40U);
  EXPECT_EQ(stats.message_start_time_ns, test::SampleOptions{}.start_ns);
  EXPECT_EQ(summary->chunk_indexes.size(), stats.chunk_count);
  if (GetParam().use_chunks) {
    EXPECT_GT(stats.chunk_count, 2U);
  }
  EXPECT_EQ(summary->attachment_indexes.size(), 1U);
  EXPECT_EQ(summary->metadata_indexes.size(), 1U);
  // The schemas and channels are known before any message is read.
  EXPECT_EQ(sut.channels().size(), 3U);
  EXPECT_EQ(sut.schemas().size(), 2U);
  // Every group of the summary has its offset record, and it points at records of that opcode.
  const Bytes& file = writer->memoryBytes();
  ASSERT_FALSE(summary->summary_offsets.empty());
  for (const SummaryOffset& o : summary->summary_offsets) {
    EXPECT_EQ(file[o.group_start], o.group_opcode);
  }
  const auto opcodes_with_offsets = summary->summary_offsets.size();
  EXPECT_EQ(opcodes_with_offsets, GetParam().use_chunks ? 6U : 5U);  // no ChunkIndex group without chunks
}

INSTANTIATE_TEST_SUITE_P(Layouts, RoundTrip,
                         ::testing::Values(Layout{"ZstdChunks", true, Compression::kZstd, true},
                                           Layout{"Lz4Chunks", true, Compression::kLz4, true},
                                           Layout{"UncompressedChunks", true, Compression::kNone, true},
                                           Layout{"NoChunks", false, Compression::kNone, true},
                                           Layout{"ZstdChunksNoSummary", true, Compression::kZstd, false},
                                           Layout{"UncompressedChunksNoSummary", true, Compression::kNone, false},
                                           Layout{"NoChunksNoSummary", false, Compression::kNone, false}),
                         [](const ::testing::TestParamInfo<Layout>& p) { return std::string(p.param.name); });

TEST(ChunkIndex, PointsAtItsChunkAndItsMessageIndexesInEveryCompression) {
  for (const Compression compression : {Compression::kZstd, Compression::kLz4, Compression::kNone}) {
    auto bytes = test::sampleBytes(WriterOptions{.chunk_bytes = 4096, .compression = compression});
    ASSERT_TRUE(bytes.ok());
    Reader sut = openOrDie(bytes.value());
    const Bytes& file = bytes.value();
    ASSERT_GT(sut.summary()->chunk_indexes.size(), 2U);

    for (const ChunkIndex& index : sut.summary()->chunk_indexes) {
      ASSERT_LT(index.chunk_start_offset, file.size());
      EXPECT_EQ(file[index.chunk_start_offset], static_cast<std::uint8_t>(Opcode::kChunk));
      EXPECT_EQ(index.compression, compressionName(compression));
      EXPECT_LE(index.message_start_time_ns, index.message_end_time_ns);
      std::uint64_t index_bytes = 0;
      for (const auto& [channel_id, offset] : index.message_index_offsets) {
        ASSERT_LT(offset, file.size());
        EXPECT_EQ(file[offset], static_cast<std::uint8_t>(Opcode::kMessageIndex));
        wire::Cursor c(std::span<const std::uint8_t>(file).subspan(offset + 1));
        index_bytes += kRecordPrefixBytes + c.u64("length");
        EXPECT_EQ(c.u16("channel_id"), channel_id);
      }
      EXPECT_EQ(index_bytes, index.message_index_length);
      // The message index records follow the chunk directly.
      EXPECT_EQ(index.chunk_start_offset + index.chunk_length,
                std::min_element(index.message_index_offsets.begin(), index.message_index_offsets.end(),
                                 [](const auto& a, const auto& b) { return a.second < b.second; })
                    ->second);
    }
  }
}

TEST(MessageIndex, OffsetsInAnUncompressedChunkLeadToMessagesWithTheirLogTimes) {
  WriterOptions o;
  o.compression = Compression::kNone;
  o.chunk_bytes = 1 << 20;  // one chunk
  auto bytes = test::sampleBytes(o);
  ASSERT_TRUE(bytes.ok());
  Reader reader = openOrDie(bytes.value());
  ASSERT_EQ(reader.summary()->chunk_indexes.size(), 1U);
  const ChunkIndex& chunk = reader.summary()->chunk_indexes[0];
  // Chunk content: start, end, uncompressed_size (8 each), crc (4), compression "" (4), records length (8).
  const std::uint64_t records_start = chunk.chunk_start_offset + kRecordPrefixBytes + 8 + 8 + 8 + 4 + 4 + 8;
  int checked = 0;

  for (const auto& [channel_id, index_offset] : chunk.message_index_offsets) {
    wire::Cursor c(std::span<const std::uint8_t>(bytes.value()).subspan(index_offset + kRecordPrefixBytes));
    c.u16("channel_id");
    wire::Cursor entries(c.bytes32("records"));
    std::uint64_t previous_ns = 0;
    while (entries.remaining() > 0) {
      const std::uint64_t log_time_ns = entries.u64("log_time");
      const std::uint64_t offset = entries.u64("offset");
      wire::Cursor message(std::span<const std::uint8_t>(bytes.value()).subspan(records_start + offset));
      EXPECT_EQ(message.u8("opcode"), static_cast<std::uint8_t>(Opcode::kMessage));
      message.u64("length");
      EXPECT_EQ(message.u16("channel_id"), channel_id);
      message.u32("sequence");
      EXPECT_EQ(message.u64("log_time"), log_time_ns);
      EXPECT_GE(log_time_ns, previous_ns);
      previous_ns = log_time_ns;
      ++checked;
    }
  }

  EXPECT_EQ(checked, 48);
}

TEST(Writer, MessagesOutOfTimeOrderGetSortedIndexesAndTrueStatistics) {
  auto sut = Writer::createInMemory(WriterOptions{.compression = Compression::kNone});
  ASSERT_TRUE(sut.ok());
  const auto channel = sut->addChannel(0, "/t", "raw");
  ASSERT_TRUE(channel.ok());
  const Bytes payload{1, 2, 3};
  for (const std::uint64_t t_ns : {300U, 100U, 200U}) {
    ASSERT_TRUE(sut->write({channel.value(), 0, t_ns, t_ns, payload}).ok());
  }

  ASSERT_TRUE(sut->close().ok());

  EXPECT_EQ(sut->statistics().message_start_time_ns, 100U);
  EXPECT_EQ(sut->statistics().message_end_time_ns, 300U);
  Reader reader = openOrDie(sut->memoryBytes());
  const ChunkIndex& chunk = reader.summary()->chunk_indexes.at(0);
  EXPECT_EQ(chunk.message_start_time_ns, 100U);
  EXPECT_EQ(chunk.message_end_time_ns, 300U);
  wire::Cursor c(std::span<const std::uint8_t>(sut->memoryBytes())
                     .subspan(chunk.message_index_offsets.at(1) + kRecordPrefixBytes + 2));
  wire::Cursor entries(c.bytes32("records"));
  EXPECT_EQ(entries.u64("t"), 100U);
  entries.u64("offset");
  EXPECT_EQ(entries.u64("t"), 200U);
  entries.u64("offset");
  EXPECT_EQ(entries.u64("t"), 300U);
  // File order is kept for reading.
  MessageView m;
  ASSERT_TRUE(reader.next(m).value());
  EXPECT_EQ(m.log_time_ns, 300U);
}

TEST(Writer, AFileOnDiskReadsLikeTheSameBytesInMemory) {
  const ::cvislam::test::TempDir dir;
  const auto path = dir / "bag.mcap";
  auto writer = Writer::create(path);
  ASSERT_TRUE(writer.ok()) << writer.error().message();
  ASSERT_TRUE(test::writeSample(writer.value(), {.imu_messages = 400}).ok());
  ASSERT_TRUE(writer->close().ok());
  auto from_file = Reader::open(path);
  ASSERT_TRUE(from_file.ok()) << from_file.error().message();
  std::ifstream in(path, std::ios::binary);
  Bytes bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  Reader from_memory = openOrDie(bytes);

  auto file_listing = test::listMessages(from_file.value());
  auto memory_listing = test::listMessages(from_memory);

  ASSERT_TRUE(file_listing.ok()) << file_listing.error().message();
  ASSERT_TRUE(memory_listing.ok());
  EXPECT_EQ(file_listing.value(), memory_listing.value());
  EXPECT_EQ(from_file->counts().messages, 400U + 40U + 40U);
  EXPECT_EQ(from_file->fileSize(), std::filesystem::file_size(path));
  // Chunk CRCs, the data section CRC, the summary CRC and the attachment CRC were all checked.
  EXPECT_EQ(from_file->counts().crcs_checked, from_file->counts().chunks + 3);
}

TEST(Writer, ARecordingCutAfterFlushReadsUpToTheFlushThenSaysWhereItStops) {
  const ::cvislam::test::TempDir dir;
  const auto path = dir / "live.mcap";
  auto writer = Writer::create(path, WriterOptions{.chunk_bytes = 1 << 20});
  ASSERT_TRUE(writer.ok());
  ASSERT_TRUE(test::writeSample(writer.value(), {.imu_messages = 20}).ok());
  ASSERT_TRUE(writer->flush().ok());
  // What a crash right now leaves on disk:
  const auto cut = dir / "cut.mcap";
  std::filesystem::copy_file(path, cut);

  auto sut = Reader::open(cut);
  ASSERT_TRUE(sut.ok()) << sut.error().message();
  MessageView m;
  int messages = 0;
  Result<bool> more = sut->next(m);
  for (; more.ok() && more.value(); more = sut->next(m)) ++messages;

  EXPECT_EQ(messages, 20 + 2 + 2);
  ASSERT_FALSE(more.ok());
  EXPECT_NE(more.error().message().find("without a Footer"), std::string::npos) << more.error().message();
  EXPECT_TRUE(writer->close().ok());
}

TEST(Writer, AddingTheSameSchemaTwiceGivesOneId) {
  auto sut = Writer::createInMemory();
  ASSERT_TRUE(sut.ok());

  const auto a = sut->addSchema(ros2::kImuType, ros2::kSchemaEncoding, ros2::kImuDefinition);
  const auto b = sut->addSchema(ros2::kImuType, ros2::kSchemaEncoding, ros2::kImuDefinition);

  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(a.value(), b.value());
  EXPECT_EQ(sut->statistics().schema_count, 1U);
}

TEST(Writer, RefusesUnknownChannelsAndSchemasAndUseAfterClose) {
  auto sut = Writer::createInMemory();
  ASSERT_TRUE(sut.ok());
  const Bytes payload{1};

  EXPECT_EQ(sut->addChannel(5, "/x", "cdr").error().code(), ErrorCode::kInvalidArgument);
  EXPECT_EQ(sut->write({7, 0, 0, 0, payload}).error().code(), ErrorCode::kInvalidArgument);
  ASSERT_TRUE(sut->close().ok());
  EXPECT_EQ(sut->addChannel(0, "/x", "cdr").error().code(), ErrorCode::kFailedPrecondition);
  EXPECT_FALSE(sut->close().ok());
}

TEST(Writer, RefusesBadOptions) {
  EXPECT_FALSE(Writer::createInMemory(WriterOptions{.chunk_bytes = 0}).ok());
  EXPECT_FALSE(Writer::createInMemory(WriterOptions{.zstd_level = 40}).ok());
  EXPECT_EQ(Writer::create("/nonexistent-dir/x.mcap").error().code(), ErrorCode::kIoError);
}

TEST(Writer, AnEmptyRecordingIsAValidFile) {
  auto sut = Writer::createInMemory();
  ASSERT_TRUE(sut.ok());
  ASSERT_TRUE(sut->close().ok());
  Reader reader = openOrDie(sut->memoryBytes());
  MessageView m;

  const auto more = reader.next(m);

  ASSERT_TRUE(more.ok()) << more.error().message();
  EXPECT_FALSE(more.value());
  EXPECT_EQ(reader.summary()->statistics->message_count, 0U);
}

TEST(Writer, WithoutCrcsTheFileSaysNotComputed) {
  WriterOptions o;
  o.write_crcs = false;
  auto bytes = test::sampleBytes(o);
  ASSERT_TRUE(bytes.ok());
  Reader sut = openOrDie(bytes.value());

  ASSERT_TRUE(test::listMessages(sut).ok());

  EXPECT_EQ(sut.counts().crcs_checked, 0U);
}

TEST(Writer, AMessageThatFillsTheChunkClosesIt) {
  auto sut = Writer::createInMemory(WriterOptions{.chunk_bytes = 1000});
  ASSERT_TRUE(sut.ok());
  const auto channel = sut->addChannel(0, "/big", "raw");
  ASSERT_TRUE(channel.ok());
  Bytes big(50'000);
  for (std::size_t i = 0; i < big.size(); ++i) big[i] = static_cast<std::uint8_t>(i * 131);
  const Bytes small{9};

  ASSERT_TRUE(sut->write({channel.value(), 0, 1, 1, small}).ok());
  ASSERT_TRUE(sut->write({channel.value(), 1, 2, 2, big}).ok());
  ASSERT_TRUE(sut->write({channel.value(), 2, 3, 3, small}).ok());
  ASSERT_TRUE(sut->close().ok());

  Reader reader = openOrDie(sut->memoryBytes());
  EXPECT_EQ(reader.summary()->statistics->chunk_count, 2U);
  MessageView m;
  ASSERT_TRUE(reader.next(m).value());
  ASSERT_TRUE(reader.next(m).value());
  EXPECT_TRUE(std::equal(m.data.begin(), m.data.end(), big.begin(), big.end()));
}

}  // namespace
}  // namespace cvislam::mcap

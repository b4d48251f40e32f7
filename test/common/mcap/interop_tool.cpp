// The C++ side of the interop check against the npm MCAP and ROS 2 implementations (interop_test.mjs runs it):
//
//   mcap_interop_tool write DIR    writes the sample bag in each of our writer's layouts into DIR, one file each
//   mcap_interop_tool list FILE    reads FILE with our reader: one line per message (sample_bag.hpp's form)
//   mcap_interop_tool decode FILE  decodes each Image and Imu message of FILE with our CDR decoders: one line each
//   mcap_interop_tool counts FILE  reads FILE to the end and prints "messages chunks crcs_checked summary(0/1)"
//
// Exit status 1 with the error on stderr when anything fails.
#include <cstdio>
#include <cstring>
#include <exception>
#include <filesystem>
#include <string>

#include "common/mcap/reader.hpp"
#include "common/mcap/writer.hpp"
#include "common/ros2/messages.hpp"
#include "test/common/mcap/sample_bag.hpp"

namespace {

namespace mcap = cvislam::mcap;
namespace ros2 = cvislam::ros2;
using cvislam::Error;
using cvislam::Status;

int failed(const Error& e) {
  std::fprintf(stderr, "%s\n", e.message().c_str());
  return 1;
}

int writeAll(const std::filesystem::path& dir) {
  struct Layout {
    const char* name = nullptr;
    mcap::WriterOptions options;
  };
  const Layout layouts[] = {
      {"ours-zstd.mcap", {.chunk_bytes = 16384, .compression = mcap::Compression::kZstd}},
      {"ours-lz4.mcap", {.chunk_bytes = 16384, .compression = mcap::Compression::kLz4}},
      {"ours-uncompressed-chunks.mcap", {.chunk_bytes = 16384, .compression = mcap::Compression::kNone}},
      {"ours-unchunked.mcap", {.use_chunks = false}},
      {"ours-zstd-no-summary.mcap",
       {.chunk_bytes = 16384, .compression = mcap::Compression::kZstd, .write_summary = false}},
  };
  for (const Layout& layout : layouts) {
    auto writer = mcap::Writer::create(dir / layout.name, layout.options);
    if (!writer.ok()) return failed(writer.error());
    if (Status s = mcap::test::writeSample(writer.value(), {.imu_messages = 400}); !s.ok()) return failed(s.error());
    if (Status s = writer->close(); !s.ok()) return failed(s.error());
    std::printf("%s\n", layout.name);
  }
  return 0;
}

int list(const std::filesystem::path& file) {
  auto reader = mcap::Reader::open(file);
  if (!reader.ok()) return failed(reader.error());
  auto listing = mcap::test::listMessages(reader.value());
  if (!listing.ok()) return failed(listing.error());
  std::fputs(listing->c_str(), stdout);
  return 0;
}

std::string stamp(const ros2::HeaderView& h) {
  return std::to_string(h.stamp.sec) + "." + std::to_string(h.stamp.nanosec) + " " + std::string(h.frame_id);
}

// A double as the hex of its IEEE-754 bits: equal text means equal values, in any language.
std::string bits(double v) {
  std::uint64_t u = 0;
  std::memcpy(&u, &v, sizeof u);
  char text[24];
  std::snprintf(text, sizeof text, "%016llx", static_cast<unsigned long long>(u));
  return text;
}

int decode(const std::filesystem::path& file) {
  auto reader = mcap::Reader::open(file);
  if (!reader.ok()) return failed(reader.error());
  mcap::MessageView m;
  for (;;) {
    const auto more = reader->next(m);
    if (!more.ok()) return failed(more.error());
    if (!more.value()) return 0;
    if (m.schema == nullptr) continue;
    std::string line = m.channel->topic + " " + std::to_string(m.sequence) + " ";
    if (m.schema->name == ros2::kImageType) {
      auto image = ros2::decodeImage(m.data);
      if (!image.ok()) return failed(image.error());
      line += stamp(image->header) + " " + std::to_string(image->width) + "x" + std::to_string(image->height) + " " +
              std::string(image->encoding) + " " + std::to_string(image->is_bigendian) + " " +
              std::to_string(image->step) + " " + std::to_string(image->data.size());
      for (std::size_t i = 0; i < image->data.size(); i += 97) line += " " + std::to_string(image->data[i]);
    } else if (m.schema->name == ros2::kImuType) {
      auto imu = ros2::decodeImu(m.data);
      if (!imu.ok()) return failed(imu.error());
      const auto& q = imu->orientation;
      const auto& w = imu->angular_velocity_rad_s;
      const auto& a = imu->linear_acceleration_m_s2;
      line += stamp(imu->header);
      for (const double v : {q.x, q.y, q.z, q.w, w.x, w.y, w.z, a.x, a.y, a.z}) line += " " + bits(v);
      for (const auto* covariance :
           {&imu->orientation_covariance, &imu->angular_velocity_covariance, &imu->linear_acceleration_covariance}) {
        for (const double v : *covariance) line += " " + bits(v);
      }
    } else {
      continue;
    }
    std::printf("%s\n", line.c_str());
  }
}

int counts(const std::filesystem::path& file) {
  auto reader = mcap::Reader::open(file);
  if (!reader.ok()) return failed(reader.error());
  auto listing = mcap::test::listMessages(reader.value());
  if (!listing.ok()) return failed(listing.error());
  const mcap::RecordCounts& c = reader->counts();
  std::printf("%llu %llu %llu %d\n", static_cast<unsigned long long>(c.messages),
              static_cast<unsigned long long>(c.chunks), static_cast<unsigned long long>(c.crcs_checked),
              reader->summary().has_value() ? 1 : 0);
  return 0;
}

int run(int argc, char** argv) {
  if (argc != 3) {
    std::fprintf(stderr, "usage: mcap_interop_tool write DIR | list FILE | decode FILE | counts FILE\n");
    return 2;
  }
  const std::string command = argv[1];
  if (command == "write") return writeAll(argv[2]);
  if (command == "list") return list(argv[2]);
  if (command == "decode") return decode(argv[2]);
  if (command == "counts") return counts(argv[2]);
  std::fprintf(stderr, "mcap_interop_tool: unknown command '%s'\n", command.c_str());
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  try {
    return run(argc, argv);
  } catch (const std::exception& e) {  // a bug, or the system out of memory: say so instead of aborting
    std::fprintf(stderr, "mcap_interop_tool: internal error: %s\n", e.what());
    return 1;
  }
}

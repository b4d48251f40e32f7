#include "server_cloud/viewer/mcap_recorder.hpp"

#include <utility>

#include "common/mcap/writer.hpp"
#include "server_cloud/viewer/foxglove_messages.hpp"

namespace cvislam::server::viewer {

Result<McapRecorder> McapRecorder::create(const std::filesystem::path& file) {
  mcap::WriterOptions options;
  options.profile = "";  // not a ROS 2 bag: foxglove schemas, JSON messages
  options.library = "cvislam_server viewer";
  auto writer = mcap::Writer::create(file, options);
  if (!writer) return writer.error().withContext("recording " + file.string());
  return McapRecorder(file, std::make_unique<mcap::Writer>(std::move(*writer)));
}

McapRecorder::McapRecorder(std::filesystem::path file, std::unique_ptr<mcap::Writer> writer)
    : file_(std::move(file)), writer_(std::move(writer)) {}
McapRecorder::McapRecorder(McapRecorder&&) noexcept = default;
McapRecorder& McapRecorder::operator=(McapRecorder&&) noexcept = default;
McapRecorder::~McapRecorder() = default;

Status McapRecorder::write(const std::vector<FeedChannel>& channels, const std::vector<FeedMessage>& messages) {
  for (const FeedMessage& m : messages) {
    if (m.channel >= channels.size()) {
      return Error{ErrorCode::kInvalidArgument, "recording " + file_.string() + ": a message of an unknown channel"};
    }
    auto id = channel_ids_.find(m.channel);
    if (id == channel_ids_.end()) {
      const FeedChannel& c = channels[m.channel];
      auto schema = writer_->addSchema(c.schema_name, "jsonschema", schemaJson(c.schema_name));
      if (!schema) return schema.error().withContext("recording " + file_.string());
      auto channel = writer_->addChannel(*schema, c.topic, "json");
      if (!channel) return channel.error().withContext("recording " + file_.string());
      id = channel_ids_.emplace(m.channel, *channel).first;
    }
    mcap::Message message;
    message.channel_id = id->second;
    message.sequence = sequences_[m.channel]++;
    message.log_time_ns = static_cast<std::uint64_t>(m.t_unix_ns);
    message.publish_time_ns = message.log_time_ns;
    message.data = {reinterpret_cast<const std::uint8_t*>(m.payload.data()), m.payload.size()};
    if (Status s = writer_->write(message); !s.ok()) return s.error().withContext("recording " + file_.string());
    ++messages_;
  }
  return Status::Ok();
}

Status McapRecorder::flush() {
  return writer_->flush();
}

Status McapRecorder::close() {
  return writer_->close();
}

}  // namespace cvislam::server::viewer

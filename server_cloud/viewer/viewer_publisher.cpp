#include "server_cloud/viewer/viewer_publisher.hpp"

#include <pthread.h>

#include <chrono>
#include <cstdio>
#include <system_error>

#include "server_cloud/stack/map_stack.hpp"

namespace cvislam::server::viewer {
namespace {

std::int64_t unixNowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::system_clock::now().time_since_epoch())
      .count();
}

// A mission name as a file name: letters, digits, '-', '_' and '.' kept, anything else '_'.
std::string fileNameOf(const std::string& mission) {
  std::string out = mission;
  for (char& c : out) {
    const bool ok =
        (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '-' || c == '_' || c == '.';
    if (!ok) c = '_';
  }
  if (out.empty() || out[0] == '.') out = "_" + out;
  return out;
}

}  // namespace

Status PublisherOptions::validate() const {
  if (!(period_s >= 0.01 && period_s <= 60.0)) {
    return Error{ErrorCode::kInvalidArgument, "viewer: the period must be 0.01 to 60 s"};
  }
  if (!(flush_period_s > 0.0)) return Error{ErrorCode::kInvalidArgument, "viewer: the flush period must be > 0"};
  return feed.validate();
}

Result<std::unique_ptr<ViewerPublisher>> ViewerPublisher::start(const MissionRegistry& missions, ViewerHub* hub,
                                                                const PublisherOptions& options) {
  if (Status s = options.validate(); !s.ok()) return s.error();
  if (!options.record_dir.empty()) {
    std::error_code ec;
    std::filesystem::create_directories(options.record_dir, ec);
    if (ec) {
      return Error{ErrorCode::kInvalidArgument,
                   "cannot make the recording folder " + options.record_dir.string() + ": " + ec.message()};
    }
  }
  std::unique_ptr<ViewerPublisher> publisher(new ViewerPublisher(missions, hub, options));
  publisher->thread_ = std::thread([p = publisher.get()] { p->run(); });
  return publisher;
}

ViewerPublisher::ViewerPublisher(const MissionRegistry& missions, ViewerHub* hub, PublisherOptions options)
    : missions_(missions), hub_(hub), options_(std::move(options)), flushed_at_(std::chrono::steady_clock::now()) {}

ViewerPublisher::~ViewerPublisher() {
  (void)finish();
}

void ViewerPublisher::run() {
  pthread_setname_np(pthread_self(), "viewer_feed");  // its CPU is the viewer's cost: named for top and /proc
  const auto period =
      std::chrono::duration_cast<std::chrono::steady_clock::duration>(std::chrono::duration<double>(options_.period_s));
  std::unique_lock lock(wake_mutex_);
  while (!stopping_) {
    lock.unlock();
    step();
    lock.lock();
    wake_.wait_for(lock, period, [this] { return stopping_; });
  }
}

void ViewerPublisher::step() {
  const std::lock_guard guard(step_mutex_);
  for (const auto& mission : missions_.missions()) {
    const std::string& name = mission->name();
    const bool recorded = !options_.record_dir.empty();
    const bool watched = hub_ != nullptr && hub_->watched(name);
    // A feed that stops being looked at keeps what it last drew: a client that comes later gets that in full, then
    // what changed since, so the two always agree.
    if (!recorded && !watched) continue;
    lookAt(name);
  }
  if (hub_ != nullptr) {
    // Clients that subscribed since the last look: the newest state of their channels first.
    for (const ViewerHub::CatchUp& c : hub_->takeCatchUps()) {
      auto feed = feeds_.find(c.mission);
      if (feed == feeds_.end()) continue;
      std::vector<FeedMessage> full;
      feed->second.fullState(full);
      std::vector<FeedMessage> wanted;
      for (FeedMessage& m : full) {
        if (c.channels.count(m.channel) != 0) wanted.push_back(std::move(m));
      }
      hub_->publishTo(c.client, c.mission, wanted);
    }
  }
  const auto now = std::chrono::steady_clock::now();
  if (now - flushed_at_ >= std::chrono::duration<double>(options_.flush_period_s)) {
    flushed_at_ = now;
    for (auto& [name, recorder] : recorders_) {
      if (Status s = recorder.flush(); !s.ok() && recording_error_.ok()) recording_error_ = s;
    }
  }
}

void ViewerPublisher::lookAt(const std::string& name) {
  auto mission = missions_.find(name);
  if (!mission) return;
  auto feed = feeds_.find(name);
  if (feed == feeds_.end()) feed = feeds_.emplace(name, MissionFeed(name, options_.feed)).first;
  std::vector<FeedMessage> messages;
  feed->second.update(*mission, unixNowNs(), std::chrono::steady_clock::now(), messages);
  if (hub_ != nullptr) {
    hub_->registerChannels(name, feed->second.channels());
    hub_->publish(name, messages);
  }
  if (options_.record_dir.empty() || messages.empty()) return;
  auto recorder = recorders_.find(name);
  if (recorder == recorders_.end()) {
    if (recording_files_.count(name) != 0) return;  // it failed before: said once
    // A restarted server records into a new file beside the old one: truncating would lose what it recorded before.
    std::filesystem::path file = options_.record_dir / (fileNameOf(name) + ".mcap");
    std::error_code ec;
    for (int n = 1; std::filesystem::exists(file, ec); ++n) {
      file = options_.record_dir / (fileNameOf(name) + "." + std::to_string(n) + ".mcap");
    }
    recording_files_[name] = file;
    auto made = McapRecorder::create(file);
    if (!made) {
      std::fprintf(stderr, "[viewer] %s\n", made.error().message().c_str());
      if (recording_error_.ok()) recording_error_ = made.error();
      return;
    }
    recorder = recorders_.emplace(name, std::move(*made)).first;
  }
  if (Status s = recorder->second.write(feed->second.channels(), messages); !s.ok() && recording_error_.ok()) {
    std::fprintf(stderr, "[viewer] %s\n", s.error().message().c_str());
    recording_error_ = s;
  }
}

Status ViewerPublisher::finish() {
  {
    const std::lock_guard lock(wake_mutex_);
    if (finished_) return recording_error_;
    finished_ = true;
    stopping_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) thread_.join();
  step();
  for (auto& [name, recorder] : recorders_) {
    if (Status s = recorder.close(); !s.ok() && recording_error_.ok()) recording_error_ = s;
  }
  return recording_error_;
}

std::map<std::string, std::filesystem::path> ViewerPublisher::recordings() const {
  const std::lock_guard guard(step_mutex_);
  return recording_files_;
}

}  // namespace cvislam::server::viewer

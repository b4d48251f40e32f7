// The viewer's clock: a thread that looks at the missions every `period_s`, and hands what changed to the hub's
// clients (viewer_hub.hpp) and to the recordings (mcap_recorder.hpp). A mission is looked at only while a client
// may see it or it is recorded, so a server without viewers pays nothing. Ingest never waits for it: the feed
// copies under each map's read lock, and messages are built and queued after.
#pragma once

#include <condition_variable>
#include <filesystem>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <thread>

#include "common/core/result.hpp"
#include "server_cloud/viewer/mcap_recorder.hpp"
#include "server_cloud/viewer/mission_feed.hpp"
#include "server_cloud/viewer/viewer_hub.hpp"

namespace cvislam::server {
class MissionRegistry;
}

namespace cvislam::server::viewer {

struct PublisherOptions {
  double period_s = 0.2;
  FeedOptions feed;
  std::filesystem::path record_dir;  // empty: no recordings
  double flush_period_s = 5.0;       // recordings are flushed this often (what a crash can lose)

  [[nodiscard]] Status validate() const;
};

class ViewerPublisher {
 public:
  // `hub` may be null (recording only). Starts the thread; the error names the recording folder when it cannot be made.
  static Result<std::unique_ptr<ViewerPublisher>> start(const MissionRegistry& missions, ViewerHub* hub,
                                                        const PublisherOptions& options);
  ~ViewerPublisher();  // stops the thread and closes the recordings
  ViewerPublisher(const ViewerPublisher&) = delete;
  ViewerPublisher& operator=(const ViewerPublisher&) = delete;

  // One look now, on the caller's thread (tests, and the last look before the recordings close).
  void step();
  // Stops the thread, takes a last look and closes the recordings; the first error is returned. Idempotent.
  Status finish();

  // Where each recorded mission goes.
  [[nodiscard]] std::map<std::string, std::filesystem::path> recordings() const;

 private:
  ViewerPublisher(const MissionRegistry& missions, ViewerHub* hub, PublisherOptions options);
  void run();
  void lookAt(const std::string& mission_name);

  const MissionRegistry& missions_;
  ViewerHub* hub_;
  PublisherOptions options_;
  mutable std::mutex step_mutex_;  // step() from a test and the thread never overlap
  std::map<std::string, MissionFeed> feeds_;
  std::map<std::string, McapRecorder> recorders_;
  std::map<std::string, std::filesystem::path> recording_files_;
  Status recording_error_ = Status::Ok();
  std::chrono::steady_clock::time_point flushed_at_;

  std::mutex wake_mutex_;
  std::condition_variable wake_;
  bool stopping_ = false;
  bool finished_ = false;
  std::thread thread_;
};

}  // namespace cvislam::server::viewer

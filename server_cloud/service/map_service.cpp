#include "server_cloud/service/map_service.hpp"

#include <algorithm>
#include <functional>
#include <utility>
#include <vector>

#include <grpcpp/grpcpp.h>

#include "cvislam/v1/map_service.grpc.pb.h"
#include "server_cloud/maps/map_export.hpp"
#include "server_cloud/maps/map_reader.hpp"
#include "server_cloud/service/grpc_status.hpp"

namespace cvislam::server {

namespace {

// Writes what `produce` makes, one message at a time, then finishes with OK; a client that goes away ends it.
template <typename Message>
class StreamWriter final : public grpc::ServerWriteReactor<Message> {
 public:
  using Producer = std::function<bool(Message&)>;  // fills the next message; false when there is none

  explicit StreamWriter(Producer produce) : produce_(std::move(produce)) { writeNext(); }
  explicit StreamWriter(const grpc::Status& refused) { this->Finish(refused); }

  void OnWriteDone(bool ok) override {
    if (!ok) {
      this->Finish(grpc::Status(grpc::StatusCode::CANCELLED, "the client stopped reading"));
      return;
    }
    writeNext();
  }
  void OnDone() override { delete this; }

 private:
  void writeNext() {
    if (produce_(message_)) {
      this->StartWrite(&message_);
    } else {
      this->Finish(grpc::Status::OK);
    }
  }

  Producer produce_;
  Message message_;
};

// Cuts files into chunks of at most kBytes of data; an empty file still sends one chunk.
class FileChunks {
 public:
  static constexpr std::size_t kBytes = 1U << 20U;
  explicit FileChunks(std::vector<maps::ExportedFile> files) : files_(std::move(files)) {}

  bool next(v1::ExportChunk& chunk) {
    if (file_ >= files_.size()) return false;
    const maps::ExportedFile& f = files_[file_];
    const std::size_t n = std::min(kBytes, f.data.size() - offset_);
    chunk.set_file(f.name);
    chunk.set_data(f.data.substr(offset_, n));
    offset_ += n;
    chunk.set_file_end(offset_ >= f.data.size());
    if (chunk.file_end()) {
      ++file_;
      offset_ = 0;
    }
    return true;
  }

 private:
  std::vector<maps::ExportedFile> files_;
  std::size_t file_ = 0;
  std::size_t offset_ = 0;
};

class MapServiceImpl final : public v1::MapService::CallbackService {
 public:
  explicit MapServiceImpl(ServerCore& core) : core_(core) {}

  grpc::ServerUnaryReactor* ListMissions(grpc::CallbackServerContext* context, const v1::ListMissionsRequest*,
                                         v1::ListMissionsResponse* response) override {
    maps::listMissions(core_.missions(), *response);
    return finish(context, Status{});
  }

  grpc::ServerUnaryReactor* ListMaps(grpc::CallbackServerContext* context, const v1::ListMapsRequest* request,
                                     v1::ListMapsResponse* response) override {
    return finish(context, maps::listMaps(core_.missions(), request->mission(), *response));
  }

  grpc::ServerUnaryReactor* GetTrajectory(grpc::CallbackServerContext* context, const v1::GetTrajectoryRequest* request,
                                          v1::GetTrajectoryResponse* response) override {
    if (request->agent() > 0xFFFFU) {
      return finish(context, Error{ErrorCode::kInvalidArgument,
                                   "agent " + std::to_string(request->agent()) + " is not an agent id (0-65535)"});
    }
    return finish(context, maps::getTrajectory(core_.missions(), request->mission(),
                                               static_cast<AgentId>(request->agent()), *response));
  }

  grpc::ServerWriteReactor<v1::MapChunk>* GetMap(grpc::CallbackServerContext*,
                                                 const v1::GetMapRequest* request) override {
    using Writer = StreamWriter<v1::MapChunk>;
    maps::SnapshotOptions options;
    options.observations = request->observations();
    options.descriptors = request->descriptors();
    auto snapshot = maps::snapshotMap(core_.missions(), request->mission(), request->map_id(), options);
    if (!snapshot) return new Writer(toGrpc(snapshot.error()));
    auto chunker = maps::MapChunker::create(std::move(snapshot).value(), request->max_chunk_bytes());
    if (!chunker) return new Writer(toGrpc(chunker.error()));
    auto shared = std::make_shared<maps::MapChunker>(std::move(chunker).value());
    return new Writer([shared](v1::MapChunk& chunk) { return shared->next(chunk); });
  }

  grpc::ServerWriteReactor<v1::ExportChunk>* ExportMap(grpc::CallbackServerContext*,
                                                       const v1::ExportMapRequest* request) override {
    using Writer = StreamWriter<v1::ExportChunk>;
    std::vector<maps::MapSnapshot> snapshots;
    if (request->has_map_id()) {
      auto one = maps::snapshotMap(core_.missions(), request->mission(), request->map_id());
      if (!one) return new Writer(toGrpc(one.error()));
      snapshots.push_back(std::move(one).value());
    } else {
      auto all = maps::snapshotMission(core_.missions(), request->mission());
      if (!all) return new Writer(toGrpc(all.error()));
      snapshots = std::move(all).value();
    }
    auto files = std::make_shared<FileChunks>(maps::exportMaps(snapshots));
    return new Writer([files](v1::ExportChunk& chunk) { return files->next(chunk); });
  }

 private:
  static grpc::ServerUnaryReactor* finish(grpc::CallbackServerContext* context, const Status& status) {
    auto* reactor = context->DefaultReactor();
    reactor->Finish(toGrpc(status));
    return reactor;
  }

  ServerCore& core_;
};

}  // namespace

std::unique_ptr<grpc::Service> makeMapService(ServerCore& core) {
  return std::make_unique<MapServiceImpl>(core);
}

}  // namespace cvislam::server

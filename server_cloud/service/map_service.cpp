#include "server_cloud/service/map_service.hpp"

#include <algorithm>
#include <chrono>
#include <functional>
#include <mutex>
#include <set>
#include <utility>
#include <vector>

#include <grpcpp/grpcpp.h>

#include "cvislam/v1/map_service.grpc.pb.h"
#include "server_cloud/maps/map_export.hpp"
#include "server_cloud/maps/map_reader.hpp"
#include "server_cloud/service/call_access.hpp"
#include "server_cloud/service/call_canceller.hpp"
#include "server_cloud/service/grpc_status.hpp"
#include "server_cloud/service/read_forwarding.hpp"
#include "server_cloud/service/write_gate.hpp"

namespace cvislam::server {

namespace {

// Map reads that must end by a deadline: a client that stops reading would otherwise keep its snapshot in memory
// for as long as its connection lives. The periodic thread cancels the overdue ones.
class ReadDeadlines {
 public:
  void add(std::chrono::steady_clock::time_point deadline, const std::shared_ptr<CallCanceller>& call) {
    std::lock_guard lock(mutex_);
    calls_.emplace_back(deadline, call);
  }
  void tick(std::chrono::steady_clock::time_point now) {
    std::vector<std::shared_ptr<CallCanceller>> overdue;
    {
      std::lock_guard lock(mutex_);
      for (auto it = calls_.begin(); it != calls_.end();) {
        auto call = it->second.lock();
        if (!call || now >= it->first) {
          if (call) overdue.push_back(std::move(call));
          it = calls_.erase(it);
        } else {
          ++it;
        }
      }
    }
    for (const auto& call : overdue) call->cancel();
  }

 private:
  std::mutex mutex_;
  std::vector<std::pair<std::chrono::steady_clock::time_point, std::weak_ptr<CallCanceller>>> calls_;
};

// Writes what `produce` makes, one message at a time, then finishes with OK; a client that goes away ends it. It
// holds its map-read slot until it is done.
template <typename Message>
class StreamWriter final : public grpc::ServerWriteReactor<Message> {
 public:
  using Producer = std::function<bool(Message&)>;  // fills the next message; false when there is none

  StreamWriter(Producer produce, StreamLimits::Slot slot, std::shared_ptr<CallCanceller> canceller)
      : produce_(std::move(produce)), slot_(std::move(slot)), canceller_(std::move(canceller)) {
    writeNext();
  }
  explicit StreamWriter(const grpc::Status& refused) { this->Finish(refused); }

  void OnWriteDone(bool ok) override {
    if (!ok) {
      this->Finish(grpc::Status(grpc::StatusCode::CANCELLED,
                                "the client stopped reading, or the read took longer than limits.map_read_timeout_s"));
      return;
    }
    writeNext();
  }
  void OnDone() override {
    if (canceller_) canceller_->ended();
    delete this;
  }

 private:
  void writeNext() {
    if (produce_(message_)) {
      this->StartWrite(&message_);
    } else {
      this->Finish(grpc::Status::OK);
    }
  }

  Producer produce_;
  StreamLimits::Slot slot_;
  std::shared_ptr<CallCanceller> canceller_;
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

v1::MissionEventMessage::Kind toWire(MissionEvent::Kind kind) {
  switch (kind) {
    case MissionEvent::Kind::kAgentConnected:
      return v1::MissionEventMessage::AGENT_CONNECTED;
    case MissionEvent::Kind::kAgentDisconnected:
      return v1::MissionEventMessage::AGENT_DISCONNECTED;
    case MissionEvent::Kind::kKeyframeAdded:
      return v1::MissionEventMessage::KEYFRAME_ADDED;
    case MissionEvent::Kind::kKeyframeRemoved:
      return v1::MissionEventMessage::KEYFRAME_REMOVED;
    case MissionEvent::Kind::kMapsMerged:
      return v1::MissionEventMessage::MAPS_MERGED;
    case MissionEvent::Kind::kMapCorrected:
      return v1::MissionEventMessage::MAP_CORRECTED;
  }
  return v1::MissionEventMessage::KIND_UNSPECIFIED;
}

class WatchReactor;

// The open WatchMission streams. Lock order: the registry before a reactor.
class WatchRegistry {
 public:
  // Registers r and runs start under the registry's lock, so that start (which locks r) keeps the lock order
  // and no tick reaches r before it has started.
  template <typename F>
  bool add(WatchReactor* r, F&& start) {
    std::lock_guard lock(mutex_);
    if (stopped_) return false;
    reactors_.insert(r);
    start();
    return true;
  }
  void remove(WatchReactor* r) {
    std::lock_guard lock(mutex_);
    reactors_.erase(r);
  }
  template <typename F>
  void forEach(F&& f) {
    std::lock_guard lock(mutex_);
    for (WatchReactor* r : reactors_) f(*r);
  }
  void stop() {
    std::lock_guard lock(mutex_);
    stopped_ = true;
  }

 private:
  std::mutex mutex_;
  std::set<WatchReactor*> reactors_;
  bool stopped_ = false;
};

// One WatchMission stream: one write in flight at a time, each carrying every event the log gained since the
// last (up to kMaxEvents). Callbacks and the periodic tick lock `mutex_`.
class WatchReactor final : public grpc::ServerWriteReactor<v1::WatchMissionResponse> {
 public:
  static constexpr std::size_t kMaxEvents = 512;

  WatchReactor(std::shared_ptr<Mission> mission, std::uint64_t from, WatchRegistry& registry)
      : mission_(std::move(mission)), next_(from), registry_(registry) {
    const bool added = registry_.add(this, [this] {
      std::lock_guard lock(mutex_);
      registered_ = true;
      sendLocked();
    });
    if (!added) {
      std::lock_guard lock(mutex_);
      finishLocked(grpc::Status(grpc::StatusCode::UNAVAILABLE, "the server is stopping"));
    }
  }

  void OnWriteDone(bool ok) override {
    std::lock_guard lock(mutex_);
    if (auto status = gate_.writeDone()) {
      Finish(std::move(*status));
      return;
    }
    if (!ok) {
      finishLocked(grpc::Status(grpc::StatusCode::CANCELLED, "the client stopped reading"));
      return;
    }
    sendLocked();
  }
  void OnCancel() override {
    std::lock_guard lock(mutex_);
    finishLocked(grpc::Status(grpc::StatusCode::CANCELLED, "cancelled"));
  }
  void OnDone() override {
    if (registered_) registry_.remove(this);
    delete this;
  }

  void tick() {
    std::lock_guard lock(mutex_);
    sendLocked();
  }
  void stop() {
    std::lock_guard lock(mutex_);
    finishLocked(grpc::Status(grpc::StatusCode::UNAVAILABLE, "the server is stopping"));
  }

 private:
  void sendLocked() {
    if (!gate_.writable()) return;
    if (mission_->retired()) {  // another replica serves it now: a new watch is forwarded there
      finishLocked(grpc::Status(grpc::StatusCode::UNAVAILABLE,
                                "the mission moved to another replica: watch again from the next event number"));
      return;
    }
    MissionEventLog::Page page = mission_->events().read(next_, kMaxEvents);
    if (page.events.empty() && page.skipped == 0) return;
    next_ = page.next;
    response_.Clear();
    response_.set_skipped(page.skipped);
    for (const MissionEvent& e : page.events) {
      v1::MissionEventMessage& m = *response_.add_events();
      m.set_number(e.number);
      m.set_t_unix_ns(e.t_unix_ns);
      m.set_kind(toWire(e.kind));
      m.set_agent(e.agent);
      if (e.kind == MissionEvent::Kind::kKeyframeAdded || e.kind == MissionEvent::Kind::kKeyframeRemoved) {
        m.mutable_keyframe()->set_agent(e.keyframe.agent);
        m.mutable_keyframe()->set_counter(e.keyframe.counter);
      }
      m.set_map_id(e.map);
      m.set_from_map_id(e.from_map);
      m.set_keyframes(e.keyframes);
      m.set_cause(e.cause);
    }
    gate_.writeStarted();
    StartWrite(&response_);
  }
  void finishLocked(const grpc::Status& status) {
    if (auto now = gate_.finish(status)) Finish(std::move(*now));
  }

  std::shared_ptr<Mission> mission_;
  std::uint64_t next_;
  WatchRegistry& registry_;
  bool registered_ = false;
  std::mutex mutex_;
  v1::WatchMissionResponse response_;
  WriteGate gate_;
};

// ListMissions across the replicas: this replica's missions, then each other replica's answer as it comes; the
// call finishes with the last one. A replica that does not answer fails the call (a partial list would look
// complete), naming it.
class MissionGather {
 public:
  MissionGather(grpc::ServerUnaryReactor* reactor, v1::ListMissionsResponse* response, std::size_t pending)
      : reactor_(reactor), response_(response), pending_(pending) {}

  void add(const grpc::Status& status, const v1::ListMissionsResponse& part, const std::string& address) {
    std::lock_guard lock(mutex_);
    if (!status.ok() && failed_.ok()) {
      failed_ = grpc::Status(status.error_code(),
                             "listing the missions of the replica at " + address +
                                 " (ask again shortly if it has just stopped): " + status.error_message());
    }
    for (const v1::MissionInfo& info : part.missions()) {
      auto* missions = response_->mutable_missions();
      // A mission this replica lost to another is stale here: the owner's entry replaces it.
      missions->erase(std::remove_if(missions->begin(), missions->end(),
                                     [&](const v1::MissionInfo& m) { return m.name() == info.name(); }),
                      missions->end());
      *missions->Add() = info;
    }
    if (--pending_ > 0) return;
    if (!failed_.ok()) {
      reactor_->Finish(failed_);
      return;
    }
    auto* missions = response_->mutable_missions();
    std::sort(missions->begin(), missions->end(),
              [](const v1::MissionInfo& a, const v1::MissionInfo& b) { return a.name() < b.name(); });
    reactor_->Finish(grpc::Status::OK);
  }

 private:
  std::mutex mutex_;
  grpc::ServerUnaryReactor* reactor_;
  v1::ListMissionsResponse* response_;
  std::size_t pending_;
  grpc::Status failed_;
};

class MapServiceImpl final : public v1::MapService::CallbackService {
 public:
  explicit MapServiceImpl(ServerCore& core) : core_(core) {}

  WatchRegistry& watches() { return watches_; }
  ReadDeadlines& deadlines() { return deadlines_; }
  void forwardWith(std::shared_ptr<grpc::ChannelCredentials> credentials) {
    peers_ = std::make_unique<PeerStubs<v1::MapService>>(std::move(credentials));
  }

  grpc::ServerUnaryReactor* ListMissions(grpc::CallbackServerContext* context, const v1::ListMissionsRequest* request,
                                         v1::ListMissionsResponse* response) override {
    const std::string token = presentedToken(*context);
    if (Status s = admitCall(core_, *context, token, "", "ListMissions"); !s.ok()) return finish(context, s);
    // With tokens on, a listing needs a token that opens something: an anonymous caller would make every
    // replica fan out and query the leases for an empty answer.
    if (core_.tokens().enabled() && !core_.tokens().opensAny(token)) {
      return finish(context, Error{ErrorCode::kUnauthenticated,
                                   "ListMissions needs a mission's token: send gRPC metadata 'authorization: Bearer "
                                   "<token>' (--token, or CVISLAM_TOKEN)"});
    }
    maps::listMissions(core_.missions(), *response);
    // Only the missions the caller's token opens: a client of one mission does not learn the others.
    auto* missions = response->mutable_missions();
    missions->erase(std::remove_if(missions->begin(), missions->end(),
                                   [&](const v1::MissionInfo& m) { return !core_.tokens().admits(m.name(), token); }),
                    missions->end());
    // Scale-out: the other replicas' missions too (each answers for its own, with the caller's token).
    MissionOwnership* ownership = core_.ownership();
    if (ownership == nullptr || peers_ == nullptr || wasForwarded(*context)) return finish(context, Status{});
    auto others = ownership->others();
    if (!others) return finish(context, others.error().withContext("listing the other replicas"));
    if (others->empty()) return finish(context, Status{});
    grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
    auto gather = std::make_shared<MissionGather>(reactor, response, others->size());
    for (const MissionOwner& other : *others) {
      std::shared_ptr<grpc::ClientContext> call = forwardingContext(*context, /*unary=*/true);
      auto part = std::make_shared<v1::ListMissionsResponse>();
      peers_->get(other.address)
          .async()
          ->ListMissions(call.get(), request, part.get(),
                         [gather, call, part, address = other.address](const grpc::Status& status) {
                           gather->add(status, *part, address);
                         });
    }
    return reactor;
  }

  grpc::ServerUnaryReactor* ListMaps(grpc::CallbackServerContext* context, const v1::ListMapsRequest* request,
                                     v1::ListMapsResponse* response) override {
    if (Status s = admitCall(core_, *context, request->mission(), "ListMaps"); !s.ok()) return finish(context, s);
    auto owner = readRoute(*context, request->mission());
    if (!owner) return finish(context, owner.error());
    if (!owner->empty()) {
      return forwardUnary(context, *owner, [&](grpc::ClientContext* call, auto done) {
        peers_->get(*owner).async()->ListMaps(call, request, response, std::move(done));
      });
    }
    return finish(context, maps::listMaps(core_.missions(), request->mission(), *response));
  }

  grpc::ServerUnaryReactor* GetTrajectory(grpc::CallbackServerContext* context, const v1::GetTrajectoryRequest* request,
                                          v1::GetTrajectoryResponse* response) override {
    if (Status s = admitCall(core_, *context, request->mission(), "GetTrajectory"); !s.ok()) {
      return finish(context, s);
    }
    auto owner = readRoute(*context, request->mission());
    if (!owner) return finish(context, owner.error());
    if (!owner->empty()) {
      return forwardUnary(context, *owner, [&](grpc::ClientContext* call, auto done) {
        peers_->get(*owner).async()->GetTrajectory(call, request, response, std::move(done));
      });
    }
    if (request->agent() > 0xFFFFU) {
      return finish(context, Error{ErrorCode::kInvalidArgument,
                                   "agent " + std::to_string(request->agent()) + " is not an agent id (0-65535)"});
    }
    return finish(context, maps::getTrajectory(core_.missions(), request->mission(),
                                               static_cast<AgentId>(request->agent()), *response));
  }

  grpc::ServerWriteReactor<v1::MapChunk>* GetMap(grpc::CallbackServerContext* context,
                                                 const v1::GetMapRequest* request) override {
    using Writer = StreamWriter<v1::MapChunk>;
    if (Status s = admitCall(core_, *context, request->mission(), "GetMap"); !s.ok()) return new Writer(toGrpc(s));
    auto owner = readRoute(*context, request->mission());
    if (!owner) return new Writer(toGrpc(owner.error()));
    if (!owner->empty()) {
      return relayFromOwner<v1::MapChunk>(*context, *owner, request, &v1::MapService::Stub::async::GetMap);
    }
    auto slot = core_.openMapReadSlot(peerAddress(*context));
    if (!slot) return new Writer(toGrpc(slot.error()));
    maps::SnapshotOptions options;
    options.observations = request->observations();
    options.descriptors = request->descriptors();
    auto snapshot = maps::snapshotMap(core_.missions(), request->mission(), request->map_id(), options);
    if (!snapshot) return new Writer(toGrpc(snapshot.error()));
    auto chunker = maps::MapChunker::create(std::move(snapshot).value(), request->max_chunk_bytes());
    if (!chunker) return new Writer(toGrpc(chunker.error()));
    auto shared = std::make_shared<maps::MapChunker>(std::move(chunker).value());
    return new Writer([shared](v1::MapChunk& chunk) { return shared->next(chunk); }, std::move(slot).value(),
                      withDeadline(context));
  }

  grpc::ServerWriteReactor<v1::ExportChunk>* ExportMap(grpc::CallbackServerContext* context,
                                                       const v1::ExportMapRequest* request) override {
    using Writer = StreamWriter<v1::ExportChunk>;
    if (Status s = admitCall(core_, *context, request->mission(), "ExportMap"); !s.ok()) return new Writer(toGrpc(s));
    auto owner = readRoute(*context, request->mission());
    if (!owner) return new Writer(toGrpc(owner.error()));
    if (!owner->empty()) {
      return relayFromOwner<v1::ExportChunk>(*context, *owner, request, &v1::MapService::Stub::async::ExportMap);
    }
    auto slot = core_.openMapReadSlot(peerAddress(*context));
    if (!slot) return new Writer(toGrpc(slot.error()));
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
    return new Writer([files](v1::ExportChunk& chunk) { return files->next(chunk); }, std::move(slot).value(),
                      withDeadline(context));
  }

  grpc::ServerWriteReactor<v1::WatchMissionResponse>* WatchMission(grpc::CallbackServerContext* context,
                                                                   const v1::WatchMissionRequest* request) override {
    using Refusal = StreamWriter<v1::WatchMissionResponse>;
    if (request->mission().empty()) {
      return new Refusal(toGrpc(Error{ErrorCode::kInvalidArgument, "the request names no mission"}));
    }
    if (Status s = admitCall(core_, *context, request->mission(), "WatchMission"); !s.ok()) {
      return new Refusal(toGrpc(s));
    }
    auto owner = readRoute(*context, request->mission());
    if (!owner) return new Refusal(toGrpc(owner.error()));
    if (!owner->empty()) {
      return relayFromOwner<v1::WatchMissionResponse>(*context, *owner, request,
                                                      &v1::MapService::Stub::async::WatchMission);
    }
    std::shared_ptr<Mission> mission = core_.missions().find(request->mission());
    if (!mission) {
      return new Refusal(toGrpc(Error{ErrorCode::kNotFound, "no mission '" + request->mission() +
                                                                "' on this server (yet: watch it once an agent "
                                                                "has connected to it)"}));
    }
    const std::uint64_t from = request->from_event() == 0 ? mission->events().nextNumber() : request->from_event();
    return new WatchReactor(std::move(mission), from, watches_);
  }

 private:
  // A canceller for the call, registered to fire at limits.map_read_timeout_s.
  std::shared_ptr<CallCanceller> withDeadline(grpc::CallbackServerContext* context) {
    auto canceller = std::make_shared<CallCanceller>(context);
    const auto timeout = std::chrono::duration<double>(core_.options().map_read_timeout_s);
    deadlines_.add(
        std::chrono::steady_clock::now() + std::chrono::duration_cast<std::chrono::steady_clock::duration>(timeout),
        canceller);
    return canceller;
  }

  // Relays the owner's answer to a streaming read: `method` is the stub's callback method for it.
  template <typename Message, typename Request, typename Method>
  grpc::ServerWriteReactor<Message>* relayFromOwner(grpc::CallbackServerContext& context, const std::string& owner,
                                                    const Request* request, Method method) {
    v1::MapService::Stub& stub = peers_->get(owner);
    return new StreamRelay<Message>(forwardingContext(context, /*unary=*/false), owner,
                                    [&](grpc::ClientContext* call, grpc::ClientReadReactor<Message>* r) {
                                      (stub.async()->*method)(call, request, r);
                                    });
  }

  // Where a read of `mission` is answered: "" here (one server, this replica serves it, or no replica ever did and
  // the local answer says so), else the address of the replica that serves it.
  Result<std::string> readRoute(const grpc::CallbackServerContext& context, const std::string& mission) {
    MissionOwnership* ownership = core_.ownership();
    if (ownership == nullptr || peers_ == nullptr || mission.empty()) return std::string();
    auto owner = ownership->owner(mission);
    if (!owner) {
      if (owner.error().code() == ErrorCode::kNotFound) return std::string();
      return owner.error();
    }
    if (owner->here) return std::string();
    if (wasForwarded(context)) {  // the owner named by the leases has just lost the mission: no second hop
      return Error{ErrorCode::kUnavailable,
                   "mission '" + mission + "' is moving between replicas (now " + owner->address + "): ask again"};
    }
    return owner->address;
  }

  static grpc::ServerUnaryReactor* finish(grpc::CallbackServerContext* context, const Status& status) {
    auto* reactor = context->DefaultReactor();
    reactor->Finish(toGrpc(status));
    return reactor;
  }

  ServerCore& core_;
  WatchRegistry watches_;
  ReadDeadlines deadlines_;
  std::unique_ptr<PeerStubs<v1::MapService>> peers_;  // scale-out: set before the server starts
};

}  // namespace

struct MapService::Impl {
  explicit Impl(ServerCore& core) : service(core) {}
  MapServiceImpl service;
};

MapService::MapService(ServerCore& core) : impl_(std::make_unique<Impl>(core)) {}
MapService::~MapService() = default;

grpc::Service* MapService::service() {
  return &impl_->service;
}

void MapService::forwardWith(std::shared_ptr<grpc::ChannelCredentials> peer_credentials) {
  impl_->service.forwardWith(std::move(peer_credentials));
}

void MapService::tick() {
  impl_->service.watches().forEach([](WatchReactor& r) { r.tick(); });
  impl_->service.deadlines().tick(std::chrono::steady_clock::now());
}

void MapService::stopWatches() {
  impl_->service.watches().stop();
  impl_->service.watches().forEach([](WatchReactor& r) { r.stop(); });
}

}  // namespace cvislam::server

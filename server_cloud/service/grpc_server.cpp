#include "server_cloud/service/grpc_server.hpp"

#include <atomic>
#include <condition_variable>
#include <cstdio>
#include <deque>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <thread>
#include <vector>

#include <grpcpp/grpcpp.h>
#include <grpcpp/health_check_service_interface.h>
#include <grpcpp/support/byte_buffer.h>
#include <grpcpp/support/proto_buffer_reader.h>

#include "common/core/text.hpp"
#include "cvislam/v1/agent_link.grpc.pb.h"
#include "cvislam/v1/monitor.grpc.pb.h"
#include "proto/wire/wire.hpp"
#include "server_cloud/service/call_access.hpp"
#include "server_cloud/service/call_canceller.hpp"
#include "server_cloud/service/grpc_status.hpp"
#include "server_cloud/service/map_service.hpp"
#include "server_cloud/service/read_forwarding.hpp"
#include "server_cloud/service/write_gate.hpp"

namespace cvislam::server {

namespace {

class LinkReactor;

// The open link streams, for the periodic downlink. It holds them weakly and hands out strong references, so that
// the periodic thread ticks streams without holding its lock: a stream opening or closing never waits for a tick.
class ReactorRegistry {
 public:
  void add(const std::shared_ptr<LinkReactor>& r) {
    std::lock_guard lock(mutex_);
    reactors_[r.get()] = r;
  }
  void remove(LinkReactor* r) {
    std::lock_guard lock(mutex_);
    reactors_.erase(r);
  }
  // The streams open now, each kept alive by the copy.
  std::vector<std::shared_ptr<LinkReactor>> snapshot() {
    std::vector<std::shared_ptr<LinkReactor>> out;
    std::lock_guard lock(mutex_);
    out.reserve(reactors_.size());
    for (const auto& [raw, weak] : reactors_) {
      if (auto r = weak.lock()) out.push_back(std::move(r));
    }
    return out;
  }

 private:
  std::mutex mutex_;
  std::map<LinkReactor*, std::weak_ptr<LinkReactor>> reactors_;
};

// One agent's stream: reads the agent's messages into its AgentSession and writes what the session returns,
// one write at a time. Every callback and the periodic tick lock `mutex_`, so the session sees one caller; the
// tick only tries the lock, so a stream busy with a slow message (a store commit, a mission load) delays its own
// downlink and nobody else's. It owns itself (self_) from creation to OnDone; the periodic thread's references
// may keep the object a little longer, and a tick after OnDone does nothing.
// It works on raw bytes and parses them itself: a typed reactor hears a message that does not parse exactly
// like the agent closing its side, and could not refuse it with INVALID_ARGUMENT.
class LinkReactor final : public grpc::ServerBidiReactor<grpc::ByteBuffer, grpc::ByteBuffer> {
 public:
  // Makes a stream's reactor, which deletes itself once the stream is done.
  static LinkReactor* open(grpc::CallbackServerContext* context, ServerCore& core, ReactorRegistry& registry) {
    std::shared_ptr<LinkReactor> reactor(new LinkReactor(context, core, registry));
    reactor->self_ = reactor;
    registry.add(reactor);
    reactor->start(core);
    return reactor.get();
  }

  void OnReadDone(bool ok) override {
    std::lock_guard lock(mutex_);
    if (!ok) {
      // The agent closed its side (or the stream broke): nothing more will come.
      finishLocked(grpc::Status::OK);
      return;
    }
    if (gate_.finishing()) return;  // ending already (cancelled, or a write failed): no more reads
    const std::size_t wire_bytes = in_.Length();
    if (!grpc::SerializationTraits<v1::AgentUplink>::Deserialize(&in_, &parsed_).ok()) {
      const Status malformed =
          Error{ErrorCode::kInvalidArgument,
                "a message of " + std::to_string(wire_bytes) + " bytes that does not parse as cvislam.v1.AgentUplink"};
      closing_status_ = malformed;
      session_->countRefused(malformed);
      finishLocked(toGrpc(malformed));
      return;
    }
    bool reply_due = false;
    const Status status = session_->handle(parsed_, wire_bytes, reply_, reply_due);
    if (!status.ok()) {
      if (!session_->redirect().empty()) context_->AddTrailingMetadata(wire::kOwnerMetadataKey, session_->redirect());
      closing_status_ = status;
      finishLocked(toGrpc(status));
      return;
    }
    if (reply_due) {
      if (reply_.has_welcome()) {
        // One line per stream: when agents came (back), and where they resume.
        std::fprintf(stderr, "[server] agent %u of mission '%s' connected; it resumes after batch %llu\n",
                     static_cast<unsigned>(session_->agent()), session_->mission().c_str(),
                     static_cast<unsigned long long>(reply_.welcome().stored_sequence()));
      }
      enqueueLocked(reply_);
    }
    StartRead(&in_);
  }

  void OnWriteDone(bool ok) override {
    std::lock_guard lock(mutex_);
    // A finish that waited for this write goes first, whether the write went through or not.
    if (auto status = gate_.writeDone()) {
      Finish(std::move(*status));
      return;
    }
    if (!ok) {
      finishLocked(grpc::Status(grpc::StatusCode::UNAVAILABLE, "the agent's stream broke"));
      return;
    }
    writeNextLocked();
  }

  void OnCancel() override {
    std::lock_guard lock(mutex_);
    finishLocked(grpc::Status(grpc::StatusCode::CANCELLED, "cancelled"));
  }

  void OnDone() override {
    registry_.remove(this);
    handle_->ended();
    {
      std::lock_guard lock(mutex_);
      done_ = true;
      session_->close(closing_status_);
      slot_.release();
    }
    const std::shared_ptr<LinkReactor> last = std::move(self_);  // may be the last reference: deletes this
  }

  // From the periodic thread: the session's acknowledgement and corrections, when due. Skipped while the stream's
  // own callback holds the lock; the next tick comes 20 ms later.
  void tick(AgentSession::Clock::time_point now) {
    std::unique_lock lock(mutex_, std::try_to_lock);
    if (!lock.owns_lock() || done_) return;
    if (Status overdue = session_->checkHelloDeadline(now); !overdue.ok()) {
      if (!gate_.finishing()) {
        closing_status_ = overdue;
        finishLocked(toGrpc(overdue));
      }
      return;
    }
    // One message in flight and none waiting: an agent that does not read gets no queue that grows (its
    // acknowledgements are cumulative and its corrections wait in its record).
    if (!gate_.writable() || !queue_.empty()) return;
    if (session_->nextDownlink(now, periodic_)) enqueueLocked(periodic_);
  }

 private:
  LinkReactor(grpc::CallbackServerContext* context, ServerCore& core, ReactorRegistry& registry)
      : context_(context), handle_(std::make_shared<CallCanceller>(context)), registry_(registry) {
    std::weak_ptr<CallCanceller> weak = handle_;
    session_ = core.openSession(
        [weak] {
          if (auto h = weak.lock()) h->cancel();
        },
        presentedToken(*context));
  }
  void start(ServerCore& core) {
    // The mission's token is checked at the Hello (it names the mission). Until then the stream is the address's:
    // its rate of streams opened, and its streams open at once.
    const std::string address = peerAddress(*context_);
    Status admitted = core.admitRequest(unauthenticatedKey(*context_), "opening an agent stream");
    if (admitted.ok()) {
      auto slot = core.openStreamSlot(address);
      if (slot) {
        slot_ = std::move(slot).value();
      } else {
        admitted = slot.error();
      }
    }
    if (!admitted.ok()) {
      std::lock_guard lock(mutex_);
      closing_status_ = admitted;
      finishLocked(toGrpc(admitted));
      return;
    }
    StartRead(&in_);
  }

  void enqueueLocked(const v1::ServerDownlink& message) {
    grpc::ByteBuffer bytes;
    bool own = false;
    if (!grpc::SerializationTraits<v1::ServerDownlink>::Serialize(message, &bytes, &own).ok()) return;
    queue_.push_back(std::move(bytes));
    writeNextLocked();
  }
  void writeNextLocked() {
    if (!gate_.writable() || queue_.empty()) return;
    out_ = std::move(queue_.front());
    queue_.pop_front();
    gate_.writeStarted();
    StartWrite(&out_);
  }
  void finishLocked(const grpc::Status& status) {
    if (auto now = gate_.finish(status)) Finish(std::move(*now));
  }

  grpc::CallbackServerContext* context_;  // valid until OnDone()
  std::shared_ptr<CallCanceller> handle_;
  ReactorRegistry& registry_;
  std::mutex mutex_;
  std::unique_ptr<AgentSession> session_;
  grpc::ByteBuffer in_;
  v1::AgentUplink parsed_;
  v1::ServerDownlink reply_;
  v1::ServerDownlink periodic_;
  grpc::ByteBuffer out_;
  std::deque<grpc::ByteBuffer> queue_;
  WriteGate gate_;
  Status closing_status_;
  StreamLimits::Slot slot_;            // counts this stream against its address's limit
  bool done_ = false;                  // OnDone ran: nothing may start on the stream any more
  std::shared_ptr<LinkReactor> self_;  // from open() to OnDone()
};

class AgentLinkService final : public v1::AgentLink::WithRawCallbackMethod_Connect<v1::AgentLink::Service> {
 public:
  explicit AgentLinkService(ServerCore& core) : core_(core) {}
  grpc::ServerBidiReactor<grpc::ByteBuffer, grpc::ByteBuffer>* Connect(grpc::CallbackServerContext* context) override {
    return LinkReactor::open(context, core_, registry_);  // deletes itself after OnDone()
  }
  ReactorRegistry& registry() { return registry_; }

 private:
  ServerCore& core_;
  ReactorRegistry registry_;
};

class MonitorService final : public v1::Monitor::CallbackService {
 public:
  explicit MonitorService(ServerCore& core) : core_(core) {}
  grpc::ServerUnaryReactor* GetStats(grpc::CallbackServerContext* context, const v1::GetStatsRequest* request,
                                     v1::ServerStats* response) override {
    auto* reactor = context->DefaultReactor();
    const std::string token = presentedToken(*context);
    if (Status s = admitCall(core_, *context, token, request->mission(), "GetStats"); !s.ok()) {
      reactor->Finish(toGrpc(s));
      return reactor;
    }
    const MissionTokens& tokens = core_.tokens();
    core_.fillStats(request->mission(), *response,
                    [&](const std::string& mission) { return tokens.admits(mission, token); });
    reactor->Finish(grpc::Status::OK);
    return reactor;
  }

 private:
  ServerCore& core_;
};

}  // namespace

struct GrpcServer::Impl {
  explicit Impl(ServerCore& c) : core(c), link(c), monitor(c), maps(c) {}

  ServerCore& core;
  AgentLinkService link;
  MonitorService monitor;
  MapService maps;
  std::unique_ptr<grpc::Server> server;
  std::unique_ptr<grpc::Server> health_server;  // plaintext, grpc.health.v1 only (ServerOptions::health_listen)
  // gRPC refuses to start a server with no synchronous method to poll for, and the default health service
  // alone does not count. A Monitor base with no method overridden gives it one, and answers UNIMPLEMENTED.
  v1::Monitor::Service health_port_placeholder;
  int port = 0;
  int health_port = 0;
  std::string address;
  std::thread periodic;
  std::mutex mutex;
  std::condition_variable wake;
  bool stopping = false;
  bool shut_down = false;

  // Both ports answer for the server and each of its services.
  void setServing(bool serving) {
    for (grpc::Server* s : {server.get(), health_server.get()}) {
      grpc::HealthCheckServiceInterface* health = s != nullptr ? s->GetHealthCheckService() : nullptr;
      if (health == nullptr) continue;
      health->SetServingStatus(serving);
      for (const char* service : {"cvislam.v1.AgentLink", "cvislam.v1.Monitor", "cvislam.v1.MapService"}) {
        health->SetServingStatus(service, serving);
      }
    }
  }

  void runPeriodic() {
    using Clock = AgentSession::Clock;
    const auto timeline_period = std::chrono::duration<double>(core.options().timeline_interval_s);
    auto next_sample = Clock::now();
    std::unique_lock lock(mutex);
    while (!stopping) {
      wake.wait_for(lock, std::chrono::milliseconds(20));
      if (stopping) break;
      lock.unlock();
      const auto now = Clock::now();
      for (const auto& reactor : link.registry().snapshot()) reactor->tick(now);
      maps.tick();
      if (now >= next_sample) {
        core.sampleTimeline();
        next_sample += std::chrono::duration_cast<Clock::duration>(timeline_period);
        if (next_sample < now) next_sample = now;
      }
      lock.lock();
    }
  }
};

GrpcServer::GrpcServer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

GrpcServer::~GrpcServer() {
  shutdown(std::chrono::milliseconds(500));
}

Result<std::unique_ptr<GrpcServer>> GrpcServer::start(ServerCore& core) {
  const ServerOptions& o = core.options();
  auto impl = std::make_unique<Impl>(core);
  grpc::EnableDefaultHealthCheckService(true);
  std::shared_ptr<grpc::ServerCredentials> credentials = grpc::InsecureServerCredentials();
  if (!o.tls_certificate.empty()) {
    auto certificate = text::readPemFile(o.tls_certificate, "TLS certificate (--tls-cert)");
    if (!certificate) return certificate.error();
    auto key = text::readPemFile(o.tls_private_key, "TLS private key (--tls-key)");
    if (!key) return key.error();
    grpc::SslServerCredentialsOptions tls;
    tls.pem_key_cert_pairs.push_back({std::move(key).value(), std::move(certificate).value()});
    credentials = grpc::SslServerCredentials(tls);
  }
  if (core.ownership() != nullptr) {
    auto peers = peerCredentials(o);
    if (!peers) return peers.error();
    impl->maps.forwardWith(std::move(peers).value());
  }
  grpc::ServerBuilder builder;
  builder.AddListeningPort(o.listen, credentials, &impl->port);
  builder.RegisterService(&impl->link);
  builder.RegisterService(&impl->monitor);
  builder.RegisterService(impl->maps.service());
  builder.SetMaxReceiveMessageSize(static_cast<int>(o.max_message_bytes));
  builder.SetMaxSendMessageSize(static_cast<int>(o.max_message_bytes));
  // Notice agents that vanished without closing (keepalive), allow the agents' own keepalive pings, and
  // refuse to share a port with another server (SO_REUSEPORT would let two servers listen on one port).
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_TIME_MS, o.keepalive_time_ms);
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_TIMEOUT_MS, o.keepalive_timeout_ms);
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_PERMIT_WITHOUT_CALLS, 1);
  builder.AddChannelArgument(GRPC_ARG_HTTP2_MIN_RECV_PING_INTERVAL_WITHOUT_DATA_MS, 100);
  // A client pinging faster than that three times over is sent away; the agents ping once a second.
  builder.AddChannelArgument(GRPC_ARG_HTTP2_MAX_PING_STRIKES, 2);
  // Bounds on what one connection and all of them may take: streams multiplexed on one connection (an agent
  // uses one, a map client a few), and the memory gRPC's buffers may hold in all.
  builder.AddChannelArgument(GRPC_ARG_MAX_CONCURRENT_STREAMS, 128);
  grpc::ResourceQuota quota("cvislam_server");
  quota.Resize(static_cast<std::size_t>(o.memory_quota_mb) << 20U);
  builder.SetResourceQuota(quota);
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  impl->server = builder.BuildAndStart();
  if (!impl->server || impl->port == 0) {
    return Error{ErrorCode::kUnavailable,
                 "cannot listen on " + o.listen + " (is the port taken, or the address not this machine's?" +
                     (o.tls_certificate.empty() ? "" : " Or do the TLS certificate and key not belong together?") +
                     ")"};
  }
  if (!o.health_listen.empty()) {
    grpc::ServerBuilder health_builder;  // the default health service, and nothing that answers
    health_builder.AddListeningPort(o.health_listen, grpc::InsecureServerCredentials(), &impl->health_port);
    health_builder.RegisterService(&impl->health_port_placeholder);
    health_builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
    impl->health_server = health_builder.BuildAndStart();
    if (!impl->health_server || impl->health_port == 0) {
      impl->server->Shutdown();
      return Error{ErrorCode::kUnavailable,
                   "cannot listen for health checks on " + o.health_listen +
                       " (health_listen: is the port taken, or the address not this machine's?)"};
    }
  }
  impl->setServing(true);
  const std::string host = o.listen.substr(0, o.listen.rfind(':'));
  impl->address = host + ":" + std::to_string(impl->port);
  Impl* raw = impl.get();
  impl->periodic = std::thread([raw] { raw->runPeriodic(); });
  return std::unique_ptr<GrpcServer>(new GrpcServer(std::move(impl)));
}

int GrpcServer::port() const {
  return impl_->port;
}
int GrpcServer::healthPort() const {
  return impl_->health_port;
}
std::string GrpcServer::address() const {
  return impl_->address;
}

void GrpcServer::shutdown(std::chrono::milliseconds grace) {
  {
    std::lock_guard lock(impl_->mutex);
    if (impl_->shut_down) return;
    impl_->shut_down = true;
    impl_->stopping = true;
  }
  impl_->wake.notify_all();
  if (impl_->periodic.joinable()) impl_->periodic.join();
  impl_->setServing(false);
  impl_->maps.stopWatches();  // they never end by themselves
  impl_->server->Shutdown(std::chrono::system_clock::now() + grace);
  impl_->server->Wait();
  if (impl_->health_server) {
    impl_->health_server->Shutdown(std::chrono::system_clock::now() + grace);
    impl_->health_server->Wait();
  }
}

}  // namespace cvislam::server

// Scale-out: a map-service read of a mission that another replica serves is passed on to that replica (its owner,
// from the leases) and the answer relayed back, so that a client may call any replica. The forwarded call carries
// the client's token and deadline, and a mark (kForwardedMetadataKey) that makes the owner answer from its own
// state instead of passing the call on again (no loops while a mission moves). Only service/ includes it (gRPC
// headers).
#pragma once

#include <atomic>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <utility>

#include <grpcpp/grpcpp.h>
#include <grpcpp/support/client_callback.h>
#include <grpcpp/support/server_callback.h>

#include "common/core/result.hpp"

namespace cvislam::server {

struct ServerOptions;

inline constexpr char kForwardedMetadataKey[] = "cvislam-forwarded";

// The credentials replicas call each other with: plaintext, or TLS trusting cluster.peer_ca (else the replica's own
// certificate).
Result<std::shared_ptr<grpc::ChannelCredentials>> peerCredentials(const ServerOptions& options);

// One stub per replica address, made on first use and kept (gRPC reconnects its channel by itself).
template <typename Service>
class PeerStubs {
 public:
  explicit PeerStubs(std::shared_ptr<grpc::ChannelCredentials> credentials) : credentials_(std::move(credentials)) {}
  typename Service::Stub& get(const std::string& address) {
    std::lock_guard lock(mutex_);
    auto& stub = stubs_[address];
    if (!stub) stub = Service::NewStub(grpc::CreateChannel(address, credentials_));
    return *stub;
  }

 private:
  std::shared_ptr<grpc::ChannelCredentials> credentials_;
  std::mutex mutex_;
  std::map<std::string, std::unique_ptr<typename Service::Stub>> stubs_;
};

// True when `context` is a call that another replica passed on.
bool wasForwarded(const grpc::CallbackServerContext& context);
// A client context that passes `incoming` on: its token, its deadline (a unary call's at most 30 s from now; a
// stream, such as a watch, may have none), the mark.
std::unique_ptr<grpc::ClientContext> forwardingContext(const grpc::CallbackServerContext& incoming, bool unary);
// The owner's answer as the client sees it: an error names the replica it came through.
grpc::Status relayedStatus(const grpc::Status& status, const std::string& owner_address);

// Relays a server stream from the owner to the client, one message at a time (a read from the owner only after
// the previous write to the client completed, so a slow client slows the owner's stream rather than filling memory
// here). The client going away cancels the owner's call; the owner's status ends the client's. Deletes itself
// once both sides are done.
//
// The next read from the owner starts in the client side's OnWriteDone, outside the owner's reactions, so the
// owner's call is held (AddHold) from the start: without the hold gRPC may end that call, and free it, as soon as
// its status arrives with no read outstanding, while the relay's write is still in flight. The hold goes when no
// read will follow: the owner's stream ended (a read came back empty), or the client left. Its OnDone, and so
// Finish, therefore never comes while a write is in flight.
template <typename Message>
class StreamRelay final : public grpc::ServerWriteReactor<Message> {
 public:
  // `start(ClientContext*, ClientReadReactor<Message>*)` begins the owner's call (the stub's async() method).
  template <typename Start>
  StreamRelay(std::unique_ptr<grpc::ClientContext> context, std::string owner_address, Start&& start)
      : context_(std::move(context)), owner_address_(std::move(owner_address)), upstream_(*this) {
    start(context_.get(), &upstream_);
    upstream_.AddHold();
    upstream_.StartRead(&message_);
    upstream_.StartCall();
  }

  void OnWriteDone(bool ok) override {
    if (!ok) {
      context_->TryCancel();  // the client left: the owner's call ends, and its OnDone finishes this one
      releaseUpstream();
      return;
    }
    upstream_.StartRead(&message_);  // under the hold, which is still there: reads stop only after this one
  }
  void OnCancel() override { context_->TryCancel(); }
  void OnDone() override { sideDone(); }

 private:
  class Upstream final : public grpc::ClientReadReactor<Message> {
   public:
    explicit Upstream(StreamRelay& relay) : relay_(relay) {}
    void OnReadDone(bool ok) override {
      if (ok) {
        relay_.StartWrite(&relay_.message_);
      } else {
        relay_.releaseUpstream();  // the owner's stream ended (or was cancelled): OnDone brings its status
      }
    }
    void OnDone(const grpc::Status& status) override {
      relay_.Finish(relayedStatus(status, relay_.owner_address_));
      relay_.sideDone();
    }

   private:
    StreamRelay& relay_;
  };

  // Once: no read of the owner's stream follows.
  void releaseUpstream() {
    if (!hold_released_.exchange(true)) upstream_.RemoveHold();
  }
  void sideDone() {
    if (done_.fetch_add(1) == 1) delete this;  // the second of the two sides to finish
  }

  std::unique_ptr<grpc::ClientContext> context_;
  std::string owner_address_;
  Upstream upstream_;
  Message message_;
  std::atomic<bool> hold_released_{false};
  std::atomic<int> done_{0};
};

// Passes a unary call on: `call(ClientContext*, std::function<void(grpc::Status)>)` starts the owner's call (the
// stub's async() method, with the incoming request and the response that the client gets).
template <typename Call>
grpc::ServerUnaryReactor* forwardUnary(grpc::CallbackServerContext* incoming, const std::string& owner_address,
                                       Call&& call) {
  grpc::ServerUnaryReactor* reactor = incoming->DefaultReactor();
  std::shared_ptr<grpc::ClientContext> context = forwardingContext(*incoming, /*unary=*/true);
  grpc::ClientContext* raw = context.get();
  call(raw, [reactor, context, owner_address](const grpc::Status& status) {
    reactor->Finish(relayedStatus(status, owner_address));
  });
  return reactor;
}

}  // namespace cvislam::server

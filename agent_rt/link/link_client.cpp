#include "agent_rt/link/link_client.hpp"

#include <condition_variable>
#include <deque>
#include <map>
#include <mutex>
#include <thread>

#include <grpcpp/grpcpp.h>

#include "cvislam/v1/agent_link.grpc.pb.h"
#include "proto/wire/wire.hpp"

namespace cvislam::agent {

namespace {
std::string describe(const grpc::Status& s) {
  static const char* const kNames[] = {
      "OK",        "CANCELLED",      "UNKNOWN",           "INVALID_ARGUMENT",   "DEADLINE_EXCEEDED",
      "NOT_FOUND", "ALREADY_EXISTS", "PERMISSION_DENIED", "RESOURCE_EXHAUSTED", "FAILED_PRECONDITION",
      "ABORTED",   "OUT_OF_RANGE",   "UNIMPLEMENTED",     "INTERNAL",           "UNAVAILABLE",
      "DATA_LOSS", "UNAUTHENTICATED"};
  const int code = static_cast<int>(s.error_code());
  const std::string name = code >= 0 && code < 17 ? kNames[code] : std::to_string(code);
  return s.error_message().empty() ? name : name + ": " + s.error_message();
}
}  // namespace

struct LinkClient::Impl {
  LinkClientOptions options;
  grpc::ChannelArguments args;
  std::shared_ptr<grpc::ChannelCredentials> credentials;
  struct Target {
    std::shared_ptr<grpc::Channel> channel;
    std::unique_ptr<v1::AgentLink::Stub> stub;
  };
  std::map<std::string, Target> targets;  // by host:port, made when first used
  std::vector<std::string> addresses;     // options.server, split
  std::size_t next_address = 0;
  std::string redirect;  // where the last refusal sent us; tried first
  std::string target;    // the replica of the open (or last) stream
  std::string owner;     // the owner the last stream's trailing metadata named; "" when none
  std::uint64_t redirects = 0;

  Target& targetFor(const std::string& address) {
    auto it = targets.find(address);
    if (it == targets.end()) {
      Target t;
      t.channel = grpc::CreateCustomChannel(address, credentials, args);
      t.stub = v1::AgentLink::NewStub(t.channel);
      it = targets.emplace(address, std::move(t)).first;
    }
    return it->second;
  }

  // The open stream, if any.
  std::unique_ptr<grpc::ClientContext> context;
  std::unique_ptr<grpc::ClientReaderWriter<v1::AgentUplink, v1::ServerDownlink>> stream;
  std::thread reader;

  std::mutex context_mutex;  // guards `context` against cancel() from another thread
  mutable std::mutex mutex;  // guards what the reader thread shares
  std::condition_variable arrived;
  std::deque<v1::ServerDownlink> inbox;
  bool reading = false;  // the reader thread runs
  bool broken = false;   // the stream ended or a write failed
  std::string last_error;

  void startReader() {
    {
      std::lock_guard lock(mutex);
      reading = true;
      broken = false;
      inbox.clear();
    }
    reader = std::thread([this] {
      v1::ServerDownlink message;
      while (stream->Read(&message)) {
        std::lock_guard lock(mutex);
        // The server sends at most a few per second; acknowledgements are cumulative, so the oldest can go.
        if (inbox.size() >= 256) inbox.pop_front();
        inbox.push_back(message);
        arrived.notify_all();
      }
      std::lock_guard lock(mutex);
      reading = false;
      broken = true;
      arrived.notify_all();
    });
  }

  // Ends the stream (cancelling it when it is still open) and collects its status.
  grpc::Status teardown() {
    if (!stream) return grpc::Status::OK;
    bool still_reading = false;
    {
      std::lock_guard lock(mutex);
      still_reading = reading;
    }
    // A stream the server ended already keeps its status (and trailing metadata): cancel only an open one.
    if (still_reading) context->TryCancel();
    if (reader.joinable()) reader.join();
    grpc::Status status = stream->Finish();
    stream.reset();
    {
      std::lock_guard lock(context_mutex);
      owner.clear();
      const auto& trailing = context->GetServerTrailingMetadata();
      if (auto it = trailing.find(wire::kOwnerMetadataKey); it != trailing.end()) {
        owner.assign(it->second.data(), it->second.size());
      }
      context.reset();
    }
    std::lock_guard lock(mutex);
    broken = true;
    return status;
  }
};

LinkClient::LinkClient(const LinkClientOptions& options) : impl_(std::make_unique<Impl>()) {
  Impl& s = *impl_;
  s.options = options;
  // Notice a dead or hung server within a few seconds, and come back quickly after it restarts.
  s.args.SetInt(GRPC_ARG_KEEPALIVE_TIME_MS, options.keepalive_ms);
  s.args.SetInt(GRPC_ARG_KEEPALIVE_TIMEOUT_MS, options.keepalive_timeout_ms);
  s.args.SetInt(GRPC_ARG_KEEPALIVE_PERMIT_WITHOUT_CALLS, 1);
  s.args.SetInt(GRPC_ARG_HTTP2_MAX_PINGS_WITHOUT_DATA, 0);
  s.args.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, 100);
  s.args.SetInt(GRPC_ARG_MIN_RECONNECT_BACKOFF_MS, 100);
  s.args.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, 1000);
  s.args.SetMaxSendMessageSize(static_cast<int>(options.max_message_bytes));
  s.args.SetMaxReceiveMessageSize(static_cast<int>(options.max_message_bytes));
  s.credentials = grpc::InsecureChannelCredentials();
  if (!options.tls_root_pem.empty()) {
    grpc::SslCredentialsOptions tls;
    tls.pem_root_certs = options.tls_root_pem;
    s.credentials = grpc::SslCredentials(tls);
  }
  s.addresses = splitServerList(options.server);
  if (s.addresses.empty()) s.addresses.push_back(options.server);
  s.target = s.addresses.front();
  s.targetFor(s.target);  // the first replica's channel now: it starts connecting in the background
}

LinkClient::~LinkClient() {
  impl_->teardown();
}

Result<std::unique_ptr<v1::ServerDownlink>> LinkClient::connect(const v1::AgentUplink& hello) {
  Impl& s = *impl_;
  // A refusal that names the owner is followed at once (twice at most: ownership may move once meanwhile).
  for (int hop = 0;; ++hop) {
    s.target = !s.redirect.empty() ? s.redirect : s.addresses[s.next_address % s.addresses.size()];
    auto welcome = connectTo(s.target, hello);
    if (welcome) return welcome;
    const bool redirected = !s.owner.empty() && s.owner != s.target;
    if (redirected && hop < 2) {
      s.redirect = s.owner;
      ++s.redirects;
      continue;
    }
    // Next time: the next replica of the list (a redirect that led nowhere is forgotten).
    if (redirected) {
      s.redirect = s.owner;
    } else if (!s.redirect.empty()) {
      s.redirect.clear();
    } else {
      ++s.next_address;
    }
    return welcome;
  }
}

Result<std::unique_ptr<v1::ServerDownlink>> LinkClient::connectTo(const std::string& address,
                                                                  const v1::AgentUplink& hello) {
  Impl& s = *impl_;
  s.teardown();
  s.owner.clear();
  Impl::Target& target = s.targetFor(address);
  const auto deadline = std::chrono::system_clock::now() + s.options.connect_timeout;
  if (!target.channel->WaitForConnected(deadline)) {
    std::lock_guard lock(s.mutex);
    s.last_error = "server " + address + " unreachable";
    return Error{ErrorCode::kUnavailable, s.last_error};
  }
  {
    std::lock_guard lock(s.context_mutex);
    s.context = std::make_unique<grpc::ClientContext>();
    if (!s.options.token.empty()) s.context->AddMetadata("authorization", "Bearer " + s.options.token);
  }
  s.stream = target.stub->Connect(s.context.get());
  s.startReader();
  if (!s.stream->Write(hello)) {
    const grpc::Status status = s.teardown();
    std::lock_guard lock(s.mutex);
    s.last_error = "the stream broke at the Hello (" + describe(status) + ")";
    return Error{ErrorCode::kUnavailable, s.last_error};
  }
  std::unique_lock lock(s.mutex);
  s.arrived.wait_until(lock, std::chrono::steady_clock::now() + s.options.connect_timeout,
                       [&] { return !s.inbox.empty() || s.broken; });
  if (!s.inbox.empty() && s.inbox.front().has_welcome()) {
    auto welcome = std::make_unique<v1::ServerDownlink>(std::move(s.inbox.front()));
    s.inbox.pop_front();
    s.last_error.clear();
    return welcome;
  }
  lock.unlock();
  const grpc::Status status = s.teardown();
  lock.lock();
  s.last_error = status.ok() ? "the server sent no Welcome" : "the server refused the Hello: " + describe(status);
  ErrorCode code = ErrorCode::kFailedPrecondition;
  if (status.error_code() == grpc::StatusCode::UNAVAILABLE) code = ErrorCode::kUnavailable;
  if (status.error_code() == grpc::StatusCode::UNAUTHENTICATED) code = ErrorCode::kUnauthenticated;
  return Error{code, s.last_error};
}

bool LinkClient::connected() const {
  std::lock_guard lock(impl_->mutex);
  return impl_->stream != nullptr && !impl_->broken;
}

bool LinkClient::send(const v1::AgentUplink& message) {
  Impl& s = *impl_;
  if (!connected()) return false;
  if (s.stream->Write(message)) return true;
  const grpc::Status status = s.teardown();
  std::lock_guard lock(s.mutex);
  s.last_error = "stream broke: " + describe(status);
  return false;
}

bool LinkClient::poll(v1::ServerDownlink& out) {
  Impl& s = *impl_;
  std::unique_lock lock(s.mutex);
  if (!s.inbox.empty()) {
    out = std::move(s.inbox.front());
    s.inbox.pop_front();
    return true;
  }
  if (s.broken && s.stream) {
    // The server ended the stream: collect its reason.
    lock.unlock();
    const grpc::Status status = s.teardown();
    lock.lock();
    s.last_error = "the server ended the stream: " + describe(status);
  }
  return false;
}

Status LinkClient::close(std::chrono::milliseconds timeout) {
  Impl& s = *impl_;
  if (!s.stream) return Status::Ok();
  s.stream->WritesDone();
  {
    std::unique_lock lock(s.mutex);
    s.arrived.wait_for(lock, timeout, [&] { return !s.reading; });
  }
  const grpc::Status status = s.teardown();
  if (status.ok() || status.error_code() == grpc::StatusCode::CANCELLED) return Status::Ok();
  return Error{ErrorCode::kUnavailable, describe(status)};
}

void LinkClient::abandon() {
  impl_->teardown();
}

void LinkClient::cancel() {
  std::lock_guard lock(impl_->context_mutex);
  if (impl_->context) impl_->context->TryCancel();
}

std::string LinkClient::target() const {
  return impl_->target;
}

std::uint64_t LinkClient::redirects() const {
  return impl_->redirects;
}

std::vector<std::string> splitServerList(const std::string& servers) {
  std::vector<std::string> out;
  std::size_t start = 0;
  while (start <= servers.size()) {
    const std::size_t comma = std::min(servers.find(',', start), servers.size());
    if (comma > start) out.push_back(servers.substr(start, comma - start));
    start = comma + 1;
  }
  return out;
}

std::string LinkClient::lastError() const {
  std::lock_guard lock(impl_->mutex);
  return impl_->last_error;
}

}  // namespace cvislam::agent

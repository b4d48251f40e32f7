// The only file that includes websocketpp (on standalone asio).
#include "server_cloud/viewer/viewer_endpoint.hpp"

#include <pthread.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <map>
#include <mutex>
#include <sstream>
#include <string_view>
#include <thread>

#include <websocketpp/config/asio.hpp>
#include <websocketpp/config/asio_no_tls.hpp>
#include <websocketpp/server.hpp>

#include "server_cloud/access/mission_tokens.hpp"
#include "server_cloud/viewer/viewer_hub.hpp"

namespace cvislam::server::viewer {
namespace {

namespace asio = websocketpp::lib::asio;
using websocketpp::connection_hdl;

std::string contentType(const std::filesystem::path& file) {
  const std::string ext = file.extension().string();
  if (ext == ".html") return "text/html; charset=utf-8";
  if (ext == ".js" || ext == ".mjs") return "text/javascript; charset=utf-8";
  if (ext == ".css") return "text/css; charset=utf-8";
  if (ext == ".json") return "application/json";
  if (ext == ".png") return "image/png";
  if (ext == ".svg") return "image/svg+xml";
  return "application/octet-stream";
}

// The file a GET path names, or empty when it names none (or tries to leave the served folders).
std::filesystem::path resolve(const EndpointOptions& options, std::string path) {
  if (const std::size_t q = path.find('?'); q != std::string::npos) path.resize(q);
  if (path.empty() || path == "/") path = "/index.html";
  if (path.find("..") != std::string::npos || path.find('\\') != std::string::npos) return {};
  constexpr std::string_view kThree = "/three/";
  if (path.rfind(kThree, 0) == 0) return options.three_dir / path.substr(kThree.size());
  return options.static_dir / path.substr(1);
}

// Listening address "host:port" as asio's endpoint.
Result<asio::ip::tcp::endpoint> parseListen(const std::string& listen) {
  const std::size_t colon = listen.rfind(':');
  if (colon == std::string::npos) {
    return Error{ErrorCode::kInvalidArgument, "viewer: listen address '" + listen + "' is not host:port"};
  }
  std::string host = listen.substr(0, colon);
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') host = host.substr(1, host.size() - 2);
  int port = -1;
  try {
    std::size_t used = 0;
    port = std::stoi(listen.substr(colon + 1), &used);
    if (used != listen.size() - colon - 1) port = -1;
  } catch (const std::exception&) {
    port = -1;
  }
  if (port < 0 || port > 65535) {
    return Error{ErrorCode::kInvalidArgument, "viewer: listen address '" + listen + "' has no port 0-65535"};
  }
  asio::error_code ec;
  const auto address = asio::ip::make_address(host.empty() || host == "*" ? "0.0.0.0" : host, ec);
  if (ec) {
    return Error{ErrorCode::kInvalidArgument,
                 "viewer: listen address '" + listen + "': '" + host + "' is not an IP address (" + ec.message() + ")"};
  }
  return asio::ip::tcp::endpoint(address, static_cast<unsigned short>(port));
}

class Server {
 public:
  virtual ~Server() = default;
  virtual int port() const = 0;
  virtual bool tls() const = 0;
};

template <typename Config>
class ServerOf final : public Server {
 public:
  using Endpoint = websocketpp::server<Config>;

  ServerOf(ViewerHub& hub, const MissionTokens& tokens, EndpointOptions options)
      : hub_(hub), tokens_(tokens), options_(std::move(options)) {}

  ~ServerOf() override {
    if (thread_.joinable()) {
      asio::post(endpoint_.get_io_service(), [this] { shutDown(); });
      thread_.join();
    }
    hub_.setWake({});
  }

  Status start(const asio::ip::tcp::endpoint& at) {
    try {
      endpoint_.clear_access_channels(websocketpp::log::alevel::all);
      endpoint_.clear_error_channels(websocketpp::log::elevel::all);
      endpoint_.set_error_channels(websocketpp::log::elevel::fatal);
      endpoint_.init_asio();
      endpoint_.set_reuse_addr(true);
      endpoint_.set_max_message_size(options_.max_client_message_bytes);
      endpoint_.set_max_http_body_size(options_.max_client_message_bytes);
      configureTls();
      endpoint_.set_validate_handler([this](connection_hdl h) { return validate(h); });
      endpoint_.set_http_handler([this](connection_hdl h) { serveFile(h); });
      endpoint_.set_open_handler([this](connection_hdl h) { opened(h); });
      endpoint_.set_close_handler([this](connection_hdl h) { closed(h); });
      endpoint_.set_fail_handler([this](connection_hdl h) { closed(h); });
      endpoint_.set_message_handler([this](connection_hdl h, typename Endpoint::message_ptr m) { received(h, m); });
      asio::error_code ec;
      endpoint_.listen(at, ec);
      if (ec) {
        return Error{ErrorCode::kUnavailable, "viewer: cannot listen on " + options_.listen + ": " + ec.message()};
      }
      endpoint_.start_accept();
      port_ = endpoint_.get_local_endpoint(ec).port();
    } catch (const std::exception& e) {
      return Error{ErrorCode::kUnavailable, "viewer: cannot serve on " + options_.listen + ": " + e.what()};
    }
    hub_.setWake([this] {
      // Coalesced: one flush on the endpoint's thread however many wakes came before it ran.
      if (!flush_posted_.exchange(true)) asio::post(endpoint_.get_io_service(), [this] { flushAll(); });
    });
    timer_ = std::make_unique<asio::steady_timer>(endpoint_.get_io_service());
    armTimer();
    thread_ = std::thread([this] {
      pthread_setname_np(pthread_self(), "viewer_ws");
      try {
        endpoint_.run();
      } catch (const std::exception& e) {
        std::fprintf(stderr, "[viewer] the endpoint stopped: %s\n", e.what());
      }
    });
    return Status::Ok();
  }

  int port() const override { return port_; }
  bool tls() const override { return !options_.tls_cert.empty(); }

 private:
  void configureTls();

  // The upgrade: the mission's token decides; the protocol must be Foxglove's.
  bool validate(connection_hdl h) {
    auto con = endpoint_.get_con_from_hdl(h);
    auto access = admitViewer(tokens_, con->get_request_header("Authorization"), con->get_uri()->get_query());
    if (!access) {
      con->set_status(websocketpp::http::status_code::unauthorized);
      con->set_body(access.error().message() + "\n");
      return false;
    }
    for (const std::string& p : con->get_requested_subprotocols()) {
      if (p == kSubprotocol) {
        con->select_subprotocol(p);
        const std::lock_guard lock(mutex_);
        admitted_[con.get()] = std::move(*access);
        return true;
      }
    }
    con->set_status(websocketpp::http::status_code::bad_request);
    con->set_body(std::string("ask for the WebSocket subprotocol ") + kSubprotocol + "\n");
    return false;
  }

  void serveFile(connection_hdl h) {
    auto con = endpoint_.get_con_from_hdl(h);
    const std::filesystem::path file = resolve(options_, con->get_resource());
    std::ifstream in(file, std::ios::binary);
    if (file.empty() || !std::filesystem::is_regular_file(file) || !in) {
      con->set_status(websocketpp::http::status_code::not_found);
      std::string body = "not found: " + con->get_resource() + "\n";
      if (con->get_resource().rfind("/three/", 0) == 0) {
        body += "three.js is not where the server looks (" + options_.three_dir.string() +
                "): run deploy/install_deploy_tools.sh, or give --viewer-three\n";
      }
      con->set_body(body);
      return;
    }
    std::ostringstream body;
    body << in.rdbuf();
    con->set_body(body.str());
    con->append_header("Content-Type", contentType(file));
    con->append_header("Cache-Control", "no-cache");
    con->set_status(websocketpp::http::status_code::ok);
  }

  void opened(connection_hdl h) {
    auto con = endpoint_.get_con_from_hdl(h);
    ClientAccess access;
    {
      const std::lock_guard lock(mutex_);
      auto it = admitted_.find(con.get());
      if (it == admitted_.end()) return;
      access = std::move(it->second);
      admitted_.erase(it);
    }
    // The kernel's send buffer, fixed (Linux would grow it to megabytes): with the socket buffer above it, what a
    // client that stops reading can hold on the server. The TCP socket, under TLS too; only open sockets take it.
    asio::error_code ignored;  // the default buffer is bounded as well
    con->get_raw_socket().set_option(
        asio::socket_base::send_buffer_size(static_cast<int>(options_.kernel_send_buffer_bytes)), ignored);
    const ViewerHub::ClientId id = hub_.open(std::move(access));
    const std::lock_guard lock(mutex_);
    clients_[id] = h;
    ids_[con.get()] = id;
  }

  void closed(connection_hdl h) {
    auto con = endpoint_.get_con_from_hdl(h);
    std::optional<ViewerHub::ClientId> id;
    {
      const std::lock_guard lock(mutex_);
      admitted_.erase(con.get());
      auto it = ids_.find(con.get());
      if (it != ids_.end()) {
        id = it->second;
        clients_.erase(it->second);
        ids_.erase(it);
      }
    }
    if (id) hub_.close(*id);
  }

  void received(connection_hdl h, const typename Endpoint::message_ptr& message) {
    if (message->get_opcode() != websocketpp::frame::opcode::text) return;  // client publishing is not offered
    auto con = endpoint_.get_con_from_hdl(h);
    std::optional<ViewerHub::ClientId> id;
    {
      const std::lock_guard lock(mutex_);
      auto it = ids_.find(con.get());
      if (it != ids_.end()) id = it->second;
    }
    if (id) (void)hub_.onText(*id, message->get_payload());
  }

  // Hands each client's queued frames to its socket while the socket's buffer has room.
  void flushAll() {
    flush_posted_.store(false);
    std::map<ViewerHub::ClientId, connection_hdl> clients;
    {
      const std::lock_guard lock(mutex_);
      clients = clients_;
    }
    ViewerHub::Frame frame;
    for (const auto& [id, h] : clients) {
      asio::error_code ec;
      auto con = endpoint_.get_con_from_hdl(h, ec);
      if (ec || !con) continue;
      while (con->get_buffered_amount() < options_.socket_buffer_bytes && hub_.pop(id, frame)) {
        con->send(frame.bytes, frame.binary ? websocketpp::frame::opcode::binary : websocketpp::frame::opcode::text);
      }
    }
  }

  // Sockets drain without telling: look again every 50 ms for clients that had a full buffer.
  void armTimer() {
    timer_->expires_after(std::chrono::milliseconds(50));
    timer_->async_wait([this](const asio::error_code& ec) {
      if (ec || stopping_) return;
      flushAll();
      armTimer();
    });
  }

  void shutDown() {
    stopping_ = true;
    if (timer_) timer_->cancel();
    asio::error_code ec;
    endpoint_.stop_listening(ec);
    std::map<ViewerHub::ClientId, connection_hdl> clients;
    {
      const std::lock_guard lock(mutex_);
      clients = clients_;
    }
    for (const auto& [id, h] : clients) {
      endpoint_.close(h, websocketpp::close::status::going_away, "server stopping", ec);
    }
    endpoint_.stop();
  }

  ViewerHub& hub_;
  const MissionTokens& tokens_;
  EndpointOptions options_;
  Endpoint endpoint_;
  std::unique_ptr<asio::steady_timer> timer_;
  std::thread thread_;
  int port_ = 0;
  std::atomic<bool> flush_posted_{false};
  bool stopping_ = false;  // the endpoint's thread only
  std::mutex mutex_;       // the handlers run on the endpoint's thread; the maps are also read by the wake
  std::map<const void*, ClientAccess> admitted_;
  std::map<ViewerHub::ClientId, connection_hdl> clients_;
  std::map<const void*, ViewerHub::ClientId> ids_;
};

template <>
void ServerOf<websocketpp::config::asio>::configureTls() {}

template <>
void ServerOf<websocketpp::config::asio_tls>::configureTls() {
  endpoint_.set_tls_init_handler([this](const connection_hdl& /*connection*/) {
    auto context = std::make_shared<asio::ssl::context>(asio::ssl::context::tls_server);
    context->set_options(asio::ssl::context::default_workarounds | asio::ssl::context::no_sslv2 |
                         asio::ssl::context::no_sslv3 | asio::ssl::context::no_tlsv1 | asio::ssl::context::no_tlsv1_1);
    context->use_certificate_chain_file(options_.tls_cert.string());
    context->use_private_key_file(options_.tls_key.string(), asio::ssl::context::pem);
    return context;
  });
}

// The certificate and key load now, so that a wrong file is an error at start rather than a failed handshake later.
Status checkTlsFiles(const EndpointOptions& options) {
  try {
    asio::ssl::context context(asio::ssl::context::tls_server);
    context.use_certificate_chain_file(options.tls_cert.string());
    context.use_private_key_file(options.tls_key.string(), asio::ssl::context::pem);
  } catch (const std::exception& e) {
    return Error{ErrorCode::kInvalidArgument, "viewer: TLS certificate " + options.tls_cert.string() + " or key " +
                                                  options.tls_key.string() + " does not load: " + e.what()};
  }
  return Status::Ok();
}

}  // namespace

struct ViewerEndpoint::Impl {
  std::unique_ptr<Server> server;
};

Status EndpointOptions::validate() const {
  if (tls_cert.empty() != tls_key.empty()) {
    return Error{ErrorCode::kInvalidArgument, "viewer: TLS needs both the certificate and its key"};
  }
  if (socket_buffer_bytes < 4096) return Error{ErrorCode::kInvalidArgument, "viewer: socket buffer below 4096 bytes"};
  return Status::Ok();
}

Result<std::unique_ptr<ViewerEndpoint>> ViewerEndpoint::start(ViewerHub& hub, const MissionTokens& tokens,
                                                              const EndpointOptions& options) {
  if (Status s = options.validate(); !s.ok()) return s.error();
  auto at = parseListen(options.listen);
  if (!at) return at.error();
  auto impl = std::make_unique<Impl>();
  if (options.tls_cert.empty()) {
    auto server = std::make_unique<ServerOf<websocketpp::config::asio>>(hub, tokens, options);
    if (Status s = server->start(*at); !s.ok()) return s.error();
    impl->server = std::move(server);
  } else {
    if (Status s = checkTlsFiles(options); !s.ok()) return s.error();
    auto server = std::make_unique<ServerOf<websocketpp::config::asio_tls>>(hub, tokens, options);
    if (Status s = server->start(*at); !s.ok()) return s.error();
    impl->server = std::move(server);
  }
  return std::unique_ptr<ViewerEndpoint>(new ViewerEndpoint(std::move(impl)));
}

ViewerEndpoint::ViewerEndpoint(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
ViewerEndpoint::~ViewerEndpoint() = default;

int ViewerEndpoint::port() const {
  return impl_->server->port();
}
bool ViewerEndpoint::tls() const {
  return impl_->server->tls();
}

}  // namespace cvislam::server::viewer

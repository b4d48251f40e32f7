#include "server_cloud/service/read_forwarding.hpp"

#include <algorithm>
#include <chrono>

#include "common/core/text.hpp"
#include "server_cloud/core/server_core.hpp"

namespace cvislam::server {

Result<std::shared_ptr<grpc::ChannelCredentials>> peerCredentials(const ServerOptions& options) {
  if (options.tls_certificate.empty()) return grpc::InsecureChannelCredentials();
  const bool own = options.cluster.peer_ca.empty();
  auto roots = text::readPemFile(
      own ? options.tls_certificate : options.cluster.peer_ca,
      own ? "TLS certificate (--tls-cert), trusted for the other replicas" : "the other replicas' CA (--peer-ca)");
  if (!roots) return roots.error();
  grpc::SslCredentialsOptions tls;
  tls.pem_root_certs = std::move(roots).value();
  return grpc::SslCredentials(tls);
}

bool wasForwarded(const grpc::CallbackServerContext& context) {
  return context.client_metadata().count(kForwardedMetadataKey) != 0U;
}

std::unique_ptr<grpc::ClientContext> forwardingContext(const grpc::CallbackServerContext& incoming, bool unary) {
  auto context = std::make_unique<grpc::ClientContext>();
  const auto& metadata = incoming.client_metadata();
  if (const auto it = metadata.find("authorization"); it != metadata.end()) {
    context->AddMetadata("authorization", std::string(it->second.data(), it->second.size()));
  }
  context->AddMetadata(kForwardedMetadataKey, "1");
  auto deadline = incoming.deadline();
  if (unary) deadline = std::min(deadline, std::chrono::system_clock::now() + std::chrono::seconds(30));
  if (deadline != std::chrono::system_clock::time_point::max()) context->set_deadline(deadline);
  return context;
}

grpc::Status relayedStatus(const grpc::Status& status, const std::string& owner_address) {
  if (status.ok()) return status;
  return {status.error_code(),
          "from the replica serving the mission (" + owner_address + "): " + status.error_message()};
}

}  // namespace cvislam::server

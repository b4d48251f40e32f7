#include "server_cloud/store/operator_log.hpp"

#include <atomic>
#include <cstdint>
#include <cstdio>

namespace cvislam::server {

std::string logForOperator(const Error& error) {
  static std::atomic<std::uint64_t> next{1};
  const std::uint64_t number = next.fetch_add(1);
  std::fprintf(stderr, "[server] error #%llu: %s\n", static_cast<unsigned long long>(number), error.toString().c_str());
  return "server error #" + std::to_string(number) + ", in its log";
}

}  // namespace cvislam::server

#include "test/support/test_data.hpp"

#include <cstdlib>

namespace cvislam::test {

std::filesystem::path dataRoot() {
  if (const char* env = std::getenv("CVISLAM_DATA_DIR"); env != nullptr && *env != '\0') {
    return std::filesystem::path(env);
  }
  return std::filesystem::path(CVISLAM_DEFAULT_DATA_DIR);
}

std::filesystem::path findData(const std::string& relative) {
  std::error_code ec;
  const std::filesystem::path path = dataRoot() / relative;
  return std::filesystem::exists(path, ec) ? path.lexically_normal() : std::filesystem::path();
}

}  // namespace cvislam::test

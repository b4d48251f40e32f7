#include "common/dataset/csv.hpp"

namespace cvislam::dataset {

bool parseFieldDouble(const std::vector<std::string_view>& fields, std::size_t i, double& out, std::string& problem) {
  const auto value = text::parseDouble(fields[i]);
  if (!value) {
    problem = "field " + std::to_string(i + 1) + " ('" + std::string(fields[i]) + "') is not a finite number";
    return false;
  }
  out = *value;
  return true;
}

bool parseFieldNs(const std::vector<std::string_view>& fields, std::size_t i, std::int64_t& out, std::string& problem) {
  const auto value = text::parseInt64(fields[i]);
  if (!value || *value < 0) {
    problem = "field " + std::to_string(i + 1) + " ('" + std::string(fields[i]) +
              "') is not a timestamp in integer nanoseconds";
    return false;
  }
  out = *value;
  return true;
}

}  // namespace cvislam::dataset

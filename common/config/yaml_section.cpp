#include "common/config/yaml_section.hpp"

namespace cvislam::config {

YamlSection::YamlSection(const YAML::Node& node, std::string name)
    : node_(node && !node.IsNull() ? node : YAML::Node(YAML::NodeType::Map)), name_(std::move(name)) {}

Status YamlSection::finish() const {
  if (!error_.empty()) return Error{ErrorCode::kInvalidArgument, error_};
  if (!node_.IsMap()) return Error{ErrorCode::kInvalidArgument, "section " + name_ + " must be a map of keys"};
  for (const auto& item : node_) {
    const auto key = item.first.as<std::string>();
    if (known_.count(key) == 0) return Error{ErrorCode::kInvalidArgument, "unknown config key " + name_ + "." + key};
  }
  return Status::Ok();
}

Result<YAML::Node> loadSections(const std::string& file, const std::set<std::string>& sections) {
  YAML::Node root;
  try {
    root = YAML::LoadFile(file);
  } catch (const YAML::Exception& e) {
    return Error{ErrorCode::kIoError, file + ": " + e.what()};
  }
  if (root.IsNull()) return YAML::Node(YAML::NodeType::Map);  // an empty file: every default
  if (!root.IsMap()) return Error{ErrorCode::kInvalidArgument, file + ": expected a YAML map at the top"};
  std::string names;
  for (const std::string& s : sections) names += (names.empty() ? "" : ", ") + s;
  for (const auto& item : root) {
    const auto key = item.first.as<std::string>();
    if (sections.count(key) == 0) {
      return Error{ErrorCode::kInvalidArgument, file + ": unknown section '" + key + "' (" + names + ")"};
    }
  }
  return root;
}

}  // namespace cvislam::config

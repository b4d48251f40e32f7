// Reading one section of a YAML config file into an Options struct: every key a section knows is read into
// its field, and a key the section does not know is an error that names it, so that a typo never silently
// leaves a default in place. Shared by the agent's and the server's config files.
//
//   YamlSection s(root["mapping"], "mapping");
//   s.read("max_keyframes", options.max_keyframes);
//   if (Status st = s.finish(); !st.ok()) ...   // "unknown config key mapping.max_keyframe"
#pragma once

#include <set>
#include <string>

#include <yaml-cpp/yaml.h>

#include "common/core/result.hpp"

namespace cvislam::config {

class YamlSection {
 public:
  // A missing section (a null node) reads as empty: every value keeps its default.
  YamlSection(const YAML::Node& node, std::string name);

  template <typename T>
  void read(const char* key, T& value) {
    known_.insert(key);
    if (!node_[key]) return;
    try {
      value = node_[key].template as<T>();
    } catch (const YAML::Exception&) {
      if (error_.empty())
        error_ = name_ + "." + key + ": cannot read '" + YAML::Dump(node_[key]) + "' as the expected type";
    }
  }

  // The first bad value, or the first unknown key.
  [[nodiscard]] Status finish() const;

 private:
  YAML::Node node_;
  std::string name_;
  std::set<std::string> known_;
  std::string error_;
};

// Loads a YAML file whose top level is a map of sections, each one of `sections`; names the file in errors.
Result<YAML::Node> loadSections(const std::string& file, const std::set<std::string>& sections);

}  // namespace cvislam::config

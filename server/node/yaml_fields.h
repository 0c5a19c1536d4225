// The YAML of the node's configuration files (server/node/config.h), read
// strictly: unknown keys and values of the wrong type are errors, and every
// error is one line naming the file, the entry and the field. For
// config.cc's two readers (peers_config.cc, rules.cc) only.
#ifndef INTERSLICE_SERVER_NODE_YAML_FIELDS_H_
#define INTERSLICE_SERVER_NODE_YAML_FIELDS_H_

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/string_view.h"
#include "server/node/config.h"

namespace interslice::server::node::yaml_fields {

// Where in which file: prefixes every error so that it is one line naming
// the file, the entry (peer or rule) and the field.
class Context {
 public:
  Context(std::string file, std::string entry)
      : file_(std::move(file)), entry_(std::move(entry)) {}

  absl::Status Error(absl::string_view field, absl::string_view message) const {
    std::string text = file_ + ": ";
    if (!entry_.empty()) absl::StrAppend(&text, entry_, ": ");
    if (!field.empty()) absl::StrAppend(&text, field, ": ");
    absl::StrAppend(&text, message);
    // One line, whatever the message (a regex error could hold a newline).
    std::replace(text.begin(), text.end(), '\n', ' ');
    return absl::InvalidArgumentError(text);
  }

 private:
  std::string file_;
  std::string entry_;
};

// "a mapping", "a list", "text", "nothing": a node's kind, for errors.
const char* KindName(const YAML::Node& node);

// Quoted scalars (YAML "..." or '...', and every JSON string) have the
// non-specific tag "!": they are text, never numbers or booleans.
bool IsPlainScalar(const YAML::Node& node);

// INVALID_ARGUMENT naming the first key of `map` not in `known`
// (`prefix` names the mapping: "match.").
absl::Status CheckKeys(const YAML::Node& map, const Context& ctx,
                       const std::string& prefix,
                       const std::vector<std::string>& known);

// A field's value as text, a number, an integer or a boolean; a value
// of another type is INVALID_ARGUMENT naming `field`.
absl::StatusOr<std::string> GetString(const YAML::Node& node,
                                      const Context& ctx,
                                      const std::string& field);

absl::StatusOr<double> GetNumber(const YAML::Node& node, const Context& ctx,
                                 const std::string& field);

absl::StatusOr<int64_t> GetInteger(const YAML::Node& node, const Context& ctx,
                                   const std::string& field);

absl::StatusOr<bool> GetBool(const YAML::Node& node, const Context& ctx,
                             const std::string& field);

// A list of text items, or one text item (a comma-separated list).
absl::StatusOr<std::vector<std::string>> GetStringList(
    const YAML::Node& node, const Context& ctx, const std::string& field);

// The file parsed; INVALID_ARGUMENT with the parser's line and column.
absl::StatusOr<YAML::Node> LoadYaml(const std::string& path);

// {min: A, max: B} (either may be left out), or one number for both.
absl::StatusOr<ValueRange> GetRange(const YAML::Node& node, const Context& ctx,
                                    const std::string& field);

// Equal ignoring case and surrounding spaces (AE titles, modality).
bool SameText(const std::string& a, const std::string& b);

}  // namespace interslice::server::node::yaml_fields

#endif  // INTERSLICE_SERVER_NODE_YAML_FIELDS_H_

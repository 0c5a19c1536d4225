#include "server/node/yaml_fields.h"

#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <set>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_join.h"
#include "absl/strings/strip.h"

namespace interslice::server::node::yaml_fields {

const char* KindName(const YAML::Node& node) {
  switch (node.Type()) {
    case YAML::NodeType::Null:
      return "nothing";
    case YAML::NodeType::Scalar:
      return node.Tag() == "!" ? "a string" : "a scalar";
    case YAML::NodeType::Sequence:
      return "a list";
    case YAML::NodeType::Map:
      return "a mapping";
    default:
      return "an undefined value";
  }
}

// Quoted scalars (YAML "..." or '...', and every JSON string) have the
// non-specific tag "!": they are text, never numbers or booleans.
bool IsPlainScalar(const YAML::Node& node) {
  return node.IsScalar() && node.Tag() != "!";
}

absl::Status CheckKeys(const YAML::Node& map, const Context& ctx,
                       const std::string& prefix,
                       const std::vector<std::string>& known) {
  for (const auto& item : map) {
    if (!item.first.IsScalar()) {
      return ctx.Error(prefix, "keys must be plain text");
    }
    const std::string key = item.first.Scalar();
    if (std::find(known.begin(), known.end(), key) == known.end()) {
      return ctx.Error(prefix.empty() ? key : absl::StrCat(prefix, ".", key),
                       absl::StrCat("unknown key (known: ",
                                    absl::StrJoin(known, ", "), ")"));
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<std::string> GetString(const YAML::Node& node,
                                      const Context& ctx,
                                      const std::string& field) {
  if (!node.IsScalar()) {
    return ctx.Error(field,
                     absl::StrCat("expected text, got ", KindName(node)));
  }
  return node.Scalar();
}

absl::StatusOr<double> GetNumber(const YAML::Node& node, const Context& ctx,
                                 const std::string& field) {
  double value = 0;
  if (!IsPlainScalar(node) || !absl::SimpleAtod(node.Scalar(), &value) ||
      !std::isfinite(value)) {
    return ctx.Error(
        field,
        absl::StrCat("expected a number, got ",
                     node.IsScalar() ? absl::StrCat("'", node.Scalar(), "'")
                                     : KindName(node)));
  }
  return value;
}

absl::StatusOr<int64_t> GetInteger(const YAML::Node& node, const Context& ctx,
                                   const std::string& field) {
  int64_t value = 0;
  if (!IsPlainScalar(node) || !absl::SimpleAtoi(node.Scalar(), &value)) {
    return ctx.Error(
        field,
        absl::StrCat("expected an integer, got ",
                     node.IsScalar() ? absl::StrCat("'", node.Scalar(), "'")
                                     : KindName(node)));
  }
  return value;
}

absl::StatusOr<bool> GetBool(const YAML::Node& node, const Context& ctx,
                             const std::string& field) {
  if (IsPlainScalar(node)) {
    const std::string text = absl::AsciiStrToLower(node.Scalar());
    if (text == "true") return true;
    if (text == "false") return false;
  }
  return ctx.Error(
      field,
      absl::StrCat("expected true or false, got ",
                   node.IsScalar() ? absl::StrCat("'", node.Scalar(), "'")
                                   : KindName(node)));
}

// A list of text items, or one text item (a comma-separated list).
absl::StatusOr<std::vector<std::string>> GetStringList(
    const YAML::Node& node, const Context& ctx, const std::string& field) {
  std::vector<std::string> out;
  if (node.IsScalar()) {
    for (absl::string_view part :
         absl::StrSplit(node.Scalar(), ',', absl::SkipWhitespace())) {
      out.emplace_back(absl::StripAsciiWhitespace(part));
    }
    return out;
  }
  if (!node.IsSequence()) {
    return ctx.Error(field,
                     absl::StrCat("expected a list, got ", KindName(node)));
  }
  for (size_t i = 0; i < node.size(); ++i) {
    absl::StatusOr<std::string> item =
        GetString(node[i], ctx, absl::StrCat(field, "[", i, "]"));
    if (!item.ok()) return item.status();
    out.push_back(*item);
  }
  return out;
}

absl::StatusOr<YAML::Node> LoadYaml(const std::string& path) {
  try {
    return YAML::LoadFile(path);
  } catch (const YAML::BadFile&) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": cannot read the file"));
  } catch (const YAML::ParserException& e) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ":", e.mark.line + 1, ":", e.mark.column + 1,
                     ": not valid YAML or JSON: ", e.msg));
  } catch (const YAML::Exception& e) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": not valid YAML or JSON: ", e.msg));
  }
}

absl::StatusOr<ValueRange> GetRange(const YAML::Node& node, const Context& ctx,
                                    const std::string& field) {
  ValueRange range;
  if (node.IsSequence() && node.size() == 2) {
    absl::StatusOr<double> lo = GetNumber(node[0], ctx, field + "[0]");
    if (!lo.ok()) return lo.status();
    absl::StatusOr<double> hi = GetNumber(node[1], ctx, field + "[1]");
    if (!hi.ok()) return hi.status();
    range.min = *lo;
    range.max = *hi;
  } else if (node.IsMap()) {
    absl::Status keys = CheckKeys(node, ctx, field, {"min", "max"});
    if (!keys.ok()) return keys;
    if (node["min"]) {
      absl::StatusOr<double> v = GetNumber(node["min"], ctx, field + ".min");
      if (!v.ok()) return v.status();
      range.min = *v;
    }
    if (node["max"]) {
      absl::StatusOr<double> v = GetNumber(node["max"], ctx, field + ".max");
      if (!v.ok()) return v.status();
      range.max = *v;
    }
  } else {
    return ctx.Error(field,
                     absl::StrCat("expected {min: A, max: B} or [A, B], got ",
                                  KindName(node)));
  }
  if (range.min && range.max && *range.min > *range.max) {
    return ctx.Error(field, "min is greater than max");
  }
  return range;
}

bool SameText(const std::string& a, const std::string& b) {
  return absl::EqualsIgnoreCase(absl::StripAsciiWhitespace(a),
                                absl::StripAsciiWhitespace(b));
}

}  // namespace interslice::server::node::yaml_fields

#include "server/dicom/config.h"

#include <arpa/inet.h>
#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <optional>
#include <set>
#include <span>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "job/errors.h"
#include "job/options.h"
#include "job/wire.h"
#include "re2/re2.h"

namespace interslice::server::dicom {
namespace {

// A PACS serves each association with a thread or a process of its own;
// beyond a handful the gain is nil and a small PACS may refuse us.
constexpr int kMaxAssociationsPerPeer = 16;

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

absl::Status ReadMaxAssociations(const YAML::Node& p, const Context& ctx,
                                 DicomPeer& peer) {
  if (!p["max_associations"]) return absl::OkStatus();
  absl::StatusOr<int64_t> n =
      GetInteger(p["max_associations"], ctx, "max_associations");
  if (!n.ok()) return n.status();
  if (*n < 1 || *n > kMaxAssociationsPerPeer) {
    return ctx.Error(
        "max_associations",
        absl::StrCat("expected 1-", kMaxAssociationsPerPeer,
                     peer.type == PeerType::kDicomWeb
                         ? " (requests in parallel when sending to this peer)"
                         : " (associations in parallel when sending to this "
                           "peer)"));
  }
  peer.max_associations = static_cast<int>(*n);
  return absl::OkStatus();
}

// A file the node reads later (a secret, a certificate): it must exist and
// be readable now, so that a typo shows at start-up. Only the path appears
// in messages, never the contents. `must_have_text`: empty (or all-space)
// files are errors too (a token or password file).
absl::StatusOr<std::string> ReadablePath(const YAML::Node& p,
                                         const Context& ctx, const char* key,
                                         bool must_have_text) {
  absl::StatusOr<std::string> path = GetString(p[key], ctx, key);
  if (!path.ok()) return path.status();
  const std::string trimmed(absl::StripAsciiWhitespace(*path));
  if (trimmed.empty()) return ctx.Error(key, "empty");
  std::error_code ec;
  if (!std::filesystem::is_regular_file(trimmed, ec)) {
    return ctx.Error(key, absl::StrCat("'", trimmed, "' is not a file"));
  }
  std::ifstream in(trimmed, std::ios::binary);
  char first = 0;
  if (!in.is_open()) {
    return ctx.Error(key, absl::StrCat("cannot read '", trimmed, "'"));
  }
  if (must_have_text) {
    bool any = false;
    while (!any && in.get(first)) {
      any = !absl::ascii_isspace(static_cast<unsigned char>(first));
    }
    if (!any) {
      return ctx.Error(key, absl::StrCat("'", trimmed, "' is empty"));
    }
  }
  return trimmed;
}

// The DICOMweb keys of a peer: url (http or https, no credentials, query
// or fragment in it), one way to authenticate at most, TLS files for https.
absl::StatusOr<DicomWebEndpoint> ParseDicomWebEndpoint(const YAML::Node& p,
                                                       const Context& ctx) {
  DicomWebEndpoint web;
  if (!p["url"]) {
    return ctx.Error("url",
                     "missing (a DICOMweb peer needs its base URL, e.g. "
                     "http://pacs:8042/dicom-web)");
  }
  absl::StatusOr<std::string> url = GetString(p["url"], ctx, "url");
  if (!url.ok()) return url.status();
  std::string text(absl::StripAsciiWhitespace(*url));
  const std::string lower = absl::AsciiStrToLower(text);
  const bool https = absl::StartsWith(lower, "https://");
  if (!https && !absl::StartsWith(lower, "http://")) {
    return ctx.Error("url", "expected an http:// or https:// URL");
  }
  const size_t authority_start = text.find("://") + 3;
  const size_t authority_end = text.find('/', authority_start);
  const std::string authority =
      text.substr(authority_start, authority_end == std::string::npos
                                       ? std::string::npos
                                       : authority_end - authority_start);
  // Credentials in the URL would show on the status page and in logs.
  if (authority.find('@') != std::string::npos) {
    return ctx.Error("url",
                     "has credentials in it: use basic_user and "
                     "basic_password_file (or bearer_token_file)");
  }
  if (authority.empty()) return ctx.Error("url", "has no host");
  if (text.find_first_of("?# \t") != std::string::npos) {
    return ctx.Error("url",
                     "expected a base URL without query, fragment or spaces");
  }
  while (absl::EndsWith(text, "/")) text.pop_back();
  web.url = text;
  struct FileKey {
    const char* key;
    std::string* out;
    bool secret;
  };
  for (const FileKey& f :
       {FileKey{"bearer_token_file", &web.bearer_token_file, true},
        FileKey{"basic_password_file", &web.basic_password_file, true},
        FileKey{"client_certificate", &web.client_certificate, false},
        FileKey{"client_key", &web.client_key, false},
        FileKey{"ca_certificates", &web.ca_certificates, false}}) {
    if (!p[f.key]) continue;
    absl::StatusOr<std::string> path = ReadablePath(p, ctx, f.key, f.secret);
    if (!path.ok()) return path.status();
    *f.out = *path;
  }
  if (p["basic_user"]) {
    absl::StatusOr<std::string> user =
        GetString(p["basic_user"], ctx, "basic_user");
    if (!user.ok()) return user.status();
    web.basic_user = std::string(absl::StripAsciiWhitespace(*user));
    if (web.basic_user.empty()) return ctx.Error("basic_user", "empty");
    if (web.basic_user.find(':') != std::string::npos) {
      return ctx.Error("basic_user", "has a ':' (RFC 7617 forbids it)");
    }
  }
  if (web.basic_user.empty() != web.basic_password_file.empty()) {
    return ctx.Error(
        web.basic_user.empty() ? "basic_user" : "basic_password_file",
        "missing (HTTP basic needs basic_user and "
        "basic_password_file)");
  }
  if (!web.bearer_token_file.empty() && !web.basic_user.empty()) {
    return ctx.Error("bearer_token_file",
                     "give either a bearer token or basic_user, not both");
  }
  if (web.client_certificate.empty() != web.client_key.empty()) {
    return ctx.Error(
        web.client_certificate.empty() ? "client_certificate" : "client_key",
        "missing (mutual TLS needs client_certificate and client_key)");
  }
  if (!https) {
    for (const char* key :
         {"client_certificate", "client_key", "ca_certificates"}) {
      if (p[key]) {
        return ctx.Error(key, "only for an https:// url");
      }
    }
  }
  return web;
}

absl::StatusOr<RuleMatch> ParseMatch(const YAML::Node& node,
                                     const Context& ctx) {
  RuleMatch match;
  if (!node) return match;  // no criteria: matches every series
  if (!node.IsMap()) {
    return ctx.Error("match",
                     absl::StrCat("expected a mapping, got ", KindName(node)));
  }
  absl::Status keys =
      CheckKeys(node, ctx, "match",
                {"modality", "series_description", "protocol_name", "body_part",
                 "slice_thickness", "slice_spacing", "slice_count",
                 "calling_ae", "called_ae"});
  if (!keys.ok()) return keys;
  auto text = [&](const char* key,
                  std::optional<std::string>* out) -> absl::Status {
    if (!node[key]) return absl::OkStatus();
    absl::StatusOr<std::string> v =
        GetString(node[key], ctx, absl::StrCat("match.", key));
    if (!v.ok()) return v.status();
    *out = std::string(absl::StripAsciiWhitespace(*v));
    return absl::OkStatus();
  };
  auto regex = [&](const char* key,
                   std::shared_ptr<const re2::RE2>* out) -> absl::Status {
    if (!node[key]) return absl::OkStatus();
    const std::string field = absl::StrCat("match.", key);
    absl::StatusOr<std::string> v = GetString(node[key], ctx, field);
    if (!v.ok()) return v.status();
    re2::RE2::Options options;
    options.set_log_errors(false);
    auto re = std::make_shared<const re2::RE2>(*v, options);
    if (!re->ok()) {
      return ctx.Error(field,
                       absl::StrCat("bad regular expression: ", re->error()));
    }
    *out = std::move(re);
    return absl::OkStatus();
  };
  auto range = [&](const char* key,
                   std::optional<ValueRange>* out) -> absl::Status {
    if (!node[key]) return absl::OkStatus();
    absl::StatusOr<ValueRange> v =
        GetRange(node[key], ctx, absl::StrCat("match.", key));
    if (!v.ok()) return v.status();
    *out = *v;
    return absl::OkStatus();
  };
  for (absl::Status s :
       {text("modality", &match.modality), text("body_part", &match.body_part),
        regex("series_description", &match.series_description),
        regex("protocol_name", &match.protocol_name),
        range("slice_thickness", &match.slice_thickness_mm),
        range("slice_spacing", &match.slice_spacing_mm),
        range("slice_count", &match.slice_count)}) {
    if (!s.ok()) return s;
  }
  for (auto [key, out] : {std::pair{"calling_ae", &match.calling_ae},
                          std::pair{"called_ae", &match.called_ae}}) {
    if (!node[key]) continue;
    absl::StatusOr<std::string> v =
        GetString(node[key], ctx, absl::StrCat("match.", key));
    if (!v.ok()) return v.status();
    absl::StatusOr<std::string> ae = NormalizeAeTitle(*v);
    if (!ae.ok()) {
      return ctx.Error(absl::StrCat("match.", key), ae.status().message());
    }
    *out = *ae;
  }
  return match;
}

// A rule's `job:` or `fill:` mapping -> the option values of the job layer
// (job/options.h): the keys are the option table's (every option the rules
// file takes), each read as its table row says (numbers, integers, text,
// true/false; lists as YAML lists or the command line's "a,b"; integer lists
// as YAML lists of integers; a box as a list of six integers or "a,b,...").
template <typename Options>
absl::Status ReadOptions(const YAML::Node& node, const Context& ctx,
                         const std::string& section,
                         std::span<const job::OptionDef<Options>> table,
                         Options& options) {
  std::vector<std::string> known;
  for (const job::OptionDef<Options>& def : table) {
    if (def.doors & job::kRulesFile) known.emplace_back(def.key);
  }
  if (absl::Status s = CheckKeys(node, ctx, section, known); !s.ok()) return s;
  for (const auto& item : node) {
    const std::string key = item.first.Scalar();
    const YAML::Node value = item.second;
    const std::string field = absl::StrCat(section, ".", key);
    const job::OptionDef<Options>* def = job::FindOption(table, key);
    std::string text;
    switch (def->kind) {
      case job::ValueKind::kNumber: {
        absl::StatusOr<double> v = GetNumber(value, ctx, field);
        if (!v.ok()) return v.status();
        text = value.Scalar();
        break;
      }
      case job::ValueKind::kInteger: {
        absl::StatusOr<int64_t> v = GetInteger(value, ctx, field);
        if (!v.ok()) return v.status();
        text = absl::StrCat(*v);
        break;
      }
      case job::ValueKind::kText: {
        absl::StatusOr<std::string> v = GetString(value, ctx, field);
        if (!v.ok()) return v.status();
        text = *v;
        break;
      }
      case job::ValueKind::kFlag: {
        absl::StatusOr<bool> v = GetBool(value, ctx, field);
        if (!v.ok()) return v.status();
        text = *v ? "true" : "false";
        break;
      }
      case job::ValueKind::kList: {
        absl::StatusOr<std::vector<std::string>> v =
            GetStringList(value, ctx, field);
        if (!v.ok()) return v.status();
        text = v->empty() ? "none" : absl::StrJoin(*v, ",");
        break;
      }
      case job::ValueKind::kIntegerList:
      case job::ValueKind::kBox: {
        const bool box = def->kind == job::ValueKind::kBox;
        if (box && value.IsScalar()) {
          text = value.Scalar();
          break;
        }
        if (!value.IsSequence()) {
          return ctx.Error(field, absl::StrCat("expected a list of integers, "
                                               "got ",
                                               KindName(value)));
        }
        std::vector<std::string> parts;
        for (size_t i = 0; i < value.size(); ++i) {
          absl::StatusOr<int64_t> v =
              GetInteger(value[i], ctx, absl::StrCat(field, "[", i, "]"));
          if (!v.ok()) return v.status();
          parts.push_back(absl::StrCat(*v));
        }
        text = absl::StrJoin(parts, ",");
        break;
      }
      case job::ValueKind::kMmBox: {
        if (value.IsScalar()) {
          text = value.Scalar();
          break;
        }
        if (!value.IsSequence()) {
          return ctx.Error(field, absl::StrCat("expected a list of numbers, "
                                               "got ",
                                               KindName(value)));
        }
        std::vector<std::string> parts;
        for (size_t i = 0; i < value.size(); ++i) {
          absl::StatusOr<double> v =
              GetNumber(value[i], ctx, absl::StrCat(field, "[", i, "]"));
          if (!v.ok()) return v.status();
          parts.push_back(value[i].Scalar());
        }
        text = absl::StrJoin(parts, ",");
        break;
      }
    }
    if (absl::Status s = job::SetOption(options, key, text); !s.ok()) {
      return ctx.Error(field, job::ErrorMessageWithoutKey(s));
    }
  }
  return absl::OkStatus();
}

// An error of BuildJobSpec / BuildFillJobSpec, named as the rules file names
// the option ("job.energy_units").
absl::Status RuleOptionError(const absl::Status& status, const Context& ctx,
                             const std::string& section) {
  const std::optional<std::string> key = job::ErrorOptionKey(status);
  return ctx.Error(key.has_value() ? absl::StrCat(section, ".", *key) : section,
                   job::ErrorMessageWithoutKey(status));
}

// The `job` mapping -> the wire spec of an interpolation job, checked as
// every door checks it.
absl::StatusOr<v1::JobSpec> ParseJob(const YAML::Node& node,
                                     const Context& ctx) {
  if (!node)
    return ctx.Error("job",
                     "missing (every rule needs a job, or a fill for "
                     "segmentations)");
  if (!node.IsMap()) {
    return ctx.Error("job",
                     absl::StrCat("expected a mapping, got ", KindName(node)));
  }
  job::InterpolationOptions options;
  // Placeholders: the server supplies the received files and the output
  // folder when it makes the job.
  options.inputs = {"dicom"};
  options.out = "out";
  if (absl::Status s = ReadOptions(node, ctx, "job",
                                   job::InterpolationOptionTable(), options);
      !s.ok()) {
    return s;
  }
  absl::StatusOr<JobSpec> spec = job::BuildJobSpec(options);
  if (!spec.ok()) return RuleOptionError(spec.status(), ctx, "job");
  return job::ToWire(*spec);
}

// The `fill` mapping (a rule for SEG / RTSTRUCT series) -> the wire spec of a
// fill job, checked as every door checks it.
absl::StatusOr<v1::JobSpec> ParseFill(const YAML::Node& node,
                                      const Context& ctx) {
  job::FillJobOptions options;
  options.segmentation = "segmentation";
  options.reference = {"dicom"};
  options.out = "out";
  // What came in as DICOM goes back as DICOM: the filled labels as a SEG
  // (and as an RTSTRUCT when the input was one, the fill's own default).
  options.seg = true;
  if (!node.IsNull()) {  // `fill:` alone: every default
    if (!node.IsMap()) {
      return ctx.Error(
          "fill", absl::StrCat("expected a mapping, got ", KindName(node)));
    }
    if (absl::Status s =
            ReadOptions(node, ctx, "fill", job::FillOptionTable(), options);
        !s.ok()) {
      return s;
    }
  }
  absl::StatusOr<FillJobSpec> spec = job::BuildFillJobSpec(options);
  if (!spec.ok()) return RuleOptionError(spec.status(), ctx, "fill");
  // The server names the received segmentation itself.
  return job::ToWire(*spec, "segmentation.dcm");
}

}  // namespace

absl::StatusOr<std::string> NormalizeAeTitle(const std::string& text) {
  const std::string ae(absl::StripAsciiWhitespace(text));
  if (ae.empty() || ae.size() > 16) {
    return absl::InvalidArgumentError(
        "an AE title has 1 to 16 characters (not all spaces)");
  }
  for (char c : ae) {
    if (c == '\\' || static_cast<unsigned char>(c) < 0x20 ||
        static_cast<unsigned char>(c) > 0x7e) {
      return absl::InvalidArgumentError(
          "an AE title holds no backslash, control or non-ASCII characters");
    }
  }
  return ae;
}

bool ValueRange::Contains(double value) const {
  return (!min || value >= *min) && (!max || value <= *max);
}

namespace {

std::string RangeText(const ValueRange& range) {
  if (range.min && range.max) {
    return absl::StrCat("in [", *range.min, ", ", *range.max, "]");
  }
  if (range.min) return absl::StrCat(">= ", *range.min);
  if (range.max) return absl::StrCat("<= ", *range.max);
  return "any";
}

// "modality is 'MR', not 'CT'" for a text criterion that failed.
std::string TextFailure(const char* criterion, const std::string& value,
                        const std::string& wanted) {
  return absl::StrCat(criterion, " is '", value, "', not '", wanted, "'");
}

std::string RangeFailure(const char* criterion,
                         const std::optional<double>& value,
                         const ValueRange& range) {
  if (!value)
    return absl::StrCat(criterion, " unknown, wanted ", RangeText(range));
  return absl::StrCat(criterion, " ", *value, " not ", RangeText(range));
}

}  // namespace

std::string RuleMatch::FirstFailure(const SeriesFacts& f) const {
  if (modality && !SameText(*modality, f.modality)) {
    return TextFailure("modality", f.modality, *modality);
  }
  if (body_part && !SameText(*body_part, f.body_part)) {
    return TextFailure("body_part", f.body_part, *body_part);
  }
  if (calling_ae && !SameText(*calling_ae, f.calling_ae)) {
    return TextFailure("calling_ae", f.calling_ae, *calling_ae);
  }
  if (called_ae && !SameText(*called_ae, f.called_ae)) {
    return TextFailure("called_ae", f.called_ae, *called_ae);
  }
  // Free text may name a patient or a study: only the criterion is named.
  if (series_description &&
      !re2::RE2::PartialMatch(f.series_description, *series_description)) {
    return absl::StrCat("series_description does not match /",
                        series_description->pattern(), "/");
  }
  if (protocol_name &&
      !re2::RE2::PartialMatch(f.protocol_name, *protocol_name)) {
    return absl::StrCat("protocol_name does not match /",
                        protocol_name->pattern(), "/");
  }
  if (slice_thickness_mm &&
      (!f.slice_thickness_mm ||
       !slice_thickness_mm->Contains(*f.slice_thickness_mm))) {
    return RangeFailure("slice_thickness", f.slice_thickness_mm,
                        *slice_thickness_mm);
  }
  if (slice_spacing_mm && (!f.slice_spacing_mm ||
                           !slice_spacing_mm->Contains(*f.slice_spacing_mm))) {
    return RangeFailure("slice_spacing", f.slice_spacing_mm, *slice_spacing_mm);
  }
  if (slice_count &&
      !slice_count->Contains(static_cast<double>(f.slice_count))) {
    return RangeFailure("slice_count", static_cast<double>(f.slice_count),
                        *slice_count);
  }
  return "";
}

bool RuleMatch::Matches(const SeriesFacts& f) const {
  return FirstFailure(f).empty();
}

std::string RuleMatch::Describe() const {
  std::vector<std::string> parts;
  if (modality) parts.push_back(absl::StrCat("modality ", *modality));
  if (body_part) parts.push_back(absl::StrCat("body_part ", *body_part));
  if (calling_ae) parts.push_back(absl::StrCat("calling_ae ", *calling_ae));
  if (called_ae) parts.push_back(absl::StrCat("called_ae ", *called_ae));
  if (series_description) {
    parts.push_back(absl::StrCat("series_description /",
                                 series_description->pattern(), "/"));
  }
  if (protocol_name) {
    parts.push_back(
        absl::StrCat("protocol_name /", protocol_name->pattern(), "/"));
  }
  if (slice_thickness_mm) {
    parts.push_back(
        absl::StrCat("slice_thickness ", RangeText(*slice_thickness_mm)));
  }
  if (slice_spacing_mm) {
    parts.push_back(
        absl::StrCat("slice_spacing ", RangeText(*slice_spacing_mm)));
  }
  if (slice_count) {
    parts.push_back(absl::StrCat("slice_count ", RangeText(*slice_count)));
  }
  if (parts.empty()) return "every series";
  return absl::StrJoin(parts, ", ");
}

const Rule* RuleSet::FirstMatch(const SeriesFacts& facts) const {
  for (const Rule& rule : rules) {
    // Fill rules are for segmentations only, and segmentations for fill
    // rules only: a SEG is never thresholded, a CT never read as labels.
    if (rule.job.has_fill() != facts.segmentation) continue;
    if (rule.match.Matches(facts)) return &rule;
  }
  return nullptr;
}

std::string RuleSet::ExplainNoMatch(const SeriesFacts& facts) const {
  if (rules.empty()) return "the rule set has no rules";
  std::vector<std::string> reasons;
  for (const Rule& rule : rules) {
    std::string why;
    if (rule.job.has_fill() && !facts.segmentation) {
      why = "a fill rule (segmentations only)";
    } else if (!rule.job.has_fill() && facts.segmentation) {
      why = "a job rule (not for segmentations)";
    } else {
      why = rule.match.FirstFailure(facts);
      if (why.empty()) why = "matches";
    }
    reasons.push_back(absl::StrCat("rule '", rule.name, "': ", why));
  }
  return absl::StrJoin(reasons, "; ");
}

absl::StatusOr<PeersConfig> LoadPeersConfig(const std::string& path) {
  absl::StatusOr<YAML::Node> root = LoadYaml(path);
  if (!root.ok()) return root.status();
  const Context file_ctx(path, "");
  PeersConfig config;
  if (root->IsNull()) return config;
  if (!root->IsMap()) {
    return file_ctx.Error("", absl::StrCat("expected a mapping with 'peers', "
                                           "got ",
                                           KindName(*root)));
  }
  absl::Status keys =
      CheckKeys(*root, file_ctx, "", {"peers", "accept_unknown_callers"});
  if (!keys.ok()) return keys;
  if ((*root)["accept_unknown_callers"]) {
    absl::StatusOr<bool> v = GetBool((*root)["accept_unknown_callers"],
                                     file_ctx, "accept_unknown_callers");
    if (!v.ok()) return v.status();
    config.accept_unknown_callers = *v;
  }
  const YAML::Node peers = (*root)["peers"];
  if (!peers || peers.IsNull()) return config;
  if (!peers.IsSequence()) {
    return file_ctx.Error(
        "peers", absl::StrCat("expected a list, got ", KindName(peers)));
  }
  std::set<std::string> names;
  for (size_t i = 0; i < peers.size(); ++i) {
    const YAML::Node p = peers[i];
    std::string entry = absl::StrCat("peer #", i + 1);
    if (p.IsMap() && p["name"] && p["name"].IsScalar()) {
      entry = absl::StrCat("peer '", p["name"].Scalar(), "' (#", i + 1, ")");
    }
    const Context ctx(path, entry);
    if (!p.IsMap()) {
      return ctx.Error("",
                       absl::StrCat("expected a mapping, got ", KindName(p)));
    }
    DicomPeer peer;
    if (p["type"]) {
      absl::StatusOr<std::string> type = GetString(p["type"], ctx, "type");
      if (!type.ok()) return type.status();
      const std::string lower =
          absl::AsciiStrToLower(absl::StripAsciiWhitespace(*type));
      if (lower == "dicomweb") {
        peer.type = PeerType::kDicomWeb;
      } else if (lower != "dimse") {
        return ctx.Error("type", absl::StrCat("'", *type,
                                              "': expected dimse (the "
                                              "default) or dicomweb"));
      }
    }
    const bool web = peer.type == PeerType::kDicomWeb;
    // Keys of the other kind of peer are errors that say so (a DICOMweb
    // peer with an ae_title was most likely meant as a DIMSE one).
    const std::vector<std::string> dimse_only = {
        "ae_title", "host", "port", "tls", "allowed_sources", "retrieve"};
    const std::vector<std::string> web_only = {"url",
                                               "bearer_token_file",
                                               "basic_user",
                                               "basic_password_file",
                                               "client_certificate",
                                               "client_key",
                                               "ca_certificates"};
    for (const std::string& key : web ? dimse_only : web_only) {
      if (p[key]) {
        return ctx.Error(key, web ? "not for a DICOMweb peer (type: "
                                    "dicomweb talks HTTP to its url)"
                                  : "only for a DICOMweb peer (add type: "
                                    "dicomweb)");
      }
    }
    std::vector<std::string> known = {"name", "type", "max_associations"};
    known.insert(known.end(), (web ? web_only : dimse_only).begin(),
                 (web ? web_only : dimse_only).end());
    keys = CheckKeys(p, ctx, "", known);
    if (!keys.ok()) return keys;
    if (!p["name"]) return ctx.Error("name", "missing");
    absl::StatusOr<std::string> name = GetString(p["name"], ctx, "name");
    if (!name.ok()) return name.status();
    peer.name = std::string(absl::StripAsciiWhitespace(*name));
    if (peer.name.empty()) return ctx.Error("name", "empty");
    if (!names.insert(peer.name).second) {
      return ctx.Error("name", "another peer has this name");
    }
    if (absl::Status s = ReadMaxAssociations(p, ctx, peer); !s.ok()) return s;
    if (web) {
      absl::StatusOr<DicomWebEndpoint> endpoint = ParseDicomWebEndpoint(p, ctx);
      if (!endpoint.ok()) return endpoint.status();
      peer.web = *std::move(endpoint);
      config.peers.push_back(std::move(peer));
      continue;
    }
    for (const char* required : {"ae_title", "host"}) {
      if (!p[required]) return ctx.Error(required, "missing");
    }
    absl::StatusOr<std::string> ae = GetString(p["ae_title"], ctx, "ae_title");
    if (!ae.ok()) return ae.status();
    absl::StatusOr<std::string> normal = NormalizeAeTitle(*ae);
    if (!normal.ok()) return ctx.Error("ae_title", normal.status().message());
    peer.ae_title = *normal;
    absl::StatusOr<std::string> host = GetString(p["host"], ctx, "host");
    if (!host.ok()) return host.status();
    peer.host = std::string(absl::StripAsciiWhitespace(*host));
    if (peer.host.empty()) return ctx.Error("host", "empty");
    if (p["port"]) {
      absl::StatusOr<int64_t> port = GetInteger(p["port"], ctx, "port");
      if (!port.ok()) return port.status();
      if (*port < 1 || *port > 65535) {
        return ctx.Error("port", "expected a port number 1-65535");
      }
      peer.port = static_cast<int>(*port);
    }
    if (p["tls"]) {
      absl::StatusOr<bool> tls = GetBool(p["tls"], ctx, "tls");
      if (!tls.ok()) return tls.status();
      peer.tls = *tls;
    }
    if (p["retrieve"]) {
      absl::StatusOr<std::string> how =
          GetString(p["retrieve"], ctx, "retrieve");
      if (!how.ok()) return how.status();
      const std::string lower =
          absl::AsciiStrToLower(absl::StripAsciiWhitespace(*how));
      if (lower == "move") {
        peer.retrieve = RetrieveMethod::kMove;
      } else if (lower != "get") {
        return ctx.Error("retrieve", absl::StrCat("'", *how,
                                                  "': expected get (C-GET, "
                                                  "the default) or move "
                                                  "(C-MOVE)"));
      }
    }
    if (const YAML::Node sources = p["allowed_sources"]; sources) {
      if (!sources.IsSequence() || sources.size() == 0) {
        return ctx.Error("allowed_sources",
                         "expected a non-empty list of addresses or networks "
                         "(\"10.0.0.0/8\", \"192.168.1.7\")");
      }
      for (size_t k = 0; k < sources.size(); ++k) {
        const std::string field = absl::StrCat("allowed_sources[", k, "]");
        absl::StatusOr<std::string> text = GetString(sources[k], ctx, field);
        if (!text.ok()) return text.status();
        absl::StatusOr<SourceNetwork> network = ParseSourceNetwork(*text);
        if (!network.ok()) return ctx.Error(field, network.status().message());
        peer.allowed_sources.push_back(*std::move(network));
      }
    }
    config.peers.push_back(std::move(peer));
  }
  return config;
}

absl::StatusOr<SourceNetwork> ParseSourceNetwork(const std::string& text) {
  const std::string trimmed(absl::StripAsciiWhitespace(text));
  SourceNetwork network;
  network.text = trimmed;
  std::string address = trimmed;
  int prefix = -1;
  if (const size_t slash = trimmed.find('/'); slash != std::string::npos) {
    address = trimmed.substr(0, slash);
    if (!absl::SimpleAtoi(trimmed.substr(slash + 1), &prefix)) {
      return absl::InvalidArgumentError(
          absl::StrCat("'", trimmed,
                       "': the prefix length after / "
                       "is not a number"));
    }
  }
  if (inet_pton(AF_INET, address.c_str(), network.address) == 1) {
    network.family = 4;
    if (prefix < 0) prefix = 32;
    if (prefix > 32) {
      return absl::InvalidArgumentError(
          absl::StrCat("'", trimmed, "': an IPv4 prefix is at most 32 bits"));
    }
  } else if (inet_pton(AF_INET6, address.c_str(), network.address) == 1) {
    network.family = 6;
    if (prefix < 0) prefix = 128;
    if (prefix > 128) {
      return absl::InvalidArgumentError(
          absl::StrCat("'", trimmed, "': an IPv6 prefix is at most 128 bits"));
    }
  } else {
    return absl::InvalidArgumentError(
        absl::StrCat("'", trimmed,
                     "' is not an IPv4 or IPv6 address (no host names: the "
                     "listener checks the connection's address)"));
  }
  network.prefix_bits = prefix;
  return network;
}

bool InNetwork(const std::string& address, const SourceNetwork& network) {
  unsigned char bytes[16] = {};
  const int family = network.family == 4 ? AF_INET : AF_INET6;
  if (inet_pton(family, address.c_str(), bytes) != 1) return false;
  const int full = network.prefix_bits / 8;
  const int rest = network.prefix_bits % 8;
  if (std::memcmp(bytes, network.address, static_cast<size_t>(full)) != 0) {
    return false;
  }
  if (rest == 0) return true;
  const unsigned char mask = static_cast<unsigned char>(0xFF << (8 - rest));
  return (bytes[full] & mask) == (network.address[full] & mask);
}

absl::StatusOr<std::vector<DicomPeer>> LoadPeersFile(const std::string& path) {
  absl::StatusOr<PeersConfig> config = LoadPeersConfig(path);
  if (!config.ok()) return config.status();
  return std::move(config->peers);
}

absl::StatusOr<RuleSet> LoadRulesFile(const std::string& path,
                                      const std::vector<DicomPeer>& peers) {
  absl::StatusOr<YAML::Node> root = LoadYaml(path);
  if (!root.ok()) return root.status();
  const Context file_ctx(path, "");
  RuleSet set;
  set.path = path;
  if (!root->IsMap()) {
    return file_ctx.Error("", absl::StrCat("expected a mapping with 'rules', "
                                           "got ",
                                           KindName(*root)));
  }
  absl::Status keys =
      CheckKeys(*root, file_ctx, "", {"stable_seconds", "rules"});
  if (!keys.ok()) return keys;
  if ((*root)["stable_seconds"]) {
    absl::StatusOr<double> v =
        GetNumber((*root)["stable_seconds"], file_ctx, "stable_seconds");
    if (!v.ok()) return v.status();
    if (!(*v > 0) || *v > 7 * 24 * 3600) {
      return file_ctx.Error(
          "stable_seconds",
          "expected a number of seconds > 0 (at most a week)");
    }
    set.stable_seconds = *v;
  }
  const YAML::Node rules = (*root)["rules"];
  if (!rules || !rules.IsSequence()) {
    return file_ctx.Error(
        "rules", rules ? absl::StrCat("expected a list, got ", KindName(rules))
                       : std::string("missing"));
  }
  std::set<std::string> names;
  for (size_t i = 0; i < rules.size(); ++i) {
    const YAML::Node r = rules[i];
    Rule rule;
    rule.name = absl::StrCat("#", i + 1);
    std::string entry = absl::StrCat("rule #", i + 1);
    if (r.IsMap() && r["name"] && r["name"].IsScalar()) {
      rule.name = std::string(absl::StripAsciiWhitespace(r["name"].Scalar()));
      entry = absl::StrCat("rule '", rule.name, "' (#", i + 1, ")");
    }
    const Context ctx(path, entry);
    if (!r.IsMap()) {
      return ctx.Error("",
                       absl::StrCat("expected a mapping, got ", KindName(r)));
    }
    keys = CheckKeys(
        r, ctx, "",
        {"name", "match", "job", "fill", "send_to", "complete_on_release"});
    if (!keys.ok()) return keys;
    if (r["name"]) {
      if (!r["name"].IsScalar()) {
        return ctx.Error(
            "name", absl::StrCat("expected text, got ", KindName(r["name"])));
      }
      if (rule.name.empty()) return ctx.Error("name", "empty");
      if (!names.insert(rule.name).second) {
        return ctx.Error("name", "another rule has this name");
      }
    }
    absl::StatusOr<RuleMatch> match = ParseMatch(r["match"], ctx);
    if (!match.ok()) return match.status();
    rule.match = *std::move(match);
    if (r["job"] && r["fill"]) {
      return ctx.Error("fill",
                       "a rule has either a job (series) or a fill "
                       "(segmentations), not both");
    }
    absl::StatusOr<v1::JobSpec> job =
        r["fill"] ? ParseFill(r["fill"], ctx) : ParseJob(r["job"], ctx);
    if (!job.ok()) return job.status();
    rule.job = *std::move(job);
    // The enhanced layout is written for CT and MR sources (Enhanced CT /
    // MR Image, core/dicom_out/enhanced_series.h): a rule that matches
    // another modality would make jobs that all fail, found only when a
    // series arrives. (A rule without a modality criterion may still meet a
    // PT series; that job fails FAILED_PRECONDITION naming the layout.)
    if (rule.job.derived_series().layout() == v1::DICOM_LAYOUT_ENHANCED &&
        rule.match.modality && !SameText(*rule.match.modality, "CT") &&
        !SameText(*rule.match.modality, "MR")) {
      return ctx.Error(
          "job",
          absl::StrCat("dicom_layout enhanced is written for CT and MR only "
                       "(Enhanced CT / Enhanced MR Image), but the rule "
                       "matches modality '",
                       *rule.match.modality, "': use dicom_layout classic"));
    }
    if (r["send_to"]) {
      absl::StatusOr<std::vector<std::string>> to =
          GetStringList(r["send_to"], ctx, "send_to");
      if (!to.ok()) return to.status();
      for (const std::string& name : *to) {
        const bool known =
            std::any_of(peers.begin(), peers.end(),
                        [&](const DicomPeer& p) { return p.name == name; });
        if (!known) {
          return ctx.Error("send_to",
                           absl::StrCat("unknown peer '", name,
                                        "' (not in the peers file)"));
        }
        if (std::find(rule.send_to.begin(), rule.send_to.end(), name) ==
            rule.send_to.end()) {
          rule.send_to.push_back(name);
        }
      }
    }
    for (const std::string& name : rule.send_to) rule.job.add_send_to(name);
    if (r["complete_on_release"]) {
      absl::StatusOr<bool> v =
          GetBool(r["complete_on_release"], ctx, "complete_on_release");
      if (!v.ok()) return v.status();
      rule.complete_on_release = *v;
    }
    set.rules.push_back(std::move(rule));
  }
  return set;
}

}  // namespace interslice::server::dicom

// The rules file (server/node/config.h has its format) and what a rule
// matches.
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
#include "server/node/config.h"
#include "server/node/yaml_fields.h"

namespace interslice::server::node {

using yaml_fields::CheckKeys;
using yaml_fields::Context;
using yaml_fields::GetBool;
using yaml_fields::GetInteger;
using yaml_fields::GetNumber;
using yaml_fields::GetRange;
using yaml_fields::GetString;
using yaml_fields::GetStringList;
using yaml_fields::IsPlainScalar;
using yaml_fields::KindName;
using yaml_fields::LoadYaml;
using yaml_fields::SameText;

namespace {

// `section`: "match" or "exclude" (the key the mapping is under).
absl::StatusOr<RuleMatch> ParseMatch(const YAML::Node& node, const Context& ctx,
                                     const std::string& section) {
  RuleMatch match;
  if (!node) return match;  // no criteria: matches every series
  if (!node.IsMap()) {
    return ctx.Error(section,
                     absl::StrCat("expected a mapping, got ", KindName(node)));
  }
  absl::Status keys = CheckKeys(
      node, ctx, section,
      {"modality", "series_description", "protocol_name", "body_part",
       "slice_thickness", "slice_spacing", "slice_count", "calling_ae",
       "called_ae", "image_type", "manufacturer", "sop_class", "own_results"});
  if (!keys.ok()) return keys;
  const std::string prefix = section + ".";
  auto text = [&](const char* key,
                  std::optional<std::string>* out) -> absl::Status {
    if (!node[key]) return absl::OkStatus();
    absl::StatusOr<std::string> v =
        GetString(node[key], ctx, absl::StrCat(prefix, key));
    if (!v.ok()) return v.status();
    *out = std::string(absl::StripAsciiWhitespace(*v));
    return absl::OkStatus();
  };
  auto regex = [&](const char* key,
                   std::shared_ptr<const re2::RE2>* out) -> absl::Status {
    if (!node[key]) return absl::OkStatus();
    const std::string field = absl::StrCat(prefix, key);
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
        GetRange(node[key], ctx, absl::StrCat(prefix, key));
    if (!v.ok()) return v.status();
    *out = *v;
    return absl::OkStatus();
  };
  for (absl::Status s :
       {text("modality", &match.modality), text("body_part", &match.body_part),
        regex("series_description", &match.series_description),
        regex("protocol_name", &match.protocol_name),
        regex("image_type", &match.image_type),
        regex("manufacturer", &match.manufacturer),
        range("slice_thickness", &match.slice_thickness_mm),
        range("slice_spacing", &match.slice_spacing_mm),
        range("slice_count", &match.slice_count)}) {
    if (!s.ok()) return s;
  }
  for (auto [key, out] : {std::pair{"calling_ae", &match.calling_ae},
                          std::pair{"called_ae", &match.called_ae}}) {
    if (!node[key]) continue;
    absl::StatusOr<std::string> v =
        GetString(node[key], ctx, absl::StrCat(prefix, key));
    if (!v.ok()) return v.status();
    absl::StatusOr<std::string> ae = NormalizeAeTitle(*v);
    if (!ae.ok()) {
      return ctx.Error(absl::StrCat(prefix, key), ae.status().message());
    }
    *out = *ae;
  }
  if (node["sop_class"]) {
    absl::StatusOr<std::vector<std::string>> uids =
        GetStringList(node["sop_class"], ctx, prefix + "sop_class");
    if (!uids.ok()) return uids.status();
    for (const std::string& uid : *uids) {
      const std::string trimmed(absl::StripAsciiWhitespace(uid));
      if (trimmed.empty() || trimmed.size() > 64 ||
          trimmed.find_first_not_of("0123456789.") != std::string::npos) {
        return ctx.Error(prefix + "sop_class",
                         absl::StrCat("'", trimmed,
                                      "' is not a SOP Class UID (digits and "
                                      "dots, e.g. 1.2.840.10008.5.1.4.1.1.2)"));
      }
      match.sop_classes.push_back(trimmed);
    }
  }
  if (node["own_results"]) {
    absl::StatusOr<bool> v =
        GetBool(node["own_results"], ctx, prefix + "own_results");
    if (!v.ok()) return v.status();
    match.own_results = *v;
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
  if (f.own_result && !own_results) {
    return "made by interslice (its own result; only a rule with "
           "match.own_results: true takes those)";
  }
  if (own_results && !f.own_result) {
    return "not made by interslice (the rule takes own_results only)";
  }
  return CriteriaFailure(f);
}

std::string RuleMatch::CriteriaFailure(const SeriesFacts& f) const {
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
  if (image_type && !re2::RE2::PartialMatch(f.image_type, *image_type)) {
    return absl::StrCat("image_type does not match /", image_type->pattern(),
                        "/");
  }
  if (manufacturer && !re2::RE2::PartialMatch(f.manufacturer, *manufacturer)) {
    return absl::StrCat("manufacturer does not match /",
                        manufacturer->pattern(), "/");
  }
  if (!sop_classes.empty() && std::find(sop_classes.begin(), sop_classes.end(),
                                        f.sop_class_uid) == sop_classes.end()) {
    return absl::StrCat("sop_class is '", f.sop_class_uid, "', not one of ",
                        absl::StrJoin(sop_classes, ", "));
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
  if (image_type) {
    parts.push_back(absl::StrCat("image_type /", image_type->pattern(), "/"));
  }
  if (manufacturer) {
    parts.push_back(
        absl::StrCat("manufacturer /", manufacturer->pattern(), "/"));
  }
  if (!sop_classes.empty()) {
    parts.push_back(
        absl::StrCat("sop_class ", absl::StrJoin(sop_classes, "|")));
  }
  if (own_results) parts.push_back("own_results");
  if (parts.empty()) return "every series";
  return absl::StrJoin(parts, ", ");
}

const Rule* RuleSet::FirstMatch(const SeriesFacts& facts) const {
  for (const Rule& rule : rules) {
    // Fill rules are for segmentations only, and segmentations for fill
    // rules only: a SEG is never thresholded, a CT never read as labels.
    if (rule.job.has_fill() != facts.segmentation) continue;
    if (!rule.match.Matches(facts)) continue;
    if (rule.exclude && rule.exclude->CriteriaFailure(facts).empty()) continue;
    return &rule;
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
      if (why.empty() && rule.exclude &&
          rule.exclude->CriteriaFailure(facts).empty()) {
        why = absl::StrCat("excluded by exclude: ", rule.exclude->Describe());
      }
      if (why.empty()) why = "matches";
    }
    reasons.push_back(absl::StrCat("rule '", rule.name, "': ", why));
  }
  return absl::StrJoin(reasons, "; ");
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
    keys = CheckKeys(r, ctx, "",
                     {"name", "match", "exclude", "job", "fill", "send_to",
                      "complete_on_release", "complete_on_request"});
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
    absl::StatusOr<RuleMatch> match = ParseMatch(r["match"], ctx, "match");
    if (!match.ok()) return match.status();
    rule.match = *std::move(match);
    if (r["exclude"]) {
      absl::StatusOr<RuleMatch> exclude =
          ParseMatch(r["exclude"], ctx, "exclude");
      if (!exclude.ok()) return exclude.status();
      if (exclude->empty()) {
        return ctx.Error("exclude",
                         "no criterion: it would exclude every series");
      }
      rule.exclude = *std::move(exclude);
    }
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
    if (r["complete_on_request"]) {
      absl::StatusOr<bool> v =
          GetBool(r["complete_on_request"], ctx, "complete_on_request");
      if (!v.ok()) return v.status();
      rule.complete_on_request = *v;
    }
    set.rules.push_back(std::move(rule));
  }
  return set;
}

}  // namespace interslice::server::node

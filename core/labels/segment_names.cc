#include "core/labels/segment_names.h"

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <set>
#include <sstream>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "nlohmann/json.hpp"

namespace interslice {
namespace {

// "scheme^value^meaning" (DICOM's and Slicer's notation); an empty string
// or "^^" is no code.
absl::StatusOr<CodedConcept> ParseCode(absl::string_view text) {
  text = absl::StripAsciiWhitespace(text);
  CodedConcept code;
  if (text.empty() || text == "^^") return code;
  std::vector<std::string> parts = absl::StrSplit(text, '^');
  if (parts.size() != 3 || parts[0].empty() || parts[1].empty()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "code '", text,
        "' is not scheme^value^meaning (e.g. SCT^10200004^Liver)"));
  }
  code.scheme = parts[0];
  code.value = parts[1];
  code.meaning = parts[2].empty() ? parts[1] : parts[2];
  return code;
}

// Fills the codes DefaultLabelSegment gives where `segment` has none, and
// the default colour where it has none.
LabelSegment WithDefaults(LabelSegment segment) {
  const LabelSegment d = DefaultLabelSegment(segment.number);
  if (segment.label.empty()) segment.label = d.label;
  if (segment.category.value.empty()) segment.category = d.category;
  if (segment.type.value.empty()) segment.type = d.type;
  if (!segment.rgb.has_value() && !segment.cielab.has_value()) {
    segment.rgb = d.rgb;
    segment.cielab = d.cielab;
  }
  return segment;
}

absl::Status CheckLabelNumber(int64_t label, const std::string& where) {
  if (label < 1 || label > 65535) {
    return absl::InvalidArgumentError(
        absl::StrFormat("%s: label %d is outside 1..65535", where, label));
  }
  return absl::OkStatus();
}

absl::StatusOr<std::vector<LabelSegment>> ReadCsv(const std::string& path,
                                                  const std::string& name) {
  std::ifstream in(path);
  if (!in) {
    return absl::InvalidArgumentError(
        absl::StrCat("cannot read the label names ", name));
  }
  std::vector<LabelSegment> out;
  std::set<int> seen;
  std::string line;
  int line_number = 0;
  while (std::getline(in, line)) {
    ++line_number;
    absl::string_view text = absl::StripAsciiWhitespace(line);
    if (text.empty() || text[0] == '#') continue;
    const std::string where = absl::StrFormat("%s line %d", name, line_number);
    std::vector<std::string> fields = absl::StrSplit(text, ',');
    for (std::string& f : fields) {
      f = std::string(absl::StripAsciiWhitespace(f));
      if (f.size() >= 2 && f.front() == '"' && f.back() == '"') {
        f = f.substr(1, f.size() - 2);
      }
    }
    int64_t label = 0;
    if (!absl::SimpleAtoi(fields[0], &label)) {
      if (out.empty() && seen.empty() && line_number == 1) continue;  // header
      return absl::InvalidArgumentError(
          absl::StrCat(where, ": '", fields[0], "' is not a label number"));
    }
    if (absl::Status s = CheckLabelNumber(label, where); !s.ok()) return s;
    if (fields.size() != 2 && fields.size() != 5 && fields.size() != 6) {
      return absl::InvalidArgumentError(
          absl::StrCat(where, ": expected label,name[,R,G,B[,code]] (",
                       fields.size(), " fields)"));
    }
    if (!seen.insert(static_cast<int>(label)).second) {
      return absl::InvalidArgumentError(
          absl::StrFormat("%s: label %d is listed twice", where, label));
    }
    LabelSegment segment;
    segment.number = static_cast<int>(label);
    segment.label = fields[1];
    if (fields.size() >= 5) {
      std::array<uint8_t, 3> rgb;
      for (int c = 0; c < 3; ++c) {
        int v = -1;
        if (!absl::SimpleAtoi(fields[2 + c], &v) || v < 0 || v > 255) {
          return absl::InvalidArgumentError(
              absl::StrCat(where, ": colour component '", fields[2 + c],
                           "' is not an integer 0..255"));
        }
        rgb[c] = static_cast<uint8_t>(v);
      }
      segment.rgb = rgb;
    }
    if (fields.size() == 6) {
      absl::StatusOr<CodedConcept> code = ParseCode(fields[5]);
      if (!code.ok()) {
        return absl::InvalidArgumentError(
            absl::StrCat(where, ": ", code.status().message()));
      }
      segment.type = *code;
    }
    out.push_back(WithDefaults(std::move(segment)));
  }
  return out;
}

absl::StatusOr<CodedConcept> JsonCode(const nlohmann::json& j,
                                      const std::string& where) {
  CodedConcept code;
  if (j.is_string()) return ParseCode(j.get<std::string>());
  if (!j.is_object() || !j.contains("scheme") || !j.contains("value") ||
      !j["scheme"].is_string() || !j["value"].is_string()) {
    return absl::InvalidArgumentError(absl::StrCat(
        where, ": a code is {\"scheme\", \"value\", \"meaning\"}"));
  }
  code.scheme = j["scheme"].get<std::string>();
  code.value = j["value"].get<std::string>();
  code.meaning = j.value("meaning", code.value);
  return code;
}

absl::StatusOr<std::vector<LabelSegment>> ReadJson(const std::string& path,
                                                   const std::string& name) {
  std::ifstream in(path);
  if (!in) {
    return absl::InvalidArgumentError(
        absl::StrCat("cannot read the label names ", name));
  }
  nlohmann::json doc = nlohmann::json::parse(in, nullptr, false);
  if (doc.is_discarded()) {
    return absl::InvalidArgumentError(
        absl::StrCat("the label names ", name, " are not valid JSON"));
  }
  if (doc.is_object() && doc.contains("segments")) doc = doc["segments"];
  if (!doc.is_array()) {
    return absl::InvalidArgumentError(absl::StrCat(
        name, ": expected an array of {\"label\", \"name\", ...} objects"));
  }
  std::vector<LabelSegment> out;
  std::set<int> seen;
  for (size_t n = 0; n < doc.size(); ++n) {
    const nlohmann::json& e = doc[n];
    const std::string where = absl::StrFormat("%s entry %d", name, n + 1);
    if (!e.is_object() || !e.contains("label") ||
        !e["label"].is_number_integer()) {
      return absl::InvalidArgumentError(
          absl::StrCat(where, ": no integer \"label\""));
    }
    const int64_t label = e["label"].get<int64_t>();
    if (absl::Status s = CheckLabelNumber(label, where); !s.ok()) return s;
    if (!seen.insert(static_cast<int>(label)).second) {
      return absl::InvalidArgumentError(
          absl::StrFormat("%s: label %d is listed twice", where, label));
    }
    LabelSegment segment;
    segment.number = static_cast<int>(label);
    if (e.contains("name")) {
      if (!e["name"].is_string()) {
        return absl::InvalidArgumentError(
            absl::StrCat(where, ": \"name\" is not a string"));
      }
      segment.label = e["name"].get<std::string>();
    }
    if (e.contains("rgb")) {
      const nlohmann::json& c = e["rgb"];
      std::array<uint8_t, 3> rgb;
      bool ok = c.is_array() && c.size() == 3;
      for (size_t k = 0; ok && k < 3; ++k) {
        ok = c[k].is_number_integer() && c[k].get<int>() >= 0 &&
             c[k].get<int>() <= 255;
        if (ok) rgb[k] = static_cast<uint8_t>(c[k].get<int>());
      }
      if (!ok) {
        return absl::InvalidArgumentError(
            absl::StrCat(where, ": \"rgb\" is not three integers 0..255"));
      }
      segment.rgb = rgb;
    }
    for (const char* field : {"type", "category"}) {
      if (!e.contains(field)) continue;
      absl::StatusOr<CodedConcept> code = JsonCode(e[field], where);
      if (!code.ok()) {
        return absl::InvalidArgumentError(
            absl::StrCat(where, ": ", code.status().message()));
      }
      (std::string(field) == "type" ? segment.type : segment.category) = *code;
    }
    out.push_back(WithDefaults(std::move(segment)));
  }
  return out;
}

}  // namespace

absl::StatusOr<std::vector<LabelSegment>> SegmentsFromSlicerFields(
    const std::vector<std::pair<std::string, std::string>>& key_values) {
  // Segment index -> its fields.
  std::map<int, std::map<std::string, std::string>> by_segment;
  for (const auto& [key, value] : key_values) {
    absl::string_view rest = key;
    if (!absl::ConsumePrefix(&rest, "Segment")) continue;
    const size_t underscore = rest.find('_');
    int index = -1;
    if (underscore == absl::string_view::npos ||
        !absl::SimpleAtoi(rest.substr(0, underscore), &index) || index < 0) {
      continue;
    }
    by_segment[index][std::string(rest.substr(underscore + 1))] = value;
  }
  std::vector<LabelSegment> out;
  std::set<int> seen;
  for (const auto& [index, fields] : by_segment) {
    const std::string where = absl::StrFormat("Slicer segment %d", index);
    if (auto layer = fields.find("Layer"); layer != fields.end()) {
      int value = 0;
      if (absl::SimpleAtoi(layer->second, &value) && value > 0) {
        return absl::InvalidArgumentError(
            "the segmentation's segments overlap (Slicer stored them in "
            "several layers); a label map needs one segment per voxel");
      }
    }
    int64_t label = index + 1;
    if (auto v = fields.find("LabelValue"); v != fields.end()) {
      if (!absl::SimpleAtoi(v->second, &label)) {
        return absl::InvalidArgumentError(absl::StrCat(
            where, ": LabelValue '", v->second, "' is not an integer"));
      }
    }
    if (absl::Status s = CheckLabelNumber(label, where); !s.ok()) return s;
    if (!seen.insert(static_cast<int>(label)).second) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s: label %d is used by two segments", where, label));
    }
    LabelSegment segment;
    segment.number = static_cast<int>(label);
    if (auto v = fields.find("Name"); v != fields.end()) {
      segment.label = v->second;
    }
    if (auto v = fields.find("Color"); v != fields.end()) {
      std::vector<std::string> parts =
          absl::StrSplit(v->second, ' ', absl::SkipEmpty());
      std::array<uint8_t, 3> rgb;
      bool ok = parts.size() == 3;
      for (size_t c = 0; ok && c < 3; ++c) {
        double x = -1;
        ok = absl::SimpleAtod(parts[c], &x) && x >= 0 && x <= 1;
        if (ok) rgb[c] = static_cast<uint8_t>(std::lround(x * 255));
      }
      if (!ok) {
        return absl::InvalidArgumentError(absl::StrCat(
            where, ": Color '", v->second, "' is not three numbers 0..1"));
      }
      segment.rgb = rgb;
    }
    if (auto v = fields.find("Terminology"); v != fields.end()) {
      // context~category~type~type modifier~...
      std::vector<std::string> parts = absl::StrSplit(v->second, '~');
      if (parts.size() >= 3) {
        absl::StatusOr<CodedConcept> category = ParseCode(parts[1]);
        absl::StatusOr<CodedConcept> type = ParseCode(parts[2]);
        if (!category.ok() || !type.ok()) {
          return absl::InvalidArgumentError(absl::StrCat(
              where, ": Terminology: ",
              (!category.ok() ? category.status() : type.status()).message()));
        }
        segment.category = *category;
        segment.type = *type;
      }
    }
    out.push_back(WithDefaults(std::move(segment)));
  }
  return out;
}

absl::StatusOr<std::vector<LabelSegment>> ReadSegmentNames(
    const std::string& path) {
  const std::string name = std::filesystem::path(path).filename().string();
  const std::string lower = absl::AsciiStrToLower(name);
  if (absl::EndsWith(lower, ".csv") || absl::EndsWith(lower, ".txt")) {
    return ReadCsv(path, name);
  }
  if (absl::EndsWith(lower, ".json")) return ReadJson(path, name);
  return absl::InvalidArgumentError(absl::StrCat(
      "the label names ", name,
      ": unknown format (expected .csv, .txt or .json; a .seg.nrrd label map "
      "names its segments itself)"));
}

absl::Status CheckSegmentsAgainstLabels(
    const std::vector<LabelSegment>& segments, const std::vector<int>& present,
    const std::string& what) {
  for (const LabelSegment& s : segments) {
    if (!std::binary_search(present.begin(), present.end(), s.number)) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s name label %d, which the label map does not hold (labels: %s)",
          what, s.number, absl::StrJoin(present, ", ")));
    }
  }
  return absl::OkStatus();
}

}  // namespace interslice

#include "server/node/peer.h"

#include <cctype>

#include "absl/strings/str_cat.h"

namespace interslice::server::node {
namespace {

// A key value: one value (no backslash: that would be a value list), no
// control characters, within its VR's length (PS3.5 table 6.2-1).
absl::Status CheckKey(const char* name, const std::string& value,
                      size_t max_length) {
  if (value.size() > max_length) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": longer than ", max_length, " characters"));
  }
  for (const char c : value) {
    if (c == '\\') {
      return absl::InvalidArgumentError(
          absl::StrCat(name, ": a single value is expected (no backslash)"));
    }
    if (std::iscntrl(static_cast<unsigned char>(c))) {
      return absl::InvalidArgumentError(
          absl::StrCat(name, ": control characters are not allowed"));
    }
  }
  return absl::OkStatus();
}

bool IsDate(const std::string& s) {
  if (s.size() != 8) return false;
  for (const char c : s) {
    if (!std::isdigit(static_cast<unsigned char>(c))) return false;
  }
  return true;
}

}  // namespace

std::string PeerLabel(const DicomPeer& peer) {
  if (peer.type == PeerType::kDicomWeb) {
    // The URL holds no credentials (the peers file refuses them).
    return absl::StrCat("peer ", peer.name, " (", peer.web.url, ")");
  }
  return absl::StrCat("peer ", peer.name, " (", peer.ae_title, "@", peer.host,
                      ":", peer.port, ")");
}

absl::Status CheckFindQuery(const FindQuery& query) {
  // LO 64, SH 16, CS 16 (PS3.5 table 6.2-1).
  if (absl::Status s = CheckKey("patient_id", query.patient_id, 64); !s.ok()) {
    return s;
  }
  if (absl::Status s = CheckKey("accession_number", query.accession_number, 16);
      !s.ok()) {
    return s;
  }
  if (absl::Status s = CheckKey("modality", query.modality, 16); !s.ok()) {
    return s;
  }
  for (const char c : query.modality) {
    if (!std::isupper(static_cast<unsigned char>(c)) &&
        !std::isdigit(static_cast<unsigned char>(c)) && c != '_') {
      return absl::InvalidArgumentError(
          "modality: upper-case letters, digits and _ only (CT, MR)");
    }
  }
  const std::string& date = query.study_date;
  if (!date.empty()) {
    const size_t dash = date.find('-');
    const bool ok =
        dash == std::string::npos
            ? IsDate(date)
            : date.size() > 1 &&
                  date.find('-', dash + 1) == std::string::npos &&
                  (dash == 0 || IsDate(date.substr(0, dash))) &&
                  (dash + 1 == date.size() || IsDate(date.substr(dash + 1)));
    if (!ok) {
      return absl::InvalidArgumentError(
          "study_date: expected YYYYMMDD or a range YYYYMMDD-YYYYMMDD (either "
          "end may be left out)");
    }
  }
  return absl::OkStatus();
}

}  // namespace interslice::server::node

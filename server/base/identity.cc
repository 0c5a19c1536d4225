#include "server/base/identity.h"

#include <set>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"

namespace interslice::server {
namespace {

bool IsValidName(std::string_view name) {
  if (name.empty() || name.size() > 64) return false;
  for (char c : name) {
    if (!(absl::ascii_isalnum(static_cast<unsigned char>(c)) || c == '.' ||
          c == '_' || c == '-' || c == '@')) {
      return false;
    }
  }
  return true;
}

bool IsValidToken(std::string_view token) {
  if (token.empty()) return false;
  for (char c : token) {
    const auto u = static_cast<unsigned char>(c);
    if (u <= 0x20 || u == 0x7f) return false;
  }
  return true;
}

// Constant time in the contents (not the lengths) of the strings.
bool SameSecret(std::string_view a, std::string_view b) {
  unsigned char diff = a.size() == b.size() ? 0 : 1;
  for (size_t i = 0; i < a.size() && i < b.size(); ++i) {
    diff |= static_cast<unsigned char>(a[i] ^ b[i]);
  }
  return diff == 0;
}

}  // namespace

absl::StatusOr<std::vector<NamedToken>> ParseTokenFile(std::string_view text) {
  // Debian's abseil has its own string_view: split and strip with it.
  const absl::string_view all(text.data(), text.size());
  std::vector<absl::string_view> lines;
  for (absl::string_view line : absl::StrSplit(all, '\n')) {
    line = absl::StripAsciiWhitespace(line);
    if (line.empty() || line.front() == '#') continue;
    lines.push_back(line);
  }
  if (lines.empty()) {
    return absl::InvalidArgumentError("the token file holds no token");
  }
  std::vector<NamedToken> tokens;
  // The original format: the file is the token.
  if (lines.size() == 1 && lines[0].find(':') == absl::string_view::npos) {
    if (!IsValidToken(std::string_view(lines[0].data(), lines[0].size()))) {
      return absl::InvalidArgumentError(
          "the token file's token must not contain whitespace");
    }
    tokens.push_back({"default", std::string(lines[0])});
    return tokens;
  }
  std::set<std::string> names, secrets;
  int number = 0;
  for (absl::string_view line : absl::StrSplit(all, '\n')) {
    ++number;
    line = absl::StripAsciiWhitespace(line);
    if (line.empty() || line.front() == '#') continue;
    const size_t colon = line.find(':');
    if (colon == absl::string_view::npos) {
      return absl::InvalidArgumentError(
          absl::StrCat("token file line ", number, ": expected NAME:TOKEN"));
    }
    const std::string name(absl::StripAsciiWhitespace(line.substr(0, colon)));
    const std::string token(absl::StripAsciiWhitespace(line.substr(colon + 1)));
    if (!IsValidName(name) || !IsValidToken(token)) {
      return absl::InvalidArgumentError(absl::StrCat(
          "token file line ", number,
          ": expected NAME:TOKEN (NAME: 1 to 64 letters, digits, '.', '_', "
          "'-', '@'; TOKEN: no whitespace)"));
    }
    if (!names.insert(name).second) {
      return absl::InvalidArgumentError(absl::StrCat(
          "token file line ", number, ": the name ", name, " is used twice"));
    }
    if (!secrets.insert(token).second) {
      return absl::InvalidArgumentError(absl::StrCat(
          "token file line ", number, ": the same token is given twice"));
    }
    tokens.push_back({name, token});
  }
  return tokens;
}

std::optional<std::string> Authenticator::MatchBearer(
    std::string_view authorization) const {
  constexpr std::string_view kPrefix = "Bearer ";
  const bool prefixed = authorization.substr(0, kPrefix.size()) == kPrefix;
  const std::string_view presented =
      prefixed ? authorization.substr(kPrefix.size()) : std::string_view();
  // Every token is compared, whatever matches: the time taken does not
  // depend on which token (if any) was presented.
  const std::string* match = nullptr;
  for (const NamedToken& t : tokens_) {
    if (SameSecret(presented, t.token) && prefixed) match = &t.name;
  }
  if (match == nullptr) return std::nullopt;
  return *match;
}

}  // namespace interslice::server

// Who is calling: bearer tokens with names (--auth-token-file), the subject
// of a verified client certificate (mutual TLS), and admin identities
// (--admin-identity). Jobs belong to the identity that submitted them. The
// same tokens and identities serve every door (gRPC: net/grpc/auth.h; the
// HTTP listener: net/http/status_page.cc).
#ifndef INTERSLICE_SERVER_BASE_IDENTITY_H_
#define INTERSLICE_SERVER_BASE_IDENTITY_H_

#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"

namespace interslice::server {

struct NamedToken {
  std::string name;
  std::string token;
};

// A token file: either one token alone (the original format; its name is
// "default"), or one "name:token" per line, with blank lines and lines
// starting with '#' ignored. Names are 1-64 of [A-Za-z0-9._@-]; tokens are
// non-empty without whitespace; names and tokens must be unique.
// INVALID_ARGUMENT naming the line (never quoting a token).
absl::StatusOr<std::vector<NamedToken>> ParseTokenFile(std::string_view text);

struct Caller {
  // Token name, or the client certificate's subject ("CN=...,O=..."), or ""
  // when the server authenticates nobody.
  std::string identity;
  bool admin = false;
};

class Authenticator {
 public:
  Authenticator(std::vector<NamedToken> tokens,
                std::vector<std::string> admin_identities)
      : tokens_(std::move(tokens)),
        admins_(admin_identities.begin(), admin_identities.end()) {}

  bool tokens_required() const { return !tokens_.empty(); }

  // Whether `identity` is one of the admin identities.
  bool IsAdmin(std::string_view identity) const {
    return !identity.empty() && admins_.count(identity) > 0;
  }

  // The caller who presented `identity` (a token's name or a certificate's
  // subject; "" for nobody).
  Caller CallerOf(std::string identity) const {
    Caller caller;
    caller.admin = IsAdmin(identity);
    caller.identity = std::move(identity);
    return caller;
  }

  // The name of the token in an "authorization" metadata value ("Bearer
  // <token>"), compared in constant time against every token; nullopt if
  // none matches.
  std::optional<std::string> MatchBearer(std::string_view authorization) const;

  // Whether `caller` may see and act on a job owned by `owner`. A server
  // that authenticates nobody (identity "") has one anonymous user, who sees
  // every job, including those its DICOM listener made (owner "dicom").
  static bool MayAccess(const Caller& caller, const std::string& owner) {
    return caller.admin || caller.identity == owner || caller.identity.empty();
  }

 private:
  std::vector<NamedToken> tokens_;
  std::set<std::string, std::less<>> admins_;
};

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_BASE_IDENTITY_H_

// The peers file (server/node/config.h has its format).
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

// A PACS serves each association with a thread or a process of its own;
// beyond a handful the gain is nil and a small PACS may refuse us.
constexpr int kMaxAssociationsPerPeer = 16;

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

namespace {

// The peer's `type`: dimse (the default) or dicomweb.
absl::StatusOr<PeerType> ParsePeerType(const YAML::Node& p,
                                       const Context& ctx) {
  if (!p["type"]) return PeerType::kDimse;
  absl::StatusOr<std::string> type = GetString(p["type"], ctx, "type");
  if (!type.ok()) return type.status();
  const std::string lower =
      absl::AsciiStrToLower(absl::StripAsciiWhitespace(*type));
  if (lower == "dicomweb") return PeerType::kDicomWeb;
  if (lower == "dimse") return PeerType::kDimse;
  return ctx.Error("type", absl::StrCat("'", *type,
                                        "': expected dimse (the "
                                        "default) or dicomweb"));
}

// The keys a peer of its type may have; keys of the other kind of peer are
// errors that say so (a DICOMweb peer with an ae_title was most likely
// meant as a DIMSE one).
absl::Status CheckPeerKeys(const YAML::Node& p, const Context& ctx, bool web) {
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
  return CheckKeys(p, ctx, "", known);
}

// A DIMSE peer's address and policy: AE title, host, port, tls, retrieve,
// allowed_sources.
absl::Status ParseDimsePeer(const YAML::Node& p, const Context& ctx,
                            DicomPeer& peer) {
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
    absl::StatusOr<std::string> how = GetString(p["retrieve"], ctx, "retrieve");
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
  return absl::OkStatus();
}

// One entry of `peers`; `names` holds the names taken before it.
absl::StatusOr<DicomPeer> ParsePeer(const YAML::Node& p, const Context& ctx,
                                    std::set<std::string>& names) {
  if (!p.IsMap()) {
    return ctx.Error("", absl::StrCat("expected a mapping, got ", KindName(p)));
  }
  DicomPeer peer;
  absl::StatusOr<PeerType> type = ParsePeerType(p, ctx);
  if (!type.ok()) return type.status();
  peer.type = *type;
  const bool web = peer.type == PeerType::kDicomWeb;
  if (absl::Status keys = CheckPeerKeys(p, ctx, web); !keys.ok()) return keys;
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
    return peer;
  }
  if (absl::Status s = ParseDimsePeer(p, ctx, peer); !s.ok()) return s;
  return peer;
}

}  // namespace

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
    absl::StatusOr<DicomPeer> peer = ParsePeer(p, Context(path, entry), names);
    if (!peer.ok()) return peer.status();
    config.peers.push_back(*std::move(peer));
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

}  // namespace interslice::server::node

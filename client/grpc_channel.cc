#include "client/grpc_channel.h"

#include <algorithm>
#include <fstream>
#include <random>
#include <sstream>
#include <vector>

#include "CLI/CLI.hpp"
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"

namespace interslice::client {
namespace {

// How long one connection attempt may take (see Connection::Open).
constexpr int kMinConnectTimeoutMs = 5000;

absl::StatusOr<std::string> ReadFile(const std::string& path,
                                     const std::string& option) {
  std::ifstream in(path, std::ios::binary);
  if (!in) {
    return absl::NotFoundError(absl::StrCat(option, ": cannot read ", path));
  }
  std::stringstream buffer;
  buffer << in.rdbuf();
  return buffer.str();
}

// A static address list ("ipv4:A:P,B:P,...") in random order. round_robin
// sends a channel's first call to the first address that connects, which is
// nearly always the first of the list; the CLI makes a channel per command,
// so without this every `submit` of a script would land on one replica.
// (DNS servers rotate the answers of dns:/// targets themselves.)
std::string ShuffleStaticList(const std::string& target) {
  const size_t colon = target.find(':');
  if (colon == std::string::npos) return target;
  const std::string scheme = target.substr(0, colon);
  if (scheme != "ipv4" && scheme != "ipv6") return target;
  std::vector<std::string> addresses =
      absl::StrSplit(target.substr(colon + 1), ',');
  if (addresses.size() < 2) return target;
  std::shuffle(addresses.begin(), addresses.end(),
               std::mt19937_64(std::random_device{}()));
  return absl::StrCat(scheme, ":", absl::StrJoin(addresses, ","));
}

}  // namespace

void AddConnectionOptions(CLI::App& app, ConnectionOptions& options) {
  app.add_option("--server", options.server,
                 "Server: HOST:PORT, or any gRPC target such as "
                 "ipv4:10.0.0.1:50051,10.0.0.2:50051 or dns:///NAME:PORT; "
                 "calls are balanced round-robin over its addresses")
      ->capture_default_str();
  app.add_option("--tls-ca", options.tls_ca,
                 "Use TLS, trusting this CA certificate (PEM)");
  app.add_option("--tls-cert", options.tls_cert,
                 "Client certificate for mutual TLS (PEM)");
  app.add_option("--tls-key", options.tls_key,
                 "Private key of the client certificate (PEM)");
  app.add_option("--token-file", options.token_file,
                 "Send the bearer token in this file");
}

absl::StatusOr<Connection> Connection::Open(const ConnectionOptions& options) {
  Connection c;
  c.address_ = options.server;
  std::shared_ptr<grpc::ChannelCredentials> credentials;
  if (!options.tls_ca.empty() || !options.tls_cert.empty()) {
    grpc::SslCredentialsOptions ssl;
    if (!options.tls_ca.empty()) {
      absl::StatusOr<std::string> ca = ReadFile(options.tls_ca, "--tls-ca");
      if (!ca.ok()) return ca.status();
      ssl.pem_root_certs = *ca;
    }
    if (!options.tls_cert.empty() || !options.tls_key.empty()) {
      absl::StatusOr<std::string> cert =
          ReadFile(options.tls_cert, "--tls-cert");
      if (!cert.ok()) return cert.status();
      absl::StatusOr<std::string> key = ReadFile(options.tls_key, "--tls-key");
      if (!key.ok()) return key.status();
      ssl.pem_cert_chain = *cert;
      ssl.pem_private_key = *key;
    }
    credentials = grpc::SslCredentials(ssl);
  } else {
    credentials = grpc::InsecureChannelCredentials();
  }
  if (!options.token_file.empty()) {
    absl::StatusOr<std::string> token =
        ReadFile(options.token_file, "--token-file");
    if (!token.ok()) return token.status();
    c.token_ = std::string(absl::StripAsciiWhitespace(*token));
  }
  grpc::ChannelArguments args;
  // Fail fast rather than retrying a dead address for the whole deadline.
  args.SetInt(GRPC_ARG_ENABLE_RETRIES, 0);
  // Replicas answer for each other's jobs (server/net/grpc/forwarding.h), so
  // every call may go to any address of the target: spread them, and skip the
  // addresses that are down.
  args.SetLoadBalancingPolicyName("round_robin");
  // A replica that restarts is used again within a second or so.
  // GRPC_ARG_MIN_RECONNECT_BACKOFF_MS is what gRPC gives one connection
  // attempt (TCP, TLS, the server's HTTP/2 SETTINGS; default 20 s): at 200
  // ms a server whose first answer was slower (TLS over a WAN, a loaded
  // host) was reported unreachable; 5 s still gives up on an address that
  // silently went away (a rescheduled pod) soon enough to try the next.
  args.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, 200);
  args.SetInt(GRPC_ARG_MIN_RECONNECT_BACKOFF_MS, kMinConnectTimeoutMs);
  args.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, 1000);
  c.channel_ = grpc::CreateCustomChannel(ShuffleStaticList(options.server),
                                         credentials, args);
  return c;
}

void Connection::Authorize(grpc::ClientContext& context) const {
  if (!token_.empty()) {
    context.AddMetadata("authorization", "Bearer " + token_);
  }
}

std::string DescribeRpcError(const grpc::Status& status,
                             const std::string& address) {
  const std::string message = status.error_message();
  switch (status.error_code()) {
    case grpc::UNAVAILABLE:
      // The server's own refusal while it drains (its messages say so), not
      // a transport failure: retrying on another replica helps.
      // A replica forwarding to the job's owner, which is down.
      if (message.find("that holds this job is unavailable") !=
          std::string::npos) {
        return message;
      }
      if (message.find("shutting down") != std::string::npos) {
        return absl::StrCat("the server at ", address,
                            " is unavailable: ", message);
      }
      return absl::StrCat("cannot reach the server at ", address, " (", message,
                          ")");
    case grpc::DEADLINE_EXCEEDED:
      // The server's upload time limits, not the client's deadline.
      if (message.rfind("upload ", 0) == 0) {
        return absl::StrCat("the server ended the upload: ", message);
      }
      return "the deadline expired before the job finished";
    case grpc::UNAUTHENTICATED:
      return absl::StrCat("the server refused the credentials (", message, ")");
    case grpc::RESOURCE_EXHAUSTED:
      return absl::StrCat("the server refused the job: ", message);
    case grpc::CANCELLED:
      return absl::StrCat(
          "the job was cancelled",
          message.empty() ? "" : absl::StrCat(" (", message, ")"));
    default:
      return message.empty()
                 ? absl::StrCat("call failed with status code ",
                                static_cast<int>(status.error_code()))
                 : message;
  }
}

}  // namespace interslice::client

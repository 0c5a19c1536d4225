// Connection options shared by the commands that talk to a server, and the
// client's one-line rendering of gRPC errors.
#ifndef INTERSLICE_CLIENT_GRPC_CHANNEL_H_
#define INTERSLICE_CLIENT_GRPC_CHANNEL_H_

#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "grpcpp/grpcpp.h"

namespace CLI {
class App;
}  // namespace CLI

namespace interslice::client {

struct ConnectionOptions {
  // HOST:PORT or any gRPC target (ipv4:A:P,B:P; dns:///NAME:PORT), balanced
  // round-robin.
  std::string server = "localhost:50051";
  std::string tls_ca;      // PEM; with it (or a client cert) the call uses TLS
  std::string tls_cert;    // client certificate (mutual TLS)
  std::string tls_key;     // its private key
  std::string token_file;  // bearer token sent as "authorization" metadata
};

void AddConnectionOptions(CLI::App& app, ConnectionOptions& options);

class Connection {
 public:
  static absl::StatusOr<Connection> Open(const ConnectionOptions& options);
  const std::shared_ptr<grpc::Channel>& channel() const { return channel_; }
  // Adds the bearer token (if any) to a call.
  void Authorize(grpc::ClientContext& context) const;
  const std::string& address() const { return address_; }

 private:
  std::shared_ptr<grpc::Channel> channel_;
  std::string token_;
  std::string address_;
};

// "cannot reach the server at ...", "the deadline expired ...", ... : one
// line for the user, by status code.
std::string DescribeRpcError(const grpc::Status& status,
                             const std::string& address);

}  // namespace interslice::client

#endif  // INTERSLICE_CLIENT_GRPC_CHANNEL_H_

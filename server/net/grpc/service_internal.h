// Shared by the files that implement InterSliceService (service.h): service.cc
// and one service_*.cc per group of RPCs. Not for use outside them.
//
// The build compiles several .cc files of a library as one translation unit
// (unity builds), so what these files share lives here, in a namespace of
// its own, rather than in one anonymous namespace per file.
#ifndef INTERSLICE_SERVER_NET_GRPC_SERVICE_INTERNAL_H_
#define INTERSLICE_SERVER_NET_GRPC_SERVICE_INTERNAL_H_

#include <cstdint>
#include <fstream>
#include <string>
#include <utility>

#include "absl/status/statusor.h"
#include "interslice/v1/interslice.grpc.pb.h"

namespace interslice::server::service_internal {

inline constexpr int kDefaultChunkBytes = 64 * 1024;

// Reactors that only report an error (authentication, bad request).
template <typename Request>
class ErrorReadReactor : public grpc::ServerReadReactor<Request> {
 public:
  explicit ErrorReadReactor(const grpc::Status& status) {
    this->Finish(status);
  }
  void OnDone() override { delete this; }
};

template <typename Response>
class ErrorWriteReactor : public grpc::ServerWriteReactor<Response> {
 public:
  explicit ErrorWriteReactor(const grpc::Status& status) {
    this->Finish(status);
  }
  void OnDone() override { delete this; }
};

template <typename Request, typename Response>
class ErrorBidiReactor : public grpc::ServerBidiReactor<Request, Response> {
 public:
  explicit ErrorBidiReactor(const grpc::Status& status) {
    this->Finish(status);
  }
  void OnDone() override { delete this; }
};

// Reads one artifact chunk by chunk (on the I/O executor).
class ArtifactReader {
 public:
  ArtifactReader(std::string path, v1::ArtifactInfo info, int64_t offset,
                 int chunk_bytes)
      : path_(std::move(path)),
        info_(std::move(info)),
        offset_(offset),
        chunk_bytes_(chunk_bytes) {}

  // Fills `chunk` with the next piece; false at the end. Blocking.
  absl::StatusOr<bool> Next(v1::ArtifactChunk* chunk);

 private:
  const std::string path_;
  const v1::ArtifactInfo info_;
  int64_t offset_;
  const int chunk_bytes_;
  std::ifstream in_;
  bool opened_ = false;
  bool first_ = true;
};

}  // namespace interslice::server::service_internal

#endif  // INTERSLICE_SERVER_NET_GRPC_SERVICE_INTERNAL_H_

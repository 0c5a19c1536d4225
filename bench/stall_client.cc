// A hostile client for bench/load_fault.sh: opens N Submit streams that send
// the header of a real job and then stall (nothing more), or trickle (64 KiB
// every few seconds), for a while, and reports how each stream ended. It is
// what an attacker or a broken network does to a server's upload slots.
//
//   interslice_stall_client --server HOST:PORT --streams N --seconds S
//       [--trickle-seconds T]
//
// Prints one line per stream: "stream i: <grpc status code> <message>" and
// exits 0. Loopback only in the project's scripts.
#include <chrono>
#include <cstdio>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "CLI/CLI.hpp"
#include "grpcpp/grpcpp.h"
#include "interslice/v1/interslice.grpc.pb.h"

namespace {

using interslice::v1::InterSlice;
using interslice::v1::SubmitResponse;
using interslice::v1::UploadRequest;

struct Stream {
  grpc::ClientContext context;
  SubmitResponse response;
  std::unique_ptr<grpc::ClientWriter<UploadRequest>> writer;
};

}  // namespace

int main(int argc, char** argv) {
  std::string server = "127.0.0.1:50051";
  int streams = 16;
  double seconds = 60;
  double trickle_seconds = 0;
  CLI::App app{"interslice_stall_client: uploads that stall (a load test)"};
  app.add_option("--server", server)->capture_default_str();
  app.add_option("--streams", streams)->capture_default_str();
  app.add_option("--seconds", seconds, "How long each stream stays open")
      ->capture_default_str();
  app.add_option("--trickle-seconds", trickle_seconds,
                 "Send 64 KiB every this many seconds (0: send nothing)")
      ->capture_default_str();
  CLI11_PARSE(app, argc, argv);

  auto channel =
      grpc::CreateChannel(server, grpc::InsecureChannelCredentials());
  auto stub = InterSlice::NewStub(channel);
  std::vector<std::unique_ptr<Stream>> open;
  for (int i = 0; i < streams; ++i) {
    auto s = std::make_unique<Stream>();
    s->context.set_deadline(
        std::chrono::system_clock::now() +
        std::chrono::milliseconds(static_cast<int64_t>(seconds * 1000) + 5000));
    s->writer = stub->Submit(&s->context, &s->response);
    UploadRequest header;
    header.mutable_header()->mutable_spec()->set_threshold(300);
    header.mutable_header()->set_file_count(1);
    header.mutable_header()->set_total_bytes(int64_t{1} << 20);
    s->writer->Write(header);
    open.push_back(std::move(s));
  }
  const auto end =
      std::chrono::steady_clock::now() +
      std::chrono::milliseconds(static_cast<int64_t>(seconds * 1000));
  int64_t offset = 0;
  const std::string data(64 * 1024, '\0');
  bool first = true;
  while (std::chrono::steady_clock::now() < end) {
    if (trickle_seconds > 0) {
      for (auto& s : open) {
        UploadRequest chunk;
        chunk.mutable_chunk()->set_file_index(0);
        if (first) {
          chunk.mutable_chunk()->set_file_name("slow.dcm");
          chunk.mutable_chunk()->set_file_size(int64_t{1} << 20);
          chunk.mutable_chunk()->set_sha256(std::string(32, '\0'));
        }
        chunk.mutable_chunk()->set_offset(offset);
        chunk.mutable_chunk()->set_data(data);
        s->writer->Write(chunk);
      }
      first = false;
      offset += static_cast<int64_t>(data.size());
      std::this_thread::sleep_for(std::chrono::milliseconds(
          static_cast<int64_t>(trickle_seconds * 1000)));
    } else {
      std::this_thread::sleep_for(std::chrono::milliseconds(200));
    }
  }
  for (size_t i = 0; i < open.size(); ++i) {
    open[i]->writer->WritesDone();
    const grpc::Status status = open[i]->writer->Finish();
    std::printf("stream %zu: %d %s\n", i, static_cast<int>(status.error_code()),
                status.error_message().c_str());
  }
  return 0;
}

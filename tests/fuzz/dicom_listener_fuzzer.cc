// libFuzzer target for the DICOM listener's receive path (issue 22): what a
// peer sends, through the code that reads it in the server process.
//
// Input: one mode byte, then
//  - mode even: the bytes a peer sends on a connection. They go through a
//    socket pair into AssociationRunner::Serve, exactly as an accepted
//    connection does (the PduGuard on every byte, DCMTK's association and
//    DIMSE handling, the C-STORE path to the spool: the bounded data-set
//    scan, DCMTK's header parse, the series assembly), with a peers file
//    that accepts any caller and the AE title INTERSLICE. The connection is
//    closed after the input, so every association ends there;
//  - mode odd: a data set; the next byte picks its transfer syntax
//    (implicit VR LE, explicit VR LE, explicit VR BE, deflated explicit VR
//    LE). It is wrapped in a Part 10 file as the listener writes one and
//    handed to SeriesAssembler::AddInstance (scan, DCMTK parse, UIDs), then
//    the rules' facts are read from its series folder (ReadSeriesFacts).
// A fresh spool folder per input. Checks, beyond "no crash, no hang, no
// unbounded allocation": an instance taken into a series passed the scan
// with its limits (depth, elements).
#include <sys/socket.h>
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>
#include <thread>

#include "core/dicom/series_reader.h"
#include "server/net/dimse/association.h"
#include "server/net/dimse/connection_gate.h"
#include "server/node/dataset_scan.h"
#include "server/node/series_assembler.h"
#include "spdlog/spdlog.h"

namespace {

namespace fs = std::filesystem;
using namespace interslice::server::dimse;
using namespace interslice::server::node;

void Check(bool condition) {
  if (!condition) __builtin_trap();
}

const char* const kSyntaxes[] = {"1.2.840.10008.1.2", "1.2.840.10008.1.2.1",
                                 "1.2.840.10008.1.2.2",
                                 "1.2.840.10008.1.2.1.99"};

// A Part 10 file: preamble, DICM, a meta group naming `syntax` (explicit VR
// little endian, as DCMTK writes it), then `dataset` as it came.
std::string Part10(const std::string& syntax, const uint8_t* dataset,
                   size_t size) {
  std::string uid = syntax;
  if (uid.size() % 2 != 0) uid.push_back('\0');
  std::string element = std::string("\x02\x00\x10\x00UI", 6);
  element.push_back(static_cast<char>(uid.size()));
  element.push_back(0);
  element += uid;
  std::string length = std::string("\x02\x00\x00\x00UL\x04\x00", 8);
  const uint32_t n = static_cast<uint32_t>(element.size());
  for (int i = 0; i < 4; ++i) length.push_back(static_cast<char>(n >> (8 * i)));
  return std::string(128, '\0') + "DICM" + length + element +
         std::string(reinterpret_cast<const char*>(dataset), size);
}

struct Spool {
  Spool() {
    root = fs::temp_directory_path() /
           ("interslice-listener-fuzz-" + std::to_string(::getpid()));
    fs::remove_all(root);
  }
  ~Spool() { fs::remove_all(root); }
  std::unique_ptr<SeriesAssembler> Open() {
    AssemblerOptions options;
    options.root = (root / "dicom-in").string();
    options.max_bytes_per_series = 64 << 20;
    RuleSet rules;
    rules.path = "(fuzz)";
    absl::StatusOr<std::unique_ptr<SeriesAssembler>> a = SeriesAssembler::Open(
        options, rules, nullptr, nullptr,
        [](const interslice::v1::JobSpec&, const std::string&,
           const std::string&,
           const std::string&) -> absl::StatusOr<std::string> {
          return absl::UnavailableError("no jobs in the fuzzer");
        });
    Check(a.ok());
    return *std::move(a);
  }
  fs::path root;
};

void FuzzDataset(const uint8_t* data, size_t size) {
  if (size < 1) return;
  const std::string syntax = kSyntaxes[data[0] % 4];
  Spool spool;
  std::unique_ptr<SeriesAssembler> assembler = spool.Open();
  const uint64_t id =
      assembler->BeginTransfer(Door::kAssociation, "FUZZ", "INTERSLICE");
  const std::string staged = assembler->StagingPath();
  {
    std::ofstream out(staged, std::ios::binary);
    out << Part10(syntax, data + 1, size - 1);
  }
  // Scanned here too, to check what AddInstance takes against the limits.
  absl::StatusOr<DatasetScanResult> scan = ScanPart10File(staged);
  absl::StatusOr<std::string> key = assembler->AddInstance(id, staged, -1);
  if (key.ok()) {
    Check(scan.ok());
    Check(scan->deepest <= DatasetScanLimits().max_depth);
    const std::string dir =
        (spool.root / "dicom-in" / "series" / *key).string();
    (void)ReadSeriesFacts(dir);
  }
  assembler->EndTransfer(id, true);
}

void FuzzConnection(const uint8_t* data, size_t size) {
  static RefusalLog refusals(nullptr);
  Spool spool;
  std::unique_ptr<SeriesAssembler> assembler = spool.Open();
  StorageScpOptions options;
  options.peers.accept_unknown_callers = true;
  options.acse_timeout_seconds = 1;
  options.dimse_timeout_seconds = 1;
  absl::StatusOr<std::unique_ptr<AssociationRunner>> runner =
      AssociationRunner::Create(options, assembler.get(), nullptr, &refusals,
                                nullptr);
  Check(runner.ok());
  int fds[2];
  Check(::socketpair(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0, fds) == 0);
  // The peer: sends the input, half-closes, reads until the listener is done.
  std::thread peer([&] {
    size_t at = 0;
    while (at < size) {
      const ssize_t n = ::send(fds[1], data + at, size - at, MSG_NOSIGNAL);
      if (n <= 0) break;
      at += static_cast<size_t>(n);
    }
    ::shutdown(fds[1], SHUT_WR);
    char sink[4096];
    while (::recv(fds[1], sink, sizeof(sink), 0) > 0) {
    }
    ::close(fds[1]);
  });
  ReadyConnection c;
  c.fd = fds[0];
  c.source = "192.0.2.1";
  c.guard = std::make_unique<PduGuard>();
  (*runner)->Serve(std::move(c));
  peer.join();
}

}  // namespace

extern "C" int LLVMFuzzerInitialize(int*, char***) {
  spdlog::set_level(spdlog::level::off);
  interslice::QuietDicomToolkitLogging();
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 1) return 0;
  if (data[0] % 2 == 0) {
    FuzzConnection(data + 1, size - 1);
  } else {
    FuzzDataset(data + 1, size - 1);
  }
  return 0;
}

// The outbox's C-STORE path (server/node/outbox.h StoreFiles) timed on
// its own, for bench/dicom_store.sh: every DICOM file under DIR (COPIES
// times) sent to one peer over --associations associations at once, REPEAT
// times; one line per run with the instances per second. --nagle-on leaves
// Nagle's algorithm on (TCP_NODELAY unset: what the server did before issue
// 25); otherwise the server's start-up setting
// (DisableNagleOnOutgoingAssociations) is applied, as interslice-server's
// main() does. --url sends by STOW-RS to that DICOMweb base URL instead
// (the same StoreFiles, a peer of type dicomweb; --associations is then the
// requests in flight).
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "CLI/CLI.hpp"
#include "core/dicom/series_reader.h"
#include "server/net/dicomweb/dicomweb_peer.h"
#include "server/net/dimse/dimse_peer.h"
#include "server/net/dimse/scu.h"
#include "server/node/outbox.h"

int main(int argc, char** argv) {
  namespace node = interslice::server::node;
  namespace dimse = interslice::server::dimse;
  namespace dicomweb = interslice::server::dicomweb;
  std::string dir, host = "127.0.0.1", ae = "STORESCP", url;
  int port = 0, associations = 1, repeat = 1, copies = 1;
  bool nagle_on = false;
  CLI::App app{"C-STORE every DICOM file of a folder to a peer, timed"};
  app.add_option("dir", dir, "Folder of DICOM files")->required();
  app.add_option("--host", host);
  app.add_option("--port", port);
  app.add_option("--url", url,
                 "A DICOMweb base URL: send by STOW-RS instead of C-STORE");
  app.add_option("--ae", ae, "The peer's AE title");
  app.add_option("--associations", associations, "max_associations");
  app.add_option("--repeat", repeat);
  app.add_option("--copies", copies,
                 "Send the folder's files this many times per run (the same "
                 "instances again: a PACS replaces them)");
  app.add_flag("--nagle-on", nagle_on,
               "Leave Nagle's algorithm on (the behaviour before issue 25)");
  CLI11_PARSE(app, argc, argv);
  if (std::getenv("INTERSLICE_DCMTK_LOG") == nullptr) {
    interslice::QuietDicomToolkitLogging();
  }
  // Before any thread, as in the server's main().
  if (nagle_on) {
    ::unsetenv("TCP_NODELAY");
  } else {
    dimse::DisableNagleOnOutgoingAssociations();
  }
  node::DicomPeer peer;
  peer.name = "bench";
  peer.ae_title = ae;
  peer.host = host;
  peer.port = port;
  peer.max_associations = associations;
  if (!url.empty()) {
    peer = {};
    peer.name = "bench";
    peer.type = node::PeerType::kDicomWeb;
    peer.web.url = url;
    peer.max_associations = associations;
  } else if (port <= 0) {
    std::fprintf(stderr, "--port or --url is required\n");
    return 1;
  }
  // The peer's client as the server makes it (server/app/server.cc).
  node::PeerClientSettings settings;
  settings.calling_ae_title = "INTERSLICE";
  std::unique_ptr<node::PeerClient> client;
  if (peer.type == node::PeerType::kDicomWeb) {
    client = std::make_unique<dicomweb::DicomWebPeerClient>(peer, settings);
  } else {
    client = std::make_unique<dimse::DimsePeerClient>(peer, settings);
  }
  const std::vector<std::string> one = node::ListDicomFiles(dir);
  std::vector<std::string> files;
  for (int c = 0; c < copies; ++c) {
    files.insert(files.end(), one.begin(), one.end());
  }
  for (int r = 0; r < repeat; ++r) {
    const auto t0 = std::chrono::steady_clock::now();
    absl::StatusOr<node::StoreResult> result = client->Store(files);
    const double s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0)
            .count();
    if (!result.ok() || result->accepted != static_cast<int>(files.size())) {
      std::fprintf(stderr, "store failed: %s\n",
                   result.ok()
                       ? result->first_refusal.c_str()
                       : std::string(result.status().message()).c_str());
      return 1;
    }
    std::printf(
        "%zu instances over %d %s, Nagle %s: %.3f s, %.1f "
        "instances/s\n",
        files.size(), associations,
        url.empty() ? "association(s)" : "STOW-RS request(s) at once",
        nagle_on ? "on" : "off", s, files.size() / s);
  }
  return 0;
}

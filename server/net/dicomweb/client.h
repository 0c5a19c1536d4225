// The DICOMweb client side (DICOM PS3.18): what the node does with a peer of
// type: dicomweb (server/node/peer.h). Plain types only; libcurl stays
// behind the .cc files.
//
// - ProbeDicomWebPeer: is the service there and does it take our
//   credentials (QIDO-RS GET {url}/studies?limit=1), the DICOMweb
//   counterpart of C-ECHO for --check-config and start-up.
// - StowFiles: the STOW-RS side of PeerClient::Store (server/node/peer.h);
//   see its comment.
#ifndef INTERSLICE_SERVER_NET_DICOMWEB_CLIENT_H_
#define INTERSLICE_SERVER_NET_DICOMWEB_CLIENT_H_

#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "server/node/peer.h"

namespace interslice::server::dicomweb {

// OK when the peer answers the QIDO-RS search with 200 (DICOM JSON) or 204
// (no studies). UNAVAILABLE (unreachable, 5xx), PERMISSION_DENIED (401,
// 403: names the credentials), FAILED_PRECONDITION (another status, or a
// 200 that is not DICOM JSON: the url is not a DICOMweb service); one line
// naming the peer, never its secrets.
absl::Status ProbeDicomWebPeer(const node::DicomPeer& peer,
                               int timeout_seconds);

// STOW-RS (PS3.18 10.5): POST {url}/studies, Content-Type multipart/related;
// type="application/dicom", one part per file, Accept application/dicom+json.
// - The files are split into requests of at most
//   options.stow_max_instances instances and options.stow_max_bytes bytes
//   (a file larger than that alone), each body streamed from the files
//   (never a whole request in memory); up to peer.max_associations requests
//   in flight at once.
// - Per request: HTTP 200 (all stored), 202 (some stored, some failed or
//   with warnings) and 409 (none stored) carry the Store Instances Response
//   (DICOM JSON): instances in Referenced SOP Sequence (0008,1199) count as
//   accepted, those in Failed SOP Sequence (0008,1198) as refused, the
//   first one's Failure Reason (0008,1197) as first_refusal ("0xA700
//   Refused: Out of resources"); instances in neither as refused ("not
//   confirmed").
// - Errors (the whole call fails, the queue retries every file): a peer
//   that cannot be reached, stalls for timeout_seconds, or answers 5xx/429
//   is UNAVAILABLE naming the peer; 401/403 PERMISSION_DENIED naming the
//   credentials; a 200/202/409 that is not DICOM JSON (an HTML page: url is
//   not a DICOMweb service) and other statuses FAILED_PRECONDITION; a file
//   that cannot be read or is not a Part 10 file INVALID_ARGUMENT naming
//   the file (base name only).
struct StowClientOptions {
  // To connect, and for a transfer that moves no byte.
  int timeout_seconds = 30;
  int stow_max_instances = 50;
  int64_t stow_max_bytes = int64_t{64} << 20;
};

absl::StatusOr<node::StoreResult> StowFiles(
    const node::DicomPeer& peer, const std::vector<std::string>& files,
    const StowClientOptions& options);

}  // namespace interslice::server::dicomweb

#endif  // INTERSLICE_SERVER_NET_DICOMWEB_CLIENT_H_

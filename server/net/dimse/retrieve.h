// Pulling a series that is already on a DIMSE peer (JobSpec.pacs_source):
// the DIMSE side of PeerClient::Retrieve (server/node/peer.h; a DICOMweb
// peer is pulled by QIDO-RS + WADO-RS instead, server/net/dicomweb/pull.h,
// with the same limits and error codes).
// C-GET (DCMTK DcmSCU::sendCGETRequest) at SERIES level of the Study Root
// model, with the storage sub-operations received on the same association
// into a job's upload folder; or, for a peer with `retrieve: move`, C-MOVE
// (DcmSCU::sendMOVERequest, Study Root, SERIES level) with the server's own
// DICOM listener as the move destination (options.move_destination_ae):
// the peer stores the instances over association(s) of its own, which the
// listener routes into the folder through options.pending_moves
// (pending_moves.h), with the same scan, fsync and rename as C-GET's.
//
// Contract:
// - Every received instance is written to `dest_dir` (which must exist) as
//   a Part 10 file under a temporary name as it arrives, byte for byte
//   (nothing parses it on the way), checked by the bounded scan of
//   dataset_scan.h, fsynced and renamed (the folder is fsynced at the end),
//   so the job later reads only complete, well-formed files; one that fails
//   the scan ends the retrieval (INVALID_ARGUMENT naming the peer's fault).
// - Sub-operations are accepted for the CT/MR image storage SOP classes the
//   reader handles (classic, enhanced, legacy converted) in every transfer
//   syntax it decodes (DecodableTransferSyntaxes), so a peer never sends
//   something the job cannot read; our role for them is SCP (SCP/SCU role
//   selection, as C-GET requires).
// - Limits: more than `limits.max_instances` instances or `limits.max_bytes`
//   bytes in all
//   ends the retrieval with RESOURCE_EXHAUSTED (the instance that crosses
//   the line is not kept; DCMTK's bit-preserving path answers it "cannot
//   understand").
// - Errors: UNAVAILABLE naming the peer when it cannot be reached or rejects
//   the association; FAILED_PRECONDITION with the peer's status when it
//   refuses the C-GET (e.g. unknown calling AE, no C-GET support);
//   NOT_FOUND when it answers but sends no instance (nothing matches the
//   UIDs); a partial retrieval is an error too (failed sub-operations:
//   FAILED_PRECONDITION with their count). Messages name the peer, never the
//   UIDs.
// - C-MOVE: the retrieval ends when the final C-MOVE response has arrived
//   and every association that stored into the move has ended (waited for
//   at most timeout_seconds). Its final response's completed count must
//   equal the instances received (else FAILED_PRECONDITION naming both);
//   failed or warning sub-operations are FAILED_PRECONDITION with their
//   counts; a refused move (0xA801: the peer does not know our AE title as
//   a move destination) FAILED_PRECONDITION naming the peer and the AE
//   title; nothing sent and nothing failed: NOT_FOUND. On every error the
//   files received so far are deleted from `dest_dir`. A move of the same
//   series from the same peer by another job at the same time:
//   FAILED_PRECONDITION. Without pending_moves (no listener):
//   FAILED_PRECONDITION.
// - Threads: blocking; call it from a worker thread, never from gRPC.
#ifndef INTERSLICE_SERVER_NET_DIMSE_RETRIEVE_H_
#define INTERSLICE_SERVER_NET_DIMSE_RETRIEVE_H_

#include <cstdint>
#include <string>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "server/node/peer.h"

namespace interslice::server::dimse {

class PendingMoves;

// How to reach the peer (from the server's PeerClientSettings), and for
// peers with `retrieve: move` our AE title the peer sends to (the
// listener's first) and the listener's registry of moves in progress
// (null: the server runs no listener).
struct RetrieveOptions {
  std::string calling_ae_title = "INTERSLICE";
  int timeout_seconds = 60;  // connect, association and each DIMSE message
  uint32_t max_pdu_bytes = 65536;
  node::DicomTlsFiles tls;  // for peers with tls: true
  std::string move_destination_ae;
  PendingMoves* pending_moves = nullptr;
};

absl::StatusOr<node::RetrieveResult> RetrieveSeries(
    const node::DicomPeer& peer, const std::string& study_instance_uid,
    const std::string& series_instance_uid, const std::string& dest_dir,
    const node::RetrieveLimits& limits, const RetrieveOptions& options);

}  // namespace interslice::server::dimse

#endif  // INTERSLICE_SERVER_NET_DIMSE_RETRIEVE_H_

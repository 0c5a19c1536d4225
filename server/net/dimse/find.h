// Listing what a DIMSE peer holds (Query/Retrieve C-FIND SCU, DCMTK DcmSCU,
// Study Root model), so that a series can then be pulled by its UIDs
// (retrieve.h): a STUDY-level query with the caller's keys, then a
// SERIES-level query within each study found. The DIMSE side of
// PeerClient::Find (server/node/peer.h: the query and result types; a
// DICOMweb peer is asked by QIDO-RS instead, server/net/dicomweb/pull.h).
//
// Contract:
// - Keys (DICOM PS3.4 C.2.2.2 matching, done by the peer): patient_id,
//   accession_number single values (wildcards * and ? allowed), study_date
//   a date or range ("20240101", "20240101-20240131", "-20240131");
//   modality filters both the study (ModalitiesInStudy) and its series.
//   Empty keys match everything. Keys are checked before anything is sent:
//   a backslash (a value list), a control character, a value longer than
//   its VR allows or a malformed date is INVALID_ARGUMENT naming the key.
// - Bounds: at most max_studies studies and max_series (in all) series. A
//   peer that answers with more gets a C-CANCEL on the cap; truncated is
//   then set and the answers kept are the first ones. A peer that goes on
//   sending after the C-CANCEL (some ignore it) has its association aborted
//   after max_studies further answers; nothing beyond the caps is kept.
// - Errors: UNAVAILABLE naming the peer when it cannot be reached, rejects
//   the association or stops answering (timeout_seconds for connecting,
//   the association and each response); FAILED_PRECONDITION when it does
//   not offer Study Root C-FIND or answers with a failure status (the
//   status in the message). Messages name the peer, never a key's value or
//   a UID.
// - Threads: blocking; call it from a worker thread, never from gRPC.
#ifndef INTERSLICE_SERVER_NET_DIMSE_FIND_H_
#define INTERSLICE_SERVER_NET_DIMSE_FIND_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "server/node/peer.h"

namespace interslice::server::dimse {

struct FindOptions {
  std::string calling_ae_title = "INTERSLICE";
  int timeout_seconds = 30;
  uint32_t max_pdu_bytes = 65536;
  int max_studies = 100;
  int max_series = 1000;
  node::DicomTlsFiles tls;  // for peers with tls: true
};

absl::StatusOr<node::FindResult> FindStudiesAndSeries(
    const node::DicomPeer& peer, const node::FindQuery& query,
    const FindOptions& options);

}  // namespace interslice::server::dimse

#endif  // INTERSLICE_SERVER_NET_DIMSE_FIND_H_

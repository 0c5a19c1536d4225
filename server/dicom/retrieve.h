// Pulling a series that is already on a DICOM peer (JobSpec.pacs_source);
// from a DICOMweb peer by QIDO-RS + WADO-RS instead (server/dicomweb/pull.h,
// the same limits and error codes). For a DIMSE peer:
// C-GET (DCMTK DcmSCU::sendCGETRequest) at SERIES level of the Study Root
// model, with the storage sub-operations received on the same association
// into a job's upload folder.
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
// - Limits: more than `max_instances` instances or `max_bytes` bytes in all
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
// - Threads: blocking; call it from a worker thread, never from gRPC.
#ifndef INTERSLICE_SERVER_DICOM_RETRIEVE_H_
#define INTERSLICE_SERVER_DICOM_RETRIEVE_H_

#include <cstdint>
#include <string>

#include "absl/status/statusor.h"
#include "server/dicom/peer.h"

namespace interslice::server::dicom {

struct RetrieveOptions {
  std::string calling_ae_title = "INTERSLICE";
  int timeout_seconds = 60;  // connect, association and each DIMSE message
  uint32_t max_pdu_bytes = 65536;
  int64_t max_instances = 100000;
  int64_t max_bytes = int64_t{2} << 30;
  DicomTlsFiles tls;  // for peers with tls: true
};

struct RetrieveResult {
  int64_t instances = 0;
  int64_t bytes = 0;
};

absl::StatusOr<RetrieveResult> RetrieveSeries(
    const DicomPeer& peer, const std::string& study_instance_uid,
    const std::string& series_instance_uid, const std::string& dest_dir,
    const RetrieveOptions& options);

}  // namespace interslice::server::dicom

#endif  // INTERSLICE_SERVER_DICOM_RETRIEVE_H_

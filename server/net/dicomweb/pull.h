// Pulling from a DICOMweb peer (PS3.18): the QIDO-RS + WADO-RS sides of
// PeerClient::Find and PeerClient::Retrieve (server/node/peer.h), with the
// same results, limits and error codes as C-FIND and C-GET.
//
// RetrieveSeriesWeb:
// - QIDO-RS GET {url}/studies/{S}/series/{X}/instances (limit
//   max_instances + 1, the answer bounded in bytes) learns how many
//   instances the series has: none (or 204) is NOT_FOUND, more than
//   max_instances RESOURCE_EXHAUSTED before anything is downloaded.
// - WADO-RS GET {url}/studies/{S}/series/{X}, Accept multipart/related;
//   type="application/dicom"; transfer-syntax=* (the instances as the peer
//   stores them). The body is parsed as it streams (multipart.h); each part
//   is written to dest_dir under our own name (pacs-000001.dcm...) via a
//   temporary file, fsynced, checked by the bounded scan of dataset_scan.h
//   and renamed; the folder is fsynced at the end.
// - A peer that lies fails cleanly and never makes us allocate beyond a
//   fixed bound: more parts than its QIDO answer listed or than
//   max_instances, more bytes than max_bytes in all (RESOURCE_EXHAUSTED), a
//   part longer or shorter than its Content-Length, a body cut short (no
//   closing boundary), a part that is not application/dicom or fails the
//   scan (INVALID_ARGUMENT), fewer parts than listed (FAILED_PRECONDITION:
//   a partial series is never passed on). The part being written when it
//   fails is removed.
// - HTTP errors as StowFiles (UNAVAILABLE, PERMISSION_DENIED,
//   FAILED_PRECONDITION; 404 is NOT_FOUND). Messages name the peer, never
//   the UIDs.
//
// FindStudiesAndSeriesWeb: QIDO-RS GET {url}/studies with the keys
// (PatientID, StudyDate, AccessionNumber, ModalitiesInStudy; limit
// max_studies + 1), then GET {url}/studies/{S}/series (Modality; limit) per
// study; the same fields as the C-FIND path (NumberOfSeriesRelatedInstances
// -1 when absent); truncated when a peer lists more than the caps (what is
// beyond them is dropped). Keys are checked by CheckFindQuery first.
#ifndef INTERSLICE_SERVER_NET_DICOMWEB_PULL_H_
#define INTERSLICE_SERVER_NET_DICOMWEB_PULL_H_

#include <string>

#include "absl/status/statusor.h"
#include "server/node/peer.h"

namespace interslice::server::dicomweb {

// `timeout_seconds`: to connect, and for a transfer that moves no byte.
absl::StatusOr<node::RetrieveResult> RetrieveSeriesWeb(
    const node::DicomPeer& peer, const std::string& study_instance_uid,
    const std::string& series_instance_uid, const std::string& dest_dir,
    const node::RetrieveLimits& limits, int timeout_seconds);

absl::StatusOr<node::FindResult> FindStudiesAndSeriesWeb(
    const node::DicomPeer& peer, const node::FindQuery& query,
    const node::FindLimits& limits, int timeout_seconds);

}  // namespace interslice::server::dicomweb

#endif  // INTERSLICE_SERVER_NET_DICOMWEB_PULL_H_

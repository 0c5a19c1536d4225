// The one place where absl::Status becomes grpc::Status, and where error
// text is scrubbed of patient data before it leaves the process or reaches a
// log.
#ifndef INTERSLICE_SERVER_STATUS_MAP_H_
#define INTERSLICE_SERVER_STATUS_MAP_H_

#include <string>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"
#include "grpcpp/support/status.h"

namespace interslice::server {

// absl and gRPC share the canonical code numbering, so codes map one to one;
// the message is passed through RedactPhi.
grpc::Status ToGrpcStatus(const absl::Status& status);

// Replaces DICOM UIDs (dotted digit strings of 4+ components, e.g. a
// SeriesInstanceUID listed by the reader's "several series" error) with
// "<uid>". Core messages otherwise carry no patient data by contract, and the
// server stores uploads under index-based names, so file names cannot leak
// either. The result is also LogSafe (one line, no control characters): a
// message may quote client text, such as JobSpec.multiframe_volume.
std::string RedactPhi(absl::string_view message);

// A job's failure caused by a full disk becomes RESOURCE_EXHAUSTED "disk
// full" (issue 22: it was INTERNAL naming the server's spool path): when the
// message carries the system's words for ENOSPC or EDQUOT, or `disk_full`
// (the spool's file system had no room left when the job failed) and the
// code is INTERNAL or UNKNOWN. Any other status is returned as it is.
absl::Status DiskFullAsResourceExhausted(const absl::Status& status,
                                         bool disk_full);

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_STATUS_MAP_H_

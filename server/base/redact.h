// Error text scrubbed of patient data before it leaves the process or
// reaches a log, and the one rule that names a full disk.
#ifndef INTERSLICE_SERVER_BASE_REDACT_H_
#define INTERSLICE_SERVER_BASE_REDACT_H_

#include <string>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"

namespace interslice::server {

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

#endif  // INTERSLICE_SERVER_BASE_REDACT_H_

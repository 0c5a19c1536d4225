// What the commands that talk to a server share: the one-line error, call
// deadlines, progress read from the wire, and the text they print about a
// job (its state, where it came from, its deliveries).
#ifndef INTERSLICE_CLIENT_REMOTE_REMOTE_COMMON_H_
#define INTERSLICE_CLIENT_REMOTE_REMOTE_COMMON_H_

#include <cstdint>
#include <string>
#include <vector>

#include "core/common/compute.h"
#include "grpcpp/grpcpp.h"
#include "interslice/v1/interslice.pb.h"

namespace interslice::client::remote {

// How often `watch` reconnects, and `fetch` retries one artifact, after the
// server became unreachable.
inline constexpr int kWatchRetries = 30;  // reconnects, 1 s apart

// Prints "interslice: error: <message>" on stderr; returns 1.
int Fail(const std::string& message);

// Gives the call `seconds` from now.
void SetTimeout(grpc::ClientContext& context, double seconds);

// A job's progress from the wire, as the progress display takes it.
ProgressEvent ToEvent(const v1::Progress& p);

// "queued", "running", "succeeded", ... as `list`, `watch`, `fetch` and
// `cancel` print it.
const char* StateName(v1::JobState s);

// Free text from the server (labels, AE titles, rule names, errors): no
// control characters reach the terminal, one line stays one line.
std::string Printable(std::string text);

// "2026-11-26 03:50:01Z" (UTC) for Unix ms; "-" for 0 (not yet).
std::string UtcTime(int64_t unix_ms);

// Where the job came from, what it reads and when it ran: the lines
// `list` and `watch` show under a job (UIDs included: only the job's owner
// and admins receive its status).
std::vector<std::string> DescribeJob(const v1::JobStatus& j);

// One line per DICOM delivery of the job (send_to): peer, state, counts,
// last error.
void PrintDeliveries(const v1::JobStatus& status);

}  // namespace interslice::client::remote

#endif  // INTERSLICE_CLIENT_REMOTE_REMOTE_COMMON_H_

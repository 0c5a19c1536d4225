// Running one job's compute in a supervised worker process, so that a crash
// inside a third-party decoder or filter (an assert in GDCM, a segfault in a
// codec on a hostile file) fails that job only: the server keeps serving and
// says which job failed and why.
//
// The worker is the server's own executable started with `--job-worker`
// (posix_spawn of /proc/self/exe: a fresh process image, so nothing of the
// server's threads, locks or sockets is inherited). The protocol is
// interslice.spool.v1.WorkerRequest on the worker's stdin and a stream of
// WorkerEvent on its stdout (proto/interslice/spool/v1/worker.proto),
// length-delimited; the worker's stderr is the server's. Cancellation and
// deadlines: the server sends SIGTERM (the worker cancels its token and ends
// with CANCELLED at the next iteration or slice) and SIGKILL if it has not
// ended `kill_grace` later.
//
// Cost: one process start and the exchange of the request and the report;
// the job's files are already on disk in the spool and stay there (measured
// in bench/load_fault.sh; see docs/speed/).
#ifndef INTERSLICE_SERVER_ENGINE_JOB_WORKER_H_
#define INTERSLICE_SERVER_ENGINE_JOB_WORKER_H_

#include <chrono>
#include <cstdint>
#include <functional>
#include <string>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "interslice/spool/v1/worker.pb.h"
#include "job/job.h"

namespace interslice::server {

struct WorkerOptions {
  // The executable to start with --job-worker; empty = /proc/self/exe.
  std::string executable;
  // After SIGTERM for a cancelled job, how long the worker may take to end
  // before SIGKILL.
  std::chrono::milliseconds kill_grace{5000};
};

// How the worker process ended, for logs and metrics.
struct WorkerOutcome {
  bool crashed = false;  // ended by a signal the server did not send
  int signal = 0;        // that signal, else 0
  int exit_code = -1;    // when it exited normally
  // The worker's peak resident set size, bytes, as it measured itself
  // (core/pipeline PeakRssBytes: VmHWM) and sent with its result; -1 when
  // it sent none (a crash). Not wait4's ru_maxrss: posix_spawn shares the
  // server's memory until the worker's execve, and Linux carries that
  // image's peak into the worker's ru_maxrss, so it reported the server's.
  int64_t peak_rss_bytes = -1;
  std::string last_stage;  // the stage it last reported
};

// Runs `request` in a worker process, forwarding its progress to
// context.progress and context.cancel to it (polled every 100 ms). Returns
// what the job made (job/job.h; peak_rss_bytes: the worker's own)
// or its error, for any kind of job; a worker that crashes gives INTERNAL
// "the job's worker process crashed (signal N, NAME) during stage S; ...";
// one that cannot be started gives UNAVAILABLE. Blocking: call it from a
// job worker thread.
// `on_source` (may be null) is called with the series the job reads once
// the worker has scanned its headers (before the job's own read), on this
// thread.
absl::StatusOr<job::JobResult> RunInWorkerProcess(
    const spool::v1::WorkerRequest& request, const ComputeContext& context,
    const WorkerOptions& options, WorkerOutcome* outcome,
    const std::function<void(const job::SourceSeries&)>& on_source = nullptr);

// The worker side: reads one WorkerRequest from `in_fd`, runs the job it
// names (job/job.h MakeJobFromWire, on the request's folders) and writes its
// events to `out_fd`. Returns the process exit code (0 when the
// job's result, OK or not, was delivered). main() calls it for
// `--job-worker`.
//
// Test hook, compiled in only with the CMake option INTERSLICE_FAULT_INJECTION
// (off by default; the instrumented test build turns it on): with
// INTERSLICE_WORKER_FAULT=abort:STAGE (or segv:STAGE) in its environment the
// worker aborts (or dereferences null) when the job reports STAGE, standing
// in for a crash inside a decoder; the server's tests use it to show that
// such a crash fails one job only.
int RunJobWorker(int in_fd, int out_fd);

// The same test hook where jobs run in the server process (--isolation
// thread), to show what a crash does there: call it after reporting `stage`.
void InjectTestFault(const std::string& stage, float threshold);

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_ENGINE_JOB_WORKER_H_

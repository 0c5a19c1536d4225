#include "server/engine/job_worker.h"

#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"
#include "core/dicom/series_reader.h"
#include "job/job.h"

extern char** environ;

namespace interslice::server {
namespace {

// Frames on the pipes: a 4-byte little-endian length, then a serialized
// message. Anything longer than this is a protocol error (a report is a few
// kilobytes; the request holds only the spec and two paths).
constexpr uint32_t kMaxFrameBytes = 16u << 20;

bool WriteAll(int fd, const char* data, size_t size) {
  while (size > 0) {
    const ssize_t n = ::write(fd, data, size);
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return false;
    data += n;
    size -= static_cast<size_t>(n);
  }
  return true;
}

bool WriteFrame(int fd, const google::protobuf::MessageLite& message) {
  std::string bytes;
  if (!message.SerializeToString(&bytes) || bytes.size() > kMaxFrameBytes) {
    return false;
  }
  const uint32_t size = static_cast<uint32_t>(bytes.size());
  const char header[4] = {static_cast<char>(size & 0xff),
                          static_cast<char>((size >> 8) & 0xff),
                          static_cast<char>((size >> 16) & 0xff),
                          static_cast<char>((size >> 24) & 0xff)};
  return WriteAll(fd, header, 4) && WriteAll(fd, bytes.data(), bytes.size());
}

// Takes the complete frames off the front of `buffer`; false on a frame
// longer than kMaxFrameBytes.
bool TakeFrames(std::string& buffer, std::vector<std::string>& frames) {
  size_t offset = 0;
  while (buffer.size() - offset >= 4) {
    const auto* p = reinterpret_cast<const unsigned char*>(&buffer[offset]);
    const uint32_t size =
        p[0] | (p[1] << 8) | (p[2] << 16) | (static_cast<uint32_t>(p[3]) << 24);
    if (size > kMaxFrameBytes) return false;
    if (buffer.size() - offset - 4 < size) break;
    frames.push_back(buffer.substr(offset + 4, size));
    offset += 4 + size;
  }
  buffer.erase(0, offset);
  return true;
}

std::string SignalName(int signal) {
  const char* name = ::sigabbrev_np(signal);
  return name != nullptr ? absl::StrCat("SIG", name)
                         : absl::StrCat("signal ", signal);
}

// The test hook of RunJobWorker: "abort:STAGE" or "segv:STAGE", optionally
// ":THRESHOLD" to hit only jobs with that threshold. Compiled in only with
// the CMake option INTERSLICE_FAULT_INJECTION (the instrumented test build,
// scripts/build-instrumented.sh); a shipped server reads no such variable.
struct Fault {
  std::string kind;
  std::string stage;
  std::optional<float> threshold;
};

Fault ReadFault() {
#ifndef INTERSLICE_FAULT_INJECTION
  return {};
#else
  const char* value = std::getenv("INTERSLICE_WORKER_FAULT");
  if (value == nullptr) return {};
  const std::vector<std::string> parts = absl::StrSplit(value, ':');
  if (parts.size() < 2) return {};
  Fault fault{parts[0], parts[1], std::nullopt};
  float threshold = 0;
  if (parts.size() > 2 && absl::SimpleAtof(parts[2], &threshold)) {
    fault.threshold = threshold;
  }
  return fault;
#endif
}

void InjectFault(const Fault& fault, const std::string& stage,
                 float threshold) {
  if (fault.kind.empty() || stage != fault.stage) return;
  if (fault.threshold.has_value() && *fault.threshold != threshold) return;
  if (fault.kind == "abort") std::abort();
  if (fault.kind == "segv") {
    volatile int* null = nullptr;
    *null = 1;
  }
}

// A worker process just started: its pid, the write end of its stdin and
// the read end of its stdout.
struct SpawnedWorker {
  pid_t pid = -1;
  int to_child = -1;
  int from_child = -1;
};

// Starts the job worker (options.executable --job-worker) with a pipe on its
// stdin and one on its stdout; UNAVAILABLE when it cannot.
absl::StatusOr<SpawnedWorker> SpawnWorker(const WorkerOptions& options) {
  int to_child[2], from_child[2];
  if (::pipe2(to_child, O_CLOEXEC) != 0) {
    return absl::UnavailableError(absl::StrCat(
        "cannot start a job worker: pipe: ", std::strerror(errno)));
  }
  if (::pipe2(from_child, O_CLOEXEC) != 0) {
    const int error = errno;
    ::close(to_child[0]);
    ::close(to_child[1]);
    return absl::UnavailableError(absl::StrCat(
        "cannot start a job worker: pipe: ", std::strerror(error)));
  }
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_adddup2(&actions, to_child[0], 0);
  posix_spawn_file_actions_adddup2(&actions, from_child[1], 1);
  // The server blocks SIGTERM in every thread (its signal thread sigwaits
  // for it) and a spawned process inherits that mask: start the worker with
  // none blocked and default dispositions.
  posix_spawnattr_t attributes;
  posix_spawnattr_init(&attributes);
  sigset_t empty, defaults;
  sigemptyset(&empty);
  sigemptyset(&defaults);
  sigaddset(&defaults, SIGPIPE);
  sigaddset(&defaults, SIGTERM);
  sigaddset(&defaults, SIGINT);
  posix_spawnattr_setsigmask(&attributes, &empty);
  posix_spawnattr_setsigdefault(&attributes, &defaults);
  posix_spawnattr_setflags(&attributes,
                           POSIX_SPAWN_SETSIGMASK | POSIX_SPAWN_SETSIGDEF);
  const std::string executable =
      options.executable.empty() ? "/proc/self/exe" : options.executable;
  std::string arg0 = "interslice-job-worker", arg1 = "--job-worker";
  char* argv[] = {arg0.data(), arg1.data(), nullptr};
  pid_t pid = -1;
  const int spawned = ::posix_spawn(&pid, executable.c_str(), &actions,
                                    &attributes, argv, environ);
  posix_spawn_file_actions_destroy(&actions);
  posix_spawnattr_destroy(&attributes);
  ::close(to_child[0]);
  ::close(from_child[1]);
  if (spawned != 0) {
    ::close(to_child[1]);
    ::close(from_child[0]);
    return absl::UnavailableError(absl::StrCat(
        "cannot start a job worker process: ", std::strerror(spawned)));
  }
  return SpawnedWorker{pid, to_child[1], from_child[0]};
}

// What the server heard from a worker (its result, whether its output did
// not parse) and which signals it sent it.
struct WorkerExchange {
  bool have_result = false;
  spool::v1::WorkerResult result;
  bool protocol_error = false;
  bool sent_term = false, sent_kill = false;
  std::chrono::steady_clock::time_point term_time;
};

// Cancellation and deadlines: SIGTERM once the job is cancelled, SIGKILL
// when the worker has not ended options.kill_grace later.
void SignalWorkerIfCancelled(pid_t pid, const ComputeContext& context,
                             const WorkerOptions& options,
                             WorkerExchange& exchange) {
  if (!exchange.sent_term && !context.CheckCancelled().ok()) {
    ::kill(pid, SIGTERM);
    exchange.sent_term = true;
    exchange.term_time = std::chrono::steady_clock::now();
  }
  if (exchange.sent_term && !exchange.sent_kill &&
      std::chrono::steady_clock::now() - exchange.term_time >
          options.kill_grace) {
    ::kill(pid, SIGKILL);
    exchange.sent_kill = true;
  }
}

// One event from the worker: progress to context.progress, the source
// series to `on_source`, or the result into `exchange`.
void HandleWorkerEvent(
    const std::string& frame, const ComputeContext& context,
    const std::function<void(const job::SourceSeries&)>& on_source,
    WorkerOutcome& out, WorkerExchange& exchange) {
  spool::v1::WorkerEvent event;
  if (!event.ParseFromString(frame)) {
    exchange.protocol_error = true;
    return;
  }
  if (event.has_progress()) {
    const spool::v1::WorkerProgress& p = event.progress();
    out.last_stage = p.stage();
    context.Report({.stage = p.stage(),
                    .fraction = p.fraction(),
                    .iteration = p.iteration(),
                    .relative_residual = p.relative_residual(),
                    .energy = p.energy()});
  } else if (event.has_result()) {
    exchange.result = event.result();
    exchange.have_result = true;
    out.peak_rss_bytes = event.result().peak_rss_bytes();
  } else if (event.has_source() && on_source) {
    const spool::v1::WorkerSource& w = event.source();
    on_source({.study_instance_uid = w.study_instance_uid(),
               .series_instance_uid = w.series_instance_uid(),
               .modality = w.modality(),
               .instance_count = w.instance_count()});
  }
}

// Reads the worker's events from `from_child` until its output ends (or
// does not parse: then the worker is killed), signalling it meanwhile when
// the job is cancelled.
void ReadWorkerEvents(
    pid_t pid, int from_child, const ComputeContext& context,
    const WorkerOptions& options,
    const std::function<void(const job::SourceSeries&)>& on_source,
    WorkerOutcome& out, WorkerExchange& exchange) {
  std::string buffer;
  char chunk[65536];
  for (;;) {
    SignalWorkerIfCancelled(pid, context, options, exchange);
    pollfd fd{from_child, POLLIN, 0};
    const int ready = ::poll(&fd, 1, 100);
    if (ready < 0 && errno != EINTR) break;
    if (ready <= 0) continue;
    const ssize_t n = ::read(from_child, chunk, sizeof(chunk));
    if (n < 0 && (errno == EINTR || errno == EAGAIN)) continue;
    if (n <= 0) break;  // end of the worker's output
    buffer.append(chunk, static_cast<size_t>(n));
    std::vector<std::string> frames;
    if (!TakeFrames(buffer, frames)) {
      exchange.protocol_error = true;
      ::kill(pid, SIGKILL);
      exchange.sent_kill = true;
      break;
    }
    for (const std::string& frame : frames) {
      HandleWorkerEvent(frame, context, on_source, out, exchange);
    }
  }
}

// Waits for the worker to end: its exit code or signal and whether that is
// a crash (a signal the server did not send), into `out`. Its peak RSS is
// the one it sent (WorkerOutcome::peak_rss_bytes says why not wait4's).
void ReapWorker(pid_t pid, const WorkerExchange& exchange, WorkerOutcome& out) {
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
  }
  if (WIFEXITED(status)) out.exit_code = WEXITSTATUS(status);
  if (WIFSIGNALED(status)) {
    out.signal = WTERMSIG(status);
    const bool ours = (exchange.sent_term && out.signal == SIGTERM) ||
                      (exchange.sent_kill && out.signal == SIGKILL);
    out.crashed = !ours;
  }
}

// The job's result as the worker reported it: its error, or what it made.
absl::StatusOr<job::JobResult> JobResultFromWorker(
    const spool::v1::WorkerResult& result, int64_t peak_rss_bytes) {
  const absl::Status status(static_cast<absl::StatusCode>(result.code()),
                            result.message());
  if (!status.ok()) return status;
  job::JobResult made;
  for (const spool::v1::WorkerStage& s : result.stages()) {
    made.stages.push_back({s.stage(), s.seconds()});
  }
  for (const spool::v1::WorkerArtifact& a : result.artifacts()) {
    made.artifacts.push_back({a.kind(), a.path(), a.size_bytes()});
  }
  made.warnings.assign(result.warnings().begin(), result.warnings().end());
  made.report_json = result.report_json();
  made.peak_rss_bytes = peak_rss_bytes;
  return made;
}

// How the job ended, from what the worker sent and how it ended: its
// result, or why there is none (a crash, a protocol error, cancellation).
absl::StatusOr<job::JobResult> WorkerJobResult(const WorkerExchange& exchange,
                                               const ComputeContext& context,
                                               const WorkerOutcome& out) {
  if (exchange.have_result && !out.crashed) {
    return JobResultFromWorker(exchange.result, out.peak_rss_bytes);
  }
  if (out.crashed) {
    return absl::InternalError(absl::StrFormat(
        "the job's worker process crashed (%s) during stage '%s'; only this "
        "job failed. The input may be malformed or unsupported%s",
        SignalName(out.signal),
        out.last_stage.empty() ? "start" : out.last_stage,
        out.signal == SIGKILL ? ", or the worker ran out of memory" : ""));
  }
  if (exchange.protocol_error && context.CheckCancelled().ok()) {
    // Stopped by us because its output did not parse, not cancelled: say
    // so (this once read "the job was cancelled", which sent people
    // looking for a client that never cancelled anything).
    return absl::InternalError(absl::StrFormat(
        "the job's worker process wrote output the server cannot read "
        "(protocol error) during stage '%s'; the worker was stopped and only "
        "this job failed",
        out.last_stage.empty() ? "start" : out.last_stage));
  }
  if (exchange.sent_term || exchange.sent_kill) {
    absl::Status cancelled = context.CheckCancelled();
    return cancelled.ok() ? absl::CancelledError("the job was cancelled")
                          : cancelled;
  }
  return absl::InternalError(absl::StrFormat(
      "the job's worker process ended without a result (exit code %d%s)",
      out.exit_code, exchange.protocol_error ? ", protocol error" : ""));
}

}  // namespace

absl::StatusOr<job::JobResult> RunInWorkerProcess(
    const spool::v1::WorkerRequest& request, const ComputeContext& context,
    const WorkerOptions& options, WorkerOutcome* outcome,
    const std::function<void(const job::SourceSeries&)>& on_source) {
  WorkerOutcome local;
  WorkerOutcome& out = outcome != nullptr ? *outcome : local;
  out = WorkerOutcome{};
  // A worker that dies while we write its request must not take the server
  // down with SIGPIPE: the write then just fails.
  static std::once_flag ignore_sigpipe;
  std::call_once(ignore_sigpipe, [] { ::signal(SIGPIPE, SIG_IGN); });

  absl::StatusOr<SpawnedWorker> worker = SpawnWorker(options);
  if (!worker.ok()) return worker.status();

  // The request, then end of input. A worker that is already gone makes
  // the write fail; its exit status says why below.
  WriteFrame(worker->to_child, request);
  ::close(worker->to_child);

  WorkerExchange exchange;
  ReadWorkerEvents(worker->pid, worker->from_child, context, options, on_source,
                   out, exchange);
  ::close(worker->from_child);
  ReapWorker(worker->pid, exchange, out);
  return WorkerJobResult(exchange, context, out);
}

void InjectTestFault(const std::string& stage, float threshold) {
  static const Fault fault = ReadFault();
  InjectFault(fault, stage, threshold);
}

int RunJobWorker(int in_fd, int out_fd) {
  // The protocol owns `out_fd`: anything else that writes to stdout (a
  // library's stray print) goes to stderr instead of corrupting it.
  const int protocol_fd = ::fcntl(out_fd, F_DUPFD_CLOEXEC, 3);
  if (protocol_fd < 0) return 2;
  if (out_fd == STDOUT_FILENO) ::dup2(STDERR_FILENO, STDOUT_FILENO);

  // The worker ends with the server (kill -9 of the server included), so
  // that a restarted server never finds an orphan still writing into the
  // job's folder; checked against the server's pid below, in case the
  // server died before this line.
  ::prctl(PR_SET_PDEATHSIG, SIGKILL);
  // SIGTERM cancels the job: block it before any thread exists, and let one
  // thread wait for it.
  static CancellationToken token;
  sigset_t term;
  sigemptyset(&term);
  sigaddset(&term, SIGTERM);
  ::pthread_sigmask(SIG_BLOCK, &term, nullptr);
  std::thread([term] {
    int signal = 0;
    if (::sigwait(&term, &signal) == 0) token.Cancel();
  }).detach();

  std::string input;
  char chunk[65536];
  for (;;) {
    const ssize_t n = ::read(in_fd, chunk, sizeof(chunk));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    input.append(chunk, static_cast<size_t>(n));
    if (input.size() > kMaxFrameBytes + 4) return 2;
  }
  std::vector<std::string> frames;
  spool::v1::WorkerRequest request;
  if (!TakeFrames(input, frames) || frames.size() != 1 ||
      !request.ParseFromString(frames[0])) {
    return 2;
  }
  if (request.server_pid() != 0 && ::getppid() != request.server_pid()) {
    return 2;  // the server is gone already
  }

  auto finish = [&](const absl::Status& status, const job::JobResult& made) {
    spool::v1::WorkerEvent event;
    spool::v1::WorkerResult* result = event.mutable_result();
    result->set_code(static_cast<int32_t>(status.code()));
    result->set_message(std::string(status.message()));
    if (status.ok()) {
      result->set_report_json(made.report_json);
      for (const StageTiming& s : made.stages) {
        spool::v1::WorkerStage* stage = result->add_stages();
        stage->set_stage(s.stage);
        stage->set_seconds(s.seconds);
      }
      for (const Artifact& a : made.artifacts) {
        spool::v1::WorkerArtifact* artifact = result->add_artifacts();
        artifact->set_kind(a.kind);
        artifact->set_path(a.path);
        artifact->set_size_bytes(a.size_bytes);
      }
      for (const std::string& w : made.warnings) result->add_warnings(w);
    }
    // The worker's own peak, failed jobs included: the server cannot measure
    // it from outside (WorkerOutcome::peak_rss_bytes).
    result->set_peak_rss_bytes(status.ok() ? made.peak_rss_bytes
                                           : PeakRssBytes());
    return WriteFrame(protocol_fd, event) ? 0 : 3;
  };

  QuietDicomToolkitLogging();
  absl::StatusOr<std::unique_ptr<job::JobKind>> made =
      job::MakeJobFromWire(request.spec());
  if (!made.ok()) return finish(made.status(), {});
  job::JobKind& job = **made;
  if (absl::Status s = job.UseSpool(request.input_dir(), request.output_dir(),
                                    request.max_output_voxels());
      !s.ok()) {
    return finish(s, {});
  }
  if (request.omit_files_dicom_objects_carry()) {
    job.OmitFilesDicomObjectsCarry();
  }
  if (request.deadline_unix_ms() > 0) {
    const auto now_unix = std::chrono::system_clock::now();
    const auto remaining =
        std::chrono::milliseconds(request.deadline_unix_ms()) -
        std::chrono::duration_cast<std::chrono::milliseconds>(
            now_unix.time_since_epoch());
    token.SetDeadline(std::chrono::steady_clock::now() + remaining);
  }
  const Fault fault = ReadFault();
  const float threshold = request.spec().threshold();
  ComputeContext context;
  context.threads = request.threads();
  context.cancel = &token;
  // Reports are frames on the protocol: one at a time, even if a stage
  // broke ComputeContext's "never concurrently" (two at once interleave
  // their bytes, and the server kills a worker whose frames do not parse).
  std::mutex protocol_mutex;
  context.progress = [&](const ProgressEvent& e) {
    std::lock_guard<std::mutex> lock(protocol_mutex);
    spool::v1::WorkerEvent event;
    spool::v1::WorkerProgress* p = event.mutable_progress();
    p->set_stage(e.stage);
    p->set_fraction(e.fraction);
    p->set_iteration(e.iteration);
    p->set_relative_residual(e.relative_residual);
    p->set_energy(e.energy);
    WriteFrame(protocol_fd, event);
    InjectFault(fault, e.stage, threshold);
  };
  // Which series this is, for the job's status; a folder without one (or
  // with several and no choice) is the job's own read's error to report.
  if (absl::StatusOr<job::SourceSeries> source = job::DescribeSourceSeries(
          request.input_dir(), request.spec().series_instance_uid(),
          ComputeContext{.threads = request.threads(), .cancel = &token});
      source.ok()) {
    std::lock_guard<std::mutex> lock(protocol_mutex);
    spool::v1::WorkerEvent event;
    spool::v1::WorkerSource* w = event.mutable_source();
    w->set_study_instance_uid(source->study_instance_uid);
    w->set_series_instance_uid(source->series_instance_uid);
    w->set_modality(source->modality);
    w->set_instance_count(source->instance_count);
    WriteFrame(protocol_fd, event);
  }
  absl::StatusOr<job::JobResult> result = job.Run(context);
  if (!result.ok()) return finish(result.status(), {});
  return finish(absl::OkStatus(), *result);
}

}  // namespace interslice::server

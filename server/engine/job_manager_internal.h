// Private to server/engine: what the files that define JobManager's methods
// share (job_manager.cc: recovery, the queue, cancellation, listing,
// draining, shutdown and the ticker; admission.cc: admitting and queueing a
// job; job_runner.cc: running one).
#ifndef INTERSLICE_SERVER_ENGINE_JOB_MANAGER_INTERNAL_H_
#define INTERSLICE_SERVER_ENGINE_JOB_MANAGER_INTERNAL_H_

#include <memory>
#include <string>

#include "server/base/audit.h"
#include "server/engine/job.h"

namespace interslice::server::job_manager_internal {

// One audit record about `job` (its owner, its origin when the DICOM node
// made it, and as `peer` the DICOM peer it pulls its series from, if any);
// nothing without an audit trail.
void AuditJob(AuditLog* audit, const std::shared_ptr<Job>& job,
              const char* event, AuditOutcome outcome,
              const std::string& detail);

}  // namespace interslice::server::job_manager_internal

#endif  // INTERSLICE_SERVER_ENGINE_JOB_MANAGER_INTERNAL_H_

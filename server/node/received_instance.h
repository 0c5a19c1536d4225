// What every door does with a received instance before the node keeps it:
// check that it was written whole and is well-formed (the bounded scan,
// dataset_scan.h, then its header's UIDs), and keep it durably (fsync,
// rename, fsync of the folder: an OK means kept, and only then may the
// door answer success). Shared by the intake (series_assembler.h) and the
// C-MOVE registry (server/net/dimse/pending_moves.h).
#ifndef INTERSLICE_SERVER_NODE_RECEIVED_INSTANCE_H_
#define INTERSLICE_SERVER_NODE_RECEIVED_INSTANCE_H_

#include <cstdint>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "server/node/dataset_scan.h"

namespace interslice::server::node {

// The identity of a received instance (from its header).
struct InstanceIds {
  std::string study_uid, series_uid, sop_instance_uid;
  std::string sop_class_uid;           // empty when not given
  std::string frame_of_reference_uid;  // empty when not given
};

// A received file at `staged` (the listener's staging file: DCMTK's meta
// group, then the data set as received) checked as every received instance
// is before it is kept: written whole (`received_bytes`: the data set's
// bytes as they arrived, -1: unknown; fewer in the file: RESOURCE_EXHAUSTED,
// the disk is full), the bounded scan (INVALID_ARGUMENT), then its header's
// UIDs (INVALID_ARGUMENT without a series or SOP instance UID). The file is
// left where it is.
struct ReceivedInstance {
  InstanceIds ids;
  int64_t size = 0;  // of the file
};
absl::StatusOr<ReceivedInstance> ReadReceivedInstance(
    const std::string& staged, int64_t received_bytes,
    const DatasetScanLimits& limits);

// Keeps a checked file: fsync, rename to `target`, fsync of its folder (an
// OK means kept: the C-STORE may answer success). RESOURCE_EXHAUSTED when
// the sync or the rename fails (the file is left at `staged`).
absl::Status KeepReceivedFile(const std::string& staged,
                              const std::string& target);

// fsync of a file or folder by path, ignoring errors (a folder after a
// rename into it; what must not fail uses FsyncFile).
void FsyncPath(const std::string& path, bool directory);
// fsync that reports failure (an instance file: success must mean kept).
absl::Status FsyncFile(const std::string& path);

}  // namespace interslice::server::node

#endif  // INTERSLICE_SERVER_NODE_RECEIVED_INSTANCE_H_

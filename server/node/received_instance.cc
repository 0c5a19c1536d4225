#include "server/node/received_instance.h"

#include <fcntl.h>
#include <unistd.h>

#include <filesystem>

#include "server/node/dataset_scan.h"
#include "server/node/series_folder.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"

namespace interslice::server::node {

namespace fs = std::filesystem;

void FsyncPath(const std::string& path, bool directory) {
  const int fd =
      ::open(path.c_str(), directory ? (O_RDONLY | O_DIRECTORY) : O_RDONLY);
  if (fd >= 0) {
    ::fsync(fd);
    ::close(fd);
  }
}

// fsync that reports failure (the instance file: success must mean kept).
absl::Status FsyncFile(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return absl::InternalError("cannot open a received instance");
  const int rc = ::fsync(fd);
  ::close(fd);
  if (rc != 0) {
    return absl::ResourceExhaustedError("cannot sync a received instance");
  }
  return absl::OkStatus();
}
absl::StatusOr<ReceivedInstance> ReadReceivedInstance(
    const std::string& staged, int64_t received_bytes,
    const DatasetScanLimits& limits) {
  std::error_code ec;
  ReceivedInstance out;
  out.size = static_cast<int64_t>(fs::file_size(staged, ec));
  if (ec) return absl::InternalError("a received instance vanished");
  // The meta group is ours (DCMTK wrote it); what follows is as received.
  absl::StatusOr<Part10Meta> meta = ReadPart10Meta(staged);
  if (!meta.ok()) return meta.status();
  if (received_bytes >= 0 &&
      out.size - meta->dataset_offset != received_bytes) {
    // The writer's buffered tail was lost (a full disk shows at close).
    return absl::ResourceExhaustedError(
        "the disk is full: a received instance could not be written whole");
  }
  // Bounded first: DCMTK's parser below reads only what passed.
  if (absl::StatusOr<DatasetScanResult> scan = ScanPart10File(staged, limits);
      !scan.ok()) {
    return scan.status();
  }
  {
    DcmFileFormat ff;
    if (ff.loadFileUntilTag(staged.c_str(), EXS_Unknown, EGL_noChange,
                            DCM_MaxReadLength, ERM_autoDetect, DCM_PixelData)
            .bad()) {
      return absl::InvalidArgumentError("the instance is not readable DICOM");
    }
    DcmDataset* ds = ff.getDataset();
    out.ids.study_uid = GetString(ds, DCM_StudyInstanceUID);
    out.ids.series_uid = GetString(ds, DCM_SeriesInstanceUID);
    out.ids.sop_instance_uid = GetString(ds, DCM_SOPInstanceUID);
    out.ids.sop_class_uid = GetString(ds, DCM_SOPClassUID);
    out.ids.frame_of_reference_uid = GetString(ds, DCM_FrameOfReferenceUID);
  }
  if (out.ids.series_uid.empty() || out.ids.sop_instance_uid.empty()) {
    return absl::InvalidArgumentError(
        "the instance has no Series or SOP Instance UID");
  }
  return out;
}

absl::Status KeepReceivedFile(const std::string& staged,
                              const std::string& target) {
  if (absl::Status synced = FsyncFile(staged); !synced.ok()) return synced;
  if (::rename(staged.c_str(), target.c_str()) != 0) {
    return absl::ResourceExhaustedError(
        "the disk is full: cannot keep a received instance");
  }
  FsyncPath(fs::path(target).parent_path().string(), true);
  return absl::OkStatus();
}

}  // namespace interslice::server::node

// The series assembler's folders (series_assembler.h has the layout): how a
// series is named on disk, what its instances' headers say, and what it
// was received as. For the node's own files only.
#ifndef INTERSLICE_SERVER_NODE_SERIES_FOLDER_H_
#define INTERSLICE_SERVER_NODE_SERIES_FOLDER_H_

#include <cstdint>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "server/node/config.h"
#include "server/node/received_instance.h"

class DcmItem;
class DcmTagKey;

namespace interslice::server::node {

// In a series folder: one file per association storing into it right now,
// and the record of why the series is incomplete.
inline constexpr char kOpenPrefix[] = "open-";
inline constexpr char kIncompleteFile[] = "incomplete.json";

// A series' key: the SHA-256 of called AE, study and series UID (hex, 32
// characters), so that no UID appears in a path or log line.
std::string Key(const std::string& called_ae, const std::string& study,
                const std::string& series);
// An instance's file name in its series folder (a re-sent instance
// replaces itself).
std::string InstanceName(const std::string& sop_instance_uid);
// A text attribute of a data set item ("" when absent).
std::string GetString(DcmItem* item, const DcmTagKey& tag);

// What a segmentation references: its first SEG or RTSTRUCT instance (in
// name order), the referenced SeriesInstanceUID and the studies to look in.
struct SegmentationRef {
  std::string file;
  std::string series_uid;
  std::vector<std::string> study_uids;  // the instance's own first
};
std::optional<SegmentationRef> ReadSegmentationRef(const std::string& dir);

// The *.dcm files of `dir`, in name order.
std::vector<std::string> DicomFiles(const std::string& dir);
// The UIDs of a kept instance's header (empty where unreadable).
InstanceIds ReadInstanceIds(const std::string& file);
// The FrameOfReferenceUID of a held series: its first instance's.
std::string HeldFrameOfReference(const std::string& held);
// SHA-256 of a kept instance's data set: the bytes after the meta group,
// as the sender sent them (the meta group is written by our listener and
// names the sender, which may differ for the same instance).
absl::StatusOr<std::string> DatasetSha256(const std::string& path);
// A kept series' id: its folder's name under unmatched/, <key>-<unix ms>
// (checked before it becomes part of a path).
bool IsKeptId(const std::string& id);
// origin.json of a series folder: the calling and called AE titles it was
// received with.
std::pair<std::string, std::string> ReadOrigin(const std::string& dir);
// A node job's origin text: "dicom:<calling>-><called> rule <name>".
std::string JobOrigin(const std::string& calling_ae,
                      const std::string& called_ae, const Rule& rule);
// Hard-links (or copies) the instances of `from` that `dir` lacks into it.
// Returns the instances and bytes added.
std::pair<int64_t, int64_t> CarryInstances(const std::string& from,
                                           const std::string& dir);

// Reads the rule-relevant facts of the series in `dir` (every *.dcm header);
// calling/called AE are left empty.
SeriesFacts ReadSeriesFacts(const std::string& dir);

}  // namespace interslice::server::node

#endif  // INTERSLICE_SERVER_NODE_SERIES_FOLDER_H_

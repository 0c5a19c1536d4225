// Private to core/dicom: reading and classifying one DICOM file's header
// without loading its pixel data, and the pixel module attributes the reader
// needs to turn stored values into modality values.
#ifndef INTERSLICE_CORE_DICOM_DICOM_HEADER_H_
#define INTERSLICE_CORE_DICOM_DICOM_HEADER_H_

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/geometry/volume.h"

class DcmItem;

namespace interslice {
namespace dicom_internal {

// Values above this length are not loaded while scanning headers, so that
// scanning a folder never reads pixel data (or other large blobs) into
// memory.
inline constexpr uint32_t kHeaderMaxReadLength = 4096;

enum class FileKind {
  kNotDicom,  // unreadable (or refused: see `problem`), no series known
  kDicomDir,
  kNotImage,  // DICOM, but not a slice of an image stack
  kImage,     // a slice (possibly with a `problem` that makes it unusable)
};

// How the stored pixel values are laid out (Image Pixel module).
struct PixelLayout {
  int bits_allocated = 16;
  int bits_stored = 16;
  int high_bit = 15;
  bool is_signed = false;
};

// Geometry and rescale of one frame of an enhanced multi-frame object, from
// its functional groups (per-frame first, then shared).
struct FrameGeometry {
  Vec3 position = {0, 0, 0};
  std::array<double, 6> orientation = {1, 0, 0, 0, 1, 0};
  std::array<double, 2> pixel_spacing = {1, 1};
  double rescale_slope = 1;
  double rescale_intercept = 0;
  // Which volume of the object the frame belongs to: StackID, temporal
  // position and frame type, e.g. "stack 1, temporal position 2, frame type
  // ORIGINAL\PRIMARY\M\NONE". Frames of different volumes may share
  // positions, so the reader stacks one volume at a time.
  std::string volume;
};

// Objects nested deeper than this (sequences within items within
// sequences...) are refused before DCMTK parses them: DCMTK parses nesting
// by recursion without a limit and overflows the stack on a few thousand
// levels. Real objects (structured reports included) stay far below.
inline constexpr int kMaxSequenceDepth = 128;

// OK unless `path` is a DICOM stream with sequences nested deeper than
// `max_depth` (INVALID_ARGUMENT naming the file). Walks the encoded elements
// iteratively (explicit/implicit little endian, explicit big endian,
// deflated), skipping values; files it cannot follow are left to DCMTK.
absl::Status CheckSequenceDepth(const std::string& path,
                                int max_depth = kMaxSequenceDepth);

struct FileHeader {
  std::string path;
  FileKind kind = FileKind::kNotDicom;
  // For kImage: why this file cannot be used. It is reported only when the
  // file's series is the one being read, so that a broken file in some other
  // series does not prevent reading a good one.
  absl::Status problem;

  std::string series_uid;
  std::string study_uid;
  std::string frame_of_reference_uid;
  std::string modality;
  std::string series_number;  // as stored (IS), may be empty
  // SOPClassUID, or when it is missing or empty the file meta header's
  // MediaStorageSOPClassUID (then sop_class_from_meta).
  std::string sop_class_uid;
  bool sop_class_from_meta = false;
  std::string sop_instance_uid;
  // What the file's series is grouped by: series_uid when present, else a
  // key of what identifies a series without it (see InferredSeriesKey).
  std::string series_key;

  // Valid only for kImage files with an OK problem.
  int rows = 0;
  int columns = 0;
  std::array<double, 6> orientation = {1, 0, 0, 0, 1, 0};
  Vec3 position = {0, 0, 0};
  std::array<double, 2> pixel_spacing = {1, 1};  // [between rows, columns]
  double rescale_slope = 1;
  double rescale_intercept = 0;
  double slice_thickness = 0;         // 0 when absent
  double spacing_between_slices = 0;  // 0 when absent
  PixelLayout layout;
  std::string transfer_syntax_uid;
  // Enhanced multi-frame objects: one entry per frame (NumberOfFrames);
  // empty for single-frame images, whose geometry is in the fields above.
  std::vector<FrameGeometry> frames;
};

// The file's base name: the only part of a path that goes into messages
// (folder names of PACS exports often hold patient names).
std::string BaseName(const std::string& path);

// Reads the header of `path` (values longer than kHeaderMaxReadLength are
// left on disk) and classifies it. Never fails: problems are recorded in the
// result.
FileHeader ScanFile(const std::string& path);

// Reads and checks the Image Pixel module attributes of `item`. `name` is the
// file's base name for messages. UNIMPLEMENTED for colour, palette or
// unsupported bit depths; INVALID_ARGUMENT for inconsistent values.
absl::StatusOr<PixelLayout> ReadPixelLayout(DcmItem& item,
                                            const std::string& name);

}  // namespace dicom_internal
}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_DICOM_HEADER_H_

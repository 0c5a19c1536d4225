#include "core/labels/label_map_io.h"

#include <algorithm>
#include <filesystem>
#include <utility>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/labels/segment_names.h"

namespace interslice {
namespace {

std::string FileName(const std::string& path) {
  return std::filesystem::path(path).filename().string();
}

template <typename T>
Volume<T> Narrowed(const LabelVolume& labels) {
  Volume<T> out;
  out.grid = labels.grid;
  out.data.assign(labels.data.begin(), labels.data.end());
  return out;
}

}  // namespace

absl::StatusOr<LabelMapOnReference> ReadLabelMapOnReference(
    const std::string& path, const Grid& reference) {
  const std::string name = FileName(path);
  LabelMapOnReference out;
  INTERSLICE_ASSIGN_OR_RETURN(out.file.header, ReadVolumeFileHeader(path));
  const VolumeFileHeader& header = out.file.header;
  if (header.nifti && ((header.scl_slope != 0 && header.scl_slope != 1) ||
                       (header.scl_slope != 0 && header.scl_inter != 0))) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "the label map %s scales its voxel values (scl_slope %g, scl_inter "
        "%g); a label map stores its labels unscaled",
        name, header.scl_slope, header.scl_inter));
  }
  // Overlapping segments of a Slicer segmentation (stored in layers) are
  // named as such rather than as a 4D volume.
  if (absl::Status s = SegmentsFromSlicerFields(header.key_values).status();
      !s.ok()) {
    return absl::Status(s.code(), absl::StrCat(name, ": ", s.message()));
  }
  INTERSLICE_ASSIGN_OR_RETURN(
      out.file.mapping,
      MatchGridToReference(header.grid, reference, "the label map"));
  absl::StatusOr<Volume<float>> raw = ReadVolumeAsFloat(path);
  if (!raw.ok()) return raw.status();
  // Labels are checked in the file's own layout, so a bad voxel is named by
  // the index a user's viewer shows for it.
  absl::StatusOr<LabelVolume> labels = LabelVolumeFromFloat(*raw);
  if (!labels.ok()) {
    return absl::Status(labels.status().code(),
                        absl::StrCat(name, ": ", labels.status().message()));
  }
  if (out.file.mapping.IsIdentity()) {
    out.labels = *std::move(labels);
    out.labels.grid = reference;
  } else {
    out.labels = ToReferenceLayout(*labels, out.file.mapping, reference);
  }
  return out;
}

absl::Status WriteLabelMapLike(const LabelVolume& labels,
                               const LabelMapFile& file,
                               const std::string& path,
                               const ComputeContext& context) {
  LabelVolume in_file_layout =
      ToFileLayout(labels, file.mapping, file.header.grid);
  VolumeHeaderFields fields;
  if (file.header.nifti) {
    fields.qform_code = file.header.qform_code;
    fields.sform_code = file.header.sform_code;
  }
  for (const auto& [key, value] : file.header.key_values) {
    // Slicer's segment extent (voxel bounds of a segment) would contradict
    // the filled segment; without it Slicer takes the whole volume.
    if (absl::StartsWith(key, "Segment") && absl::EndsWith(key, "_Extent")) {
      continue;
    }
    fields.key_values.emplace_back(key, value);
  }
  const uint16_t largest = in_file_layout.data.empty()
                               ? 0
                               : *std::max_element(in_file_layout.data.begin(),
                                                   in_file_layout.data.end());
  const std::string& type = file.header.component_type;
  if (type == "unsigned_char" && largest <= 255) {
    return WriteVolume(Narrowed<uint8_t>(in_file_layout), path, fields,
                       context);
  }
  if (type == "short" && largest <= 32767) {
    return WriteVolume(Narrowed<int16_t>(in_file_layout), path, fields,
                       context);
  }
  return WriteVolume(in_file_layout, path, fields, context);
}

}  // namespace interslice

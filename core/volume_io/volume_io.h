// Research volume formats through ITK: NIfTI (.nii, .nii.gz) and NRRD
// (.nrrd). Geometry is written and read exactly as held by Grid (ITK keeps
// LPS internally and converts to RAS for NIfTI itself).
#ifndef INTERSLICE_CORE_VOLUME_IO_VOLUME_IO_H_
#define INTERSLICE_CORE_VOLUME_IO_VOLUME_IO_H_

#include <cstdint>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"

namespace interslice {

// The format follows the extension: .nii.gz / .nii (NIfTI-1) or .nrrd
// (gzip-encoded NRRD). INVALID_ARGUMENT for another extension (or a NIfTI
// axis over 32767 voxels); INTERNAL with the path and the reason when writing
// fails; CANCELLED / DEADLINE_EXCEEDED when context.cancel fires. The file
// appears complete or not at all (written to a temporary name, then renamed).
//
// Compression (.nii.gz, .nrrd) uses context.threads threads (0 = all):
// 4 MiB blocks deflated in parallel. A .nii.gz is a series of gzip members
// (libdeflate level 1; every gzip reader reads all members); a .nrrd's data
// are one gzip member (zlib run-length blocks joined as pigz does), for
// readers that stop after one member. The decompressed bytes are exactly
// what ITK writes uncompressed (header from ITK, voxels as held in memory).
absl::Status WriteVolume(const Volume<float>& volume, const std::string& path,
                         const ComputeContext& context = {});
absl::Status WriteVolume(const Volume<uint8_t>& volume, const std::string& path,
                         const ComputeContext& context = {});
absl::Status WriteVolume(const Volume<uint16_t>& volume,  // label maps
                         const std::string& path,
                         const ComputeContext& context = {});

// Reads a scalar volume written by WriteVolume (any scalar type, converted).
absl::StatusOr<Volume<float>> ReadVolumeAsFloat(const std::string& path);

// What a volume file's header says, for writing a result back in the layout
// and header of its input (label maps, issue 24; core/volume_io/layout.h).
struct VolumeFileHeader {
  bool nifti = false;  // else NRRD
  // The geometry as ITK reads it (LPS; for NIfTI from the sform when its
  // code is set, else the qform, as ITK decides).
  Grid grid;
  // ITK's name of the voxel type: "unsigned_char", "short", "float", ...
  std::string component_type;
  bool integer_type = false;
  // NIfTI: qform_code and sform_code (nifti1.h: 0 unknown, 1 scanner, 2
  // aligned, 3 Talairach, 4 MNI, 5 template) and the value scaling
  // (scl_slope 0 means none).
  int qform_code = 0, sform_code = 0;
  double scl_slope = 0, scl_inter = 0;
  // NRRD: the "space" field as written (e.g. "left-posterior-superior",
  // "RAS"; empty without one) and the "key:=value" fields in file order
  // (Slicer's segment metadata among them).
  std::string nrrd_space;
  std::vector<std::pair<std::string, std::string>> key_values;
};

// INVALID_ARGUMENT / NOT_FOUND as ReadVolumeAsFloat, plus a NIfTI header
// that is not NIfTI-1 (348 bytes).
absl::StatusOr<VolumeFileHeader> ReadVolumeFileHeader(const std::string& path);

// Header fields a written file takes over from another file (WriteVolume
// below). Fields of the other format are ignored.
struct VolumeHeaderFields {
  // NIfTI: written instead of ITK's (which sets both to 1, scanner).
  std::optional<int> qform_code, sform_code;
  // NRRD: written as "key:=value" lines.
  std::vector<std::pair<std::string, std::string>> key_values;
};

// WriteVolume with `fields` in the header (label maps in their input's
// header). INVALID_ARGUMENT for a qform/sform code outside 0..5 or a key or
// value with a newline, besides WriteVolume's errors.
absl::Status WriteVolume(const Volume<uint8_t>& volume, const std::string& path,
                         const VolumeHeaderFields& fields,
                         const ComputeContext& context = {});
absl::Status WriteVolume(const Volume<int16_t>& volume, const std::string& path,
                         const VolumeHeaderFields& fields,
                         const ComputeContext& context = {});
absl::Status WriteVolume(const Volume<uint16_t>& volume,
                         const std::string& path,
                         const VolumeHeaderFields& fields,
                         const ComputeContext& context = {});

}  // namespace interslice

#endif  // INTERSLICE_CORE_VOLUME_IO_VOLUME_IO_H_

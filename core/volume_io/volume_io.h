// Research volume formats through ITK: NIfTI (.nii, .nii.gz) and NRRD
// (.nrrd). Geometry is written and read exactly as held by Grid (ITK keeps
// LPS internally and converts to RAS for NIfTI itself).
#ifndef INTERSLICE_CORE_VOLUME_IO_VOLUME_IO_H_
#define INTERSLICE_CORE_VOLUME_IO_VOLUME_IO_H_

#include <cstdint>
#include <string>

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

}  // namespace interslice

#endif  // INTERSLICE_CORE_VOLUME_IO_VOLUME_IO_H_

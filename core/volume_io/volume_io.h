// Research volume formats through ITK: NIfTI (.nii, .nii.gz) and NRRD
// (.nrrd). Geometry is written and read exactly as held by Grid (ITK keeps
// LPS internally and converts to RAS for NIfTI itself).
#ifndef INTERSLICE_CORE_VOLUME_IO_VOLUME_IO_H_
#define INTERSLICE_CORE_VOLUME_IO_VOLUME_IO_H_

#include <cstdint>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/geometry/volume.h"

namespace interslice {

// The format follows the extension: .nii.gz / .nii (NIfTI-1) or .nrrd
// (compressed NRRD). INVALID_ARGUMENT for another extension; INTERNAL with
// the path and ITK's reason when writing fails. The file appears complete or
// not at all (written to a temporary name, then renamed).
absl::Status WriteVolume(const Volume<float>& volume, const std::string& path);
absl::Status WriteVolume(const Volume<uint8_t>& volume,
                         const std::string& path);
absl::Status WriteVolume(const Volume<uint16_t>& volume,  // label maps
                         const std::string& path);

// Reads a scalar volume written by WriteVolume (any scalar type, converted).
absl::StatusOr<Volume<float>> ReadVolumeAsFloat(const std::string& path);

}  // namespace interslice

#endif  // INTERSLICE_CORE_VOLUME_IO_VOLUME_IO_H_

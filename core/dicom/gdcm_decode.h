// Private to core/dicom: the fallback decoder for transfer syntaxes DCMTK's
// free edition cannot decode (JPEG 2000), through GDCM. Kept in its own file
// so that GDCM's headers never meet DCMTK's.
#ifndef INTERSLICE_CORE_DICOM_GDCM_DECODE_H_
#define INTERSLICE_CORE_DICOM_GDCM_DECODE_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace interslice {
namespace dicom_internal {

// Transfer syntaxes DecodeWithGdcm is used for: JPEG 2000 Image Compression
// (Lossless Only) 1.2.840.10008.1.2.4.90 and JPEG 2000 1.2.840.10008.1.2.4.91.
bool IsGdcmFallbackSyntax(const std::string& transfer_syntax_uid);

// Decodes every frame of `path` with GDCM into little-endian stored values,
// frame after frame (frames * rows * columns samples of bits_allocated / 8
// bytes). INVALID_ARGUMENT naming `name` when GDCM cannot read or decode the
// file or when the decoded image does not have the expected size or sample
// width (checked before the buffer is allocated).
absl::StatusOr<std::vector<uint8_t>> DecodeWithGdcm(const std::string& path,
                                                    const std::string& name,
                                                    int rows, int columns,
                                                    int64_t frames,
                                                    int bits_allocated);

}  // namespace dicom_internal
}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_GDCM_DECODE_H_

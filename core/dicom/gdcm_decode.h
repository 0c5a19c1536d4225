// Private to core/dicom: the fallback decoder for transfer syntaxes DCMTK's
// free edition cannot decode (JPEG 2000), through GDCM's JPEG 2000 codec.
// Kept in its own file so that GDCM's headers never meet DCMTK's.
//
// GDCM sees only the codestream of one frame, never the DICOM file: its
// file-level reader (gdcm::ImageReader) interprets dozens of attributes with
// assert()s that abort the process on values a hostile or broken file can
// hold (empty RescaleSlope, PixelSpacing with another VR, ...), and its codec
// trusts the codestream's size, component count and precision to match the
// buffer it allocates from the header. The reader validates the header
// itself (dicom_header.h) and CheckJpeg2000Codestream below validates the
// codestream before GDCM decodes it.
#ifndef INTERSLICE_CORE_DICOM_GDCM_DECODE_H_
#define INTERSLICE_CORE_DICOM_GDCM_DECODE_H_

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace interslice {
namespace dicom_internal {

// Transfer syntaxes DecodeJpeg2000Frame is used for: JPEG 2000 Image
// Compression (Lossless Only) 1.2.840.10008.1.2.4.90 and JPEG 2000
// 1.2.840.10008.1.2.4.91.
bool IsGdcmFallbackSyntax(const std::string& transfer_syntax_uid);

// How the header says a frame's samples are stored.
struct Jpeg2000Target {
  int rows = 0;
  int columns = 0;
  int bits_allocated = 16;
  int bits_stored = 16;
  bool is_signed = false;
};

// OK when `data` is a JPEG 2000 codestream (PS3.5 A.4.4: no JP2 file
// wrapper) whose SIZ marker describes one component of target.columns x
// target.rows samples, without subsampling, whose precision needs
// target.bits_allocated bits per sample, in at most 4096 tiles; and whose
// marker segments up to the first tile's data stay within `data` (GDCM walks
// them without bounds checks). INVALID_ARGUMENT naming `name` otherwise.
absl::Status CheckJpeg2000Codestream(const uint8_t* data, size_t size,
                                     const std::string& name,
                                     const Jpeg2000Target& target);

// Checks (above) and decodes one frame with GDCM into little-endian stored
// values: rows * columns samples of bits_allocated / 8 bytes. INVALID_ARGUMENT
// naming `name` when the codestream is refused or does not decode.
absl::StatusOr<std::vector<uint8_t>> DecodeJpeg2000Frame(
    const uint8_t* data, size_t size, const std::string& name,
    const Jpeg2000Target& target);

}  // namespace dicom_internal
}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_GDCM_DECODE_H_

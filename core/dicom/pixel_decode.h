// Part of the DICOM series reader (series_reader.h): from one scanned file
// (dicom_header.h FileHeader) to the modality values of some of its frames.
//
// Decoding: native pixel data (implicit/explicit little endian, explicit big
// endian, deflated) and what a registered DCMTK codec decodes (JPEG
// baseline, extended and lossless, JPEG-LS, RLE) through DCMTK, which
// decodes every frame of the file; JPEG 2000 (1.2.840.10008.1.2.4.90/.91)
// through GDCM (gdcm_decode.h), used only when DCMTK cannot decode, one
// asked-for frame's codestream at a time, one fragment per frame when there
// are several frames. Anything else: UNIMPLEMENTED naming the syntax.
//
// Values: stored value (the BitsStored bits at HighBit, sign-extended when
// PixelRepresentation is 1; other bits, e.g. overlays, ignored) *
// RescaleSlope + RescaleIntercept, with the rescale of the frame (its
// functional groups, multi-frame files) or of the file (single frame), as
// float. Units are those of the modality (HU for CT).
#ifndef INTERSLICE_CORE_DICOM_PIXEL_DECODE_H_
#define INTERSLICE_CORE_DICOM_PIXEL_DECODE_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "core/dicom/dicom_header.h"

namespace interslice {

struct TransferSyntaxInfo {
  std::string uid;
  std::string name;
};

// The transfer syntaxes this reader decodes: the uncompressed and deflated
// ones, those a registered DCMTK codec can decode (JPEG, JPEG-LS, RLE), and
// JPEG 2000 through GDCM. Computed from the codec registry, so it stays true.
std::vector<TransferSyntaxInfo> DecodableTransferSyntaxes();

// Registers DCMTK's JPEG, JPEG-LS and RLE decoders; idempotent and
// thread-safe (ReadDicomSeries and DecodeDicomFrames call it).
void RegisterDicomDecoders();

// One frame to decode and where its values go.
struct DicomFrameTarget {
  int frame = 0;         // 0-based frame number in the file (0: single frame)
  float* out = nullptr;  // Columns x Rows values, row after row
};

// INVALID_ARGUMENT when decoding the file of `header` needs more than
// `max_voxels` samples: DCMTK's decoders decode every frame of a file, those
// not asked for included, so Rows x Columns x NumberOfFrames bounds what a
// decode allocates, whatever frames are used.
absl::Status CheckDecodedSize(const dicom_internal::FileHeader& header,
                              int64_t max_voxels);

// Loads the file of `header` (a FileKind::kImage header without a problem,
// from ScanFile) again and writes the modality values of each target's
// frame to its `out`. The file is checked against the header first: its
// sequence depth (dicom_header.h), Rows/Columns (a file that changed since
// it was scanned), the pixel module (ReadPixelLayout), and native pixel data
// against Rows x Columns x frames before it is read.
// Errors (messages name the file by base name, and the frame for JPEG 2000
// frames of multi-frame files): the header's own problem, or
// INVALID_ARGUMENT for a header that is not an image, a frame outside
// [0, NumberOfFrames) or a null `out`; INVALID_ARGUMENT for a truncated or
// unreadable file, missing or short pixel data, fewer fragments than frames,
// or a JPEG 2000 codestream GDCM must not see (gdcm_decode.h);
// UNIMPLEMENTED for an undecodable transfer syntax or pixel module
// (ReadPixelLayout). On error, targets may be partly written.
// Threading: safe to call concurrently for different targets (each call
// reads its own copy of the file); registers the decoders once.
absl::Status DecodeDicomFrames(const dicom_internal::FileHeader& header,
                               const std::vector<DicomFrameTarget>& targets);

}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_PIXEL_DECODE_H_

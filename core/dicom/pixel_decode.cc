#include "core/dicom/pixel_decode.h"

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <mutex>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/dicom/gdcm_decode.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dccodec.h"
#include "dcmtk/dcmdata/dcdatset.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcpixel.h"
#include "dcmtk/dcmdata/dcpixseq.h"
#include "dcmtk/dcmdata/dcpxitem.h"
#include "dcmtk/dcmdata/dcrledrg.h"
#include "dcmtk/dcmdata/dcxfer.h"
#include "dcmtk/dcmjpeg/djdecode.h"
#include "dcmtk/dcmjpls/djdecode.h"

namespace interslice {
namespace {

using dicom_internal::BaseName;
using dicom_internal::FileHeader;
using dicom_internal::FileKind;
using dicom_internal::PixelLayout;

// Stored values (little-endian bytes as DCMTK hands them out) to modality
// values.
template <int kBytes>
void ConvertPixels(const Uint8* bytes, int64_t count, const PixelLayout& l,
                   double slope, double intercept, float* out) {
  const int shift = l.high_bit + 1 - l.bits_stored;
  const uint32_t mask =
      l.bits_stored == 32 ? 0xffffffffu : (uint32_t{1} << l.bits_stored) - 1;
  const uint32_t sign_bit = uint32_t{1} << (l.bits_stored - 1);
  const int64_t wrap = int64_t{1} << l.bits_stored;
  for (int64_t i = 0; i < count; ++i) {
    const Uint8* p = bytes + i * kBytes;
    uint32_t raw = p[0];
    if constexpr (kBytes >= 2) raw |= uint32_t{p[1]} << 8;
    if constexpr (kBytes == 4) {
      raw |= uint32_t{p[2]} << 16 | uint32_t{p[3]} << 24;
    }
    // Bits outside BitsStored may hold overlays or garbage.
    const uint32_t value = (raw >> shift) & mask;
    int64_t stored = value;
    if (l.is_signed && (value & sign_bit) != 0) stored -= wrap;
    out[i] =
        static_cast<float>(static_cast<double>(stored) * slope + intercept);
  }
}

// The rescale of frame `frame` of the file: its functional groups for
// multi-frame files, the file's own for single frames.
void FrameRescale(const FileHeader& h, int frame, double& slope,
                  double& intercept) {
  if (h.frames.empty()) {
    slope = h.rescale_slope;
    intercept = h.rescale_intercept;
  } else {
    slope = h.frames[frame].rescale_slope;
    intercept = h.frames[frame].rescale_intercept;
  }
}

void ConvertFrame(const Uint8* src, int64_t samples, const PixelLayout& layout,
                  const FileHeader& h, int frame, float* out) {
  double slope = 1, intercept = 0;
  FrameRescale(h, frame, slope, intercept);
  switch (layout.bits_allocated) {
    case 8:
      ConvertPixels<1>(src, samples, layout, slope, intercept, out);
      break;
    case 16:
      ConvertPixels<2>(src, samples, layout, slope, intercept, out);
      break;
    default:
      ConvertPixels<4>(src, samples, layout, slope, intercept, out);
      break;
  }
}

// The JPEG 2000 codestream of frame `frame` (0-based) of `frames`: with one
// frame, all fragments together; with several, one fragment per frame (as
// GDCM requires, and as writers do; frames split over fragments are refused
// rather than guessed from the offset table).
absl::Status Jpeg2000FrameBytes(DcmDataset& ds, const std::string& name,
                                int64_t frames, int frame,
                                std::vector<uint8_t>& out) {
  out.clear();
  DcmElement* element = nullptr;
  ds.findAndGetElement(DCM_PixelData, element);
  DcmPixelData* pixels = dynamic_cast<DcmPixelData*>(element);
  DcmPixelSequence* sequence = nullptr;
  if (pixels != nullptr) {
    E_TransferSyntax xfer = EXS_Unknown;
    const DcmRepresentationParameter* param = nullptr;
    pixels->getOriginalRepresentationKey(xfer, param);
    pixels->getEncapsulatedRepresentation(xfer, param, sequence);
  }
  if (sequence == nullptr || sequence->card() < 2) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": no encapsulated JPEG 2000 pixel data"));
  }
  // The first item is the basic offset table.
  const unsigned long fragments = sequence->card() - 1;
  if (frames > 1 && fragments != static_cast<unsigned long>(frames)) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s: %d JPEG 2000 fragments for %d frames; frames split over several "
        "fragments are not supported",
        name, fragments, frames));
  }
  auto append = [&](unsigned long index) -> absl::Status {
    DcmPixelItem* item = nullptr;
    if (sequence->getItem(item, index).bad() || item == nullptr) {
      return absl::InvalidArgumentError(
          absl::StrCat(name, ": missing pixel data fragment"));
    }
    const Uint32 length = item->getLength();
    if (length == 0) return absl::OkStatus();
    Uint8* bytes = nullptr;
    if (item->getUint8Array(bytes).bad() || bytes == nullptr) {
      return absl::InvalidArgumentError(absl::StrCat(
          name, ": cannot read a pixel data fragment; truncated file?"));
    }
    out.insert(out.end(), bytes, bytes + length);
    return absl::OkStatus();
  };
  if (frames > 1) return append(static_cast<unsigned long>(frame) + 1);
  for (unsigned long i = 1; i <= fragments; ++i) {
    INTERSLICE_RETURN_IF_ERROR(append(i));
  }
  return absl::OkStatus();
}

// Decodes the asked-for frames of a JPEG 2000 file (GDCM, one frame at a
// time, so that memory stays bounded by one frame whatever NumberOfFrames
// says).
absl::Status DecodeJpeg2000Frames(DcmDataset& ds, const FileHeader& h,
                                  const std::vector<DicomFrameTarget>& targets,
                                  const PixelLayout& layout) {
  const std::string name = BaseName(h.path);
  const int64_t frames = h.frames.empty() ? 1 : h.frames.size();
  const int64_t frame_samples = int64_t{h.rows} * h.columns;
  // Decoded samples are plain values: HighBit plays no part.
  PixelLayout decoded_layout = layout;
  decoded_layout.high_bit = layout.bits_stored - 1;
  const dicom_internal::Jpeg2000Target j2k = {
      .rows = h.rows,
      .columns = h.columns,
      .bits_allocated = layout.bits_allocated,
      .bits_stored = layout.bits_stored,
      .is_signed = layout.is_signed};
  std::vector<uint8_t> codestream;
  for (const DicomFrameTarget& target : targets) {
    const std::string frame_name =
        frames > 1 ? absl::StrCat(name, " frame ", target.frame + 1) : name;
    INTERSLICE_RETURN_IF_ERROR(
        Jpeg2000FrameBytes(ds, frame_name, frames, target.frame, codestream));
    INTERSLICE_ASSIGN_OR_RETURN(
        const std::vector<uint8_t> decoded,
        dicom_internal::DecodeJpeg2000Frame(
            codestream.data(), codestream.size(), frame_name, j2k));
    ConvertFrame(decoded.data(), frame_samples, decoded_layout, h, target.frame,
                 target.out);
  }
  return absl::OkStatus();
}

}  // namespace

void RegisterDicomDecoders() {
  static std::once_flag once;
  // DCMTK's codec registry is process-wide; registering twice would add
  // duplicate codecs.
  std::call_once(once, [] {
    DJDecoderRegistration::registerCodecs();
    DJLSDecoderRegistration::registerCodecs();
    DcmRLEDecoderRegistration::registerCodecs();
  });
}

std::vector<TransferSyntaxInfo> DecodableTransferSyntaxes() {
  RegisterDicomDecoders();
  static constexpr E_TransferSyntax kNative[] = {
      EXS_LittleEndianImplicit, EXS_LittleEndianExplicit,
      EXS_DeflatedLittleEndianExplicit, EXS_BigEndianExplicit};
  static constexpr E_TransferSyntax kEncapsulated[] = {
      EXS_JPEGProcess1,     EXS_JPEGProcess2_4,       EXS_JPEGProcess14,
      EXS_JPEGProcess14SV1, EXS_JPEGLSLossless,       EXS_JPEGLSLossy,
      EXS_RLELossless,      EXS_JPEG2000LosslessOnly, EXS_JPEG2000};
  std::vector<TransferSyntaxInfo> out;
  auto add = [&out](E_TransferSyntax xfer) {
    const DcmXfer x(xfer);
    out.push_back({x.getXferID(), x.getXferName()});
  };
  for (E_TransferSyntax xfer : kNative) add(xfer);
  for (E_TransferSyntax xfer : kEncapsulated) {
    if (DcmCodecList::canChangeCoding(xfer, EXS_LittleEndianExplicit) ||
        dicom_internal::IsGdcmFallbackSyntax(DcmXfer(xfer).getXferID())) {
      add(xfer);
    }
  }
  return out;
}

absl::Status CheckDecodedSize(const FileHeader& header, int64_t max_voxels) {
  const int64_t frames = std::max<int64_t>(1, header.frames.size());
  const int64_t file_voxels = int64_t{header.rows} * header.columns * frames;
  if (file_voxels > max_voxels) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s holds %d x %d x %d = %d voxels in all its frames, more than the "
        "limit of %d (max_voxels)",
        BaseName(header.path), header.columns, header.rows, frames, file_voxels,
        max_voxels));
  }
  return absl::OkStatus();
}

absl::Status DecodeDicomFrames(const FileHeader& h,
                               const std::vector<DicomFrameTarget>& targets) {
  const std::string name = BaseName(h.path);
  INTERSLICE_RETURN_IF_ERROR(h.problem);
  if (h.kind != FileKind::kImage) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": not an image slice"));
  }
  const int64_t frames = h.frames.empty() ? 1 : h.frames.size();
  for (const DicomFrameTarget& target : targets) {
    if (target.frame < 0 || target.frame >= frames || target.out == nullptr) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s: cannot decode frame %d of %d%s", name, target.frame + 1, frames,
          target.out == nullptr ? " into no buffer" : ""));
    }
  }
  RegisterDicomDecoders();
  // The file may have changed since its header was scanned.
  INTERSLICE_RETURN_IF_ERROR(dicom_internal::CheckSequenceDepth(h.path));
  DcmFileFormat file;
  // The default read limit leaves the pixel data on disk until it is
  // accessed below, which is all that is needed.
  OFCondition cond = file.loadFile(OFFilename(h.path.c_str()));
  if (cond.bad()) {
    return absl::InvalidArgumentError(absl::StrCat(
        name, ": truncated or unreadable DICOM file (", cond.text(), ")"));
  }
  DcmDataset& ds = *file.getDataset();
  const int64_t frame_samples = int64_t{h.rows} * h.columns;
  // Decoders may rewrite the pixel module: check again against what was
  // planned.
  Uint16 rows = 0, columns = 0;
  ds.findAndGetUint16(DCM_Rows, rows);
  ds.findAndGetUint16(DCM_Columns, columns);
  if (rows != h.rows || columns != h.columns) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": Rows/Columns changed while reading"));
  }
  INTERSLICE_ASSIGN_OR_RETURN(const PixelLayout layout,
                              dicom_internal::ReadPixelLayout(ds, name));
  const int64_t needed = frames * frame_samples * (layout.bits_allocated / 8);

  const E_TransferSyntax xfer = ds.getOriginalXfer();
  if (DcmXfer(xfer).isEncapsulated()) {
    cond = ds.chooseRepresentation(EXS_LittleEndianExplicit, nullptr);
    if (cond.bad() || !ds.canWriteXfer(EXS_LittleEndianExplicit)) {
      if (!dicom_internal::IsGdcmFallbackSyntax(h.transfer_syntax_uid)) {
        return absl::UnimplementedError(absl::StrCat(
            name, ": cannot decode pixel data in transfer syntax '",
            DcmXfer(xfer).getXferName(), "' (", h.transfer_syntax_uid, ")",
            cond.bad() ? absl::StrCat(": ", cond.text()) : ""));
      }
      return DecodeJpeg2000Frames(ds, h, targets, layout);
    }
  }
  DcmElement* pixels = nullptr;
  if (ds.findAndGetElement(DCM_PixelData, pixels).bad() || pixels == nullptr) {
    return absl::InvalidArgumentError(absl::StrCat(name, ": no pixel data"));
  }
  Uint8* bytes = nullptr;
  cond = pixels->getUint8Array(bytes);
  if (cond.bad() || bytes == nullptr) {
    return absl::InvalidArgumentError(absl::StrCat(
        name, ": cannot read pixel data (",
        cond.bad() ? cond.text() : "no value", "); truncated file?"));
  }
  const Uint32 element_length = pixels->getLength();
  const int64_t length =
      element_length == DCM_UndefinedLength ? 0 : element_length;
  if (length < needed) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s: pixel data is too short: %d bytes, but %d frame(s) of %d x %d "
        "pixels of %d bits need %d",
        name, length, frames, h.columns, h.rows, layout.bits_allocated,
        needed));
  }
  const int64_t frame_bytes = frame_samples * (layout.bits_allocated / 8);
  for (const DicomFrameTarget& target : targets) {
    ConvertFrame(bytes + target.frame * frame_bytes, frame_samples, layout, h,
                 target.frame, target.out);
  }
  return absl::OkStatus();
}

}  // namespace interslice

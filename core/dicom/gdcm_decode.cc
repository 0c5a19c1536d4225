#include "core/dicom/gdcm_decode.h"

#include <cstring>
#include <exception>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "gdcmDataElement.h"
#include "gdcmFragment.h"
#include "gdcmJPEG2000Codec.h"
#include "gdcmPhotometricInterpretation.h"
#include "gdcmPixelFormat.h"
#include "gdcmSequenceOfFragments.h"

namespace interslice {
namespace dicom_internal {
namespace {

// More tiles than this are refused: OpenJPEG allocates a few kilobytes of
// coding parameters per tile before it reads any tile data, so a SIZ marker
// with 1 x 1 tiles would cost gigabytes. Real images use one tile or a few.
constexpr uint64_t kMaxTiles = 4096;

constexpr uint16_t kSoc = 0xff4f, kSiz = 0xff51, kCod = 0xff52, kSod = 0xff93,
                   kEoc = 0xffd9, kEph = 0xff92;

uint16_t Be16(const uint8_t* p) { return uint16_t(p[0] << 8 | p[1]); }
uint32_t Be32(const uint8_t* p) {
  return uint32_t{p[0]} << 24 | uint32_t{p[1]} << 16 | uint32_t{p[2]} << 8 |
         p[3];
}

// Markers without a length field, as GDCM's parsej2k_imp lists them.
bool HasNoLength(uint16_t marker) {
  return (marker >= 0xff30 && marker <= 0xff3f) || marker == kSoc ||
         marker == kSod || marker == kEoc || marker == kEph;
}

// After decoding, GDCM walks the codestream's marker segments again
// (gdcmJPEG2000Codec.cxx, parsej2k_imp) to learn whether it is lossless, and
// trusts every length field and the COD segment's size. This repeats that
// walk with bounds checks: true when it stays within the data.
bool GdcmMarkerWalkStaysInBounds(const uint8_t* data, size_t size) {
  size_t pos = 0;
  while (pos + 2 <= size) {
    const uint16_t marker = Be16(data + pos);
    pos += 2;
    if (HasNoLength(marker)) {
      if (marker == kSod) return true;
      continue;
    }
    if (pos + 2 > size) return true;  // GDCM stops here
    const uint16_t length = Be16(data + pos);
    pos += 2;
    if (length < 2) return true;  // GDCM stops here
    const size_t body = length - 2;
    if (marker == kCod) {
      // GDCM reads bytes 4 and 9 of the segment whatever its length.
      if (pos + 10 > size) return false;
      if (data[pos + 4] > 1) return true;   // GDCM stops: invalid MCT
      if (data[pos + 9] != 1) return true;  // GDCM stops: lossy or invalid
    }
    if (body > size - pos) return false;
    pos += body;
  }
  return true;
}

}  // namespace

bool IsGdcmFallbackSyntax(const std::string& transfer_syntax_uid) {
  return transfer_syntax_uid == "1.2.840.10008.1.2.4.90" ||
         transfer_syntax_uid == "1.2.840.10008.1.2.4.91";
}

absl::Status CheckJpeg2000Codestream(const uint8_t* data, size_t size,
                                     const std::string& name,
                                     const Jpeg2000Target& target) {
  auto refuse = [&name](const std::string& why) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": JPEG 2000 pixel data refused: ", why));
  };
  // SOC, then SIZ with one component: 4 + 41 bytes.
  constexpr size_t kSizEnd = 4 + 38;
  if (size < kSizEnd + 3 || Be16(data) != kSoc || Be16(data + 2) != kSiz) {
    return refuse(
        "not a JPEG 2000 codestream (no SOC and SIZ markers at its start; a "
        "JP2 file wrapper is not allowed in DICOM)");
  }
  const uint8_t* siz = data + 4;
  const uint16_t length = Be16(siz);
  const uint32_t x = Be32(siz + 4), y = Be32(siz + 8);
  const uint32_t x0 = Be32(siz + 12), y0 = Be32(siz + 16);
  const uint32_t tile_x = Be32(siz + 20), tile_y = Be32(siz + 24);
  const uint32_t tile_x0 = Be32(siz + 28), tile_y0 = Be32(siz + 32);
  const uint16_t components = Be16(siz + 36);
  if (components != 1) {
    return refuse(absl::StrCat("the codestream has ", components,
                               " components; only greyscale (1) is "
                               "supported"));
  }
  if (length != 41) {
    return refuse(absl::StrCat("invalid SIZ marker length ", length));
  }
  if (x0 >= x || y0 >= y || x - x0 != static_cast<uint32_t>(target.columns) ||
      y - y0 != static_cast<uint32_t>(target.rows)) {
    return refuse(absl::StrFormat(
        "the codestream is %d x %d samples but the header says %d x %d "
        "(Columns x Rows)",
        int64_t{x} - x0, int64_t{y} - y0, target.columns, target.rows));
  }
  const uint8_t precision_byte = siz[38];
  if (siz[39] != 1 || siz[40] != 1) {
    return refuse("subsampled components are not supported");
  }
  if (tile_x == 0 || tile_y == 0 || tile_x0 > x0 || tile_y0 > y0) {
    return refuse("invalid tile grid");
  }
  const uint64_t tiles = (uint64_t{x} - tile_x0 + tile_x - 1) / tile_x *
                         ((uint64_t{y} - tile_y0 + tile_y - 1) / tile_y);
  if (tiles > kMaxTiles) {
    return refuse(
        absl::StrCat(tiles, " tiles (at most ", kMaxTiles, " are accepted)"));
  }
  // GDCM writes each decoded sample in 1, 2 or 4 bytes by the codestream's
  // precision, into a buffer sized by BitsAllocated: the two must agree.
  const int precision = (precision_byte & 0x7f) + 1;
  const int sample_bits = precision <= 8 ? 8 : precision <= 16 ? 16 : 32;
  if (precision > 32 || sample_bits != target.bits_allocated) {
    return refuse(absl::StrCat("the codestream's ", precision,
                               "-bit samples do not fit BitsAllocated ",
                               target.bits_allocated));
  }
  if (!GdcmMarkerWalkStaysInBounds(data, size)) {
    return refuse("a marker segment runs past the end of the data");
  }
  return absl::OkStatus();
}

absl::StatusOr<std::vector<uint8_t>> DecodeJpeg2000Frame(
    const uint8_t* data, size_t size, const std::string& name,
    const Jpeg2000Target& target) {
  if (absl::Status ok = CheckJpeg2000Codestream(data, size, name, target);
      !ok.ok()) {
    return ok;
  }
  if (size > UINT32_MAX - 1) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": JPEG 2000 frame larger than 4 GiB"));
  }
  const size_t expected = size_t(target.rows) * size_t(target.columns) *
                          size_t(target.bits_allocated / 8);
  try {
    gdcm::JPEG2000Codec codec;
    // The reader already decodes files in parallel, with the caller's thread
    // count; OpenJPEG would otherwise start one thread per CPU per frame.
    codec.SetNumberOfThreadsForDecompression(0);
    codec.SetNumberOfDimensions(2);
    const unsigned int dims[3] = {static_cast<unsigned int>(target.columns),
                                  static_cast<unsigned int>(target.rows), 1};
    codec.SetDimensions(dims);
    codec.SetPixelFormat(
        gdcm::PixelFormat(1, static_cast<unsigned short>(target.bits_allocated),
                          static_cast<unsigned short>(target.bits_stored),
                          static_cast<unsigned short>(target.bits_stored - 1),
                          target.is_signed ? 1 : 0));
    codec.SetPhotometricInterpretation(
        gdcm::PhotometricInterpretation::MONOCHROME2);
    codec.SetPlanarConfiguration(0);

    gdcm::SmartPointer<gdcm::SequenceOfFragments> fragments =
        new gdcm::SequenceOfFragments;
    gdcm::Fragment fragment;
    fragment.SetByteValue(reinterpret_cast<const char*>(data),
                          gdcm::VL(static_cast<uint32_t>(size)));
    fragments->AddFragment(fragment);
    gdcm::DataElement in(gdcm::Tag(0x7fe0, 0x0010));
    in.SetVR(gdcm::VR::OB);
    in.SetValue(*fragments);
    gdcm::DataElement out;
    if (!codec.Decode(in, out)) {
      return absl::InvalidArgumentError(
          absl::StrCat(name, ": GDCM cannot decode the JPEG 2000 codestream"));
    }
    const gdcm::ByteValue* decoded = out.GetByteValue();
    // GDCM pads odd lengths to even.
    if (decoded == nullptr || decoded->GetLength() < expected ||
        decoded->GetLength() > expected + 1) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s: GDCM decoded %d bytes of JPEG 2000 pixel data, expected %d",
          name, decoded == nullptr ? 0 : int64_t{decoded->GetLength()},
          expected));
    }
    std::vector<uint8_t> buffer(expected);
    std::memcpy(buffer.data(), decoded->GetPointer(), expected);
    // GDCM hands out samples in host byte order; the converter reads little
    // endian.
    static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__,
                  "big-endian hosts need a byte swap here");
    return buffer;
  } catch (const std::exception& e) {
    // GDCM reports some failures by exceptions (never with patient data).
    return absl::InvalidArgumentError(absl::StrCat(
        name, ": GDCM failed on the JPEG 2000 codestream (", e.what(), ")"));
  } catch (...) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": GDCM failed on the JPEG 2000 codestream"));
  }
}

}  // namespace dicom_internal
}  // namespace interslice

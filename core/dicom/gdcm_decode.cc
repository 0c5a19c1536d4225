#include "core/dicom/gdcm_decode.h"

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "gdcmImage.h"
#include "gdcmImageReader.h"
#include "gdcmPixelFormat.h"

namespace interslice {
namespace dicom_internal {

bool IsGdcmFallbackSyntax(const std::string& transfer_syntax_uid) {
  return transfer_syntax_uid == "1.2.840.10008.1.2.4.90" ||
         transfer_syntax_uid == "1.2.840.10008.1.2.4.91";
}

absl::StatusOr<std::vector<uint8_t>> DecodeWithGdcm(const std::string& path,
                                                    const std::string& name,
                                                    int rows, int columns,
                                                    int64_t frames,
                                                    int bits_allocated) {
  gdcm::ImageReader reader;
  reader.SetFileName(path.c_str());
  if (!reader.Read()) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": GDCM cannot read the file (JPEG 2000 path)"));
  }
  const gdcm::Image& image = reader.GetImage();
  const unsigned int* dims = image.GetDimensions();
  const int64_t gdcm_frames = image.GetNumberOfDimensions() > 2 ? dims[2] : 1;
  const gdcm::PixelFormat& format = image.GetPixelFormat();
  if (static_cast<int>(dims[0]) != columns ||
      static_cast<int>(dims[1]) != rows || gdcm_frames != frames ||
      format.GetSamplesPerPixel() != 1 ||
      format.GetBitsAllocated() != bits_allocated) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s: GDCM decodes %d x %d x %d samples of %d bits, but the header "
        "says %d x %d x %d of %d",
        name, dims[0], dims[1], gdcm_frames, format.GetBitsAllocated(), columns,
        rows, frames, bits_allocated));
  }
  const int64_t expected =
      int64_t{rows} * columns * frames * (bits_allocated / 8);
  if (static_cast<int64_t>(image.GetBufferLength()) != expected) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s: GDCM reports %d bytes of decoded pixel data, expected %d", name,
        image.GetBufferLength(), expected));
  }
  std::vector<uint8_t> buffer(expected);
  if (!image.GetBuffer(reinterpret_cast<char*>(buffer.data()))) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": GDCM cannot decode the JPEG 2000 pixel data"));
  }
  // GDCM hands out samples in host byte order; the converter reads little
  // endian.
  static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__,
                "big-endian hosts need a byte swap here");
  return buffer;
}

}  // namespace dicom_internal
}  // namespace interslice

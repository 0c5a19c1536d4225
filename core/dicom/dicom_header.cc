#include "core/dicom/dicom_header.h"

#include <cctype>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "core/common/status_macros.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdatset.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcitem.h"
#include "dcmtk/dcmdata/dcmetinf.h"
#include "dcmtk/dcmdata/dcpixel.h"
#include "dcmtk/dcmdata/dcpixseq.h"
#include "dcmtk/dcmdata/dcsequen.h"
#include "dcmtk/dcmdata/dctag.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "dcmtk/dcmdata/dcxfer.h"
#include "zlib.h"

namespace interslice {
namespace dicom_internal {
namespace {

// kEmpty: present without a value (type 2 attributes may be).
enum class AttrState { kAbsent, kEmpty, kOk, kInvalid };

std::string GetString(DcmItem& item, const DcmTagKey& tag) {
  OFString value;
  if (item.findAndGetOFString(tag, value).bad()) return "";
  return std::string(absl::StripAsciiWhitespace(value.c_str()));
}

// All values of a multi-valued string, backslash-separated.
std::string GetAllStrings(DcmItem& item, const DcmTagKey& tag) {
  OFString value;
  if (item.findAndGetOFStringArray(tag, value).bad()) return "";
  return std::string(absl::StripAsciiWhitespace(value.c_str()));
}

// Reads exactly `n` finite numbers of a DS/FD attribute.
AttrState GetDoubles(DcmItem& item, const DcmTagKey& tag, double* out, int n) {
  DcmElement* element = nullptr;
  if (item.findAndGetElement(tag, element).bad() || element == nullptr) {
    return AttrState::kAbsent;
  }
  if (element->getLength() == 0) return AttrState::kEmpty;
  if (element->getVM() != static_cast<unsigned long>(n)) {
    return AttrState::kInvalid;
  }
  for (int i = 0; i < n; ++i) {
    Float64 value = 0;
    if (element->getFloat64(value, i).bad() || !std::isfinite(value)) {
      return AttrState::kInvalid;
    }
    out[i] = value;
  }
  return AttrState::kOk;
}

// RescaleSlope and RescaleIntercept of `item`, when present (absent: 1 and
// 0). Every stored value goes through them, so a value that is present but
// empty, not a number, not finite, or a slope of 0 (which would map the
// whole image to one value) makes the slice unusable. GDCM, which decodes
// JPEG 2000, would even abort the process on an empty RescaleSlope
// (gdcmImageHelper.cxx, GetRescaleInterceptSlopeValue); refusing it here
// keeps such a file away from every decoder. `what` names the slice.
absl::Status ReadRescale(DcmItem& item, const std::string& what, double* slope,
                         double* intercept) {
  struct Attr {
    const DcmTagKey& tag;
    const char* name;
    double* value;
  };
  for (const Attr& a :
       {Attr{DCM_RescaleSlope, "RescaleSlope (0028,1053)", slope},
        Attr{DCM_RescaleIntercept, "RescaleIntercept (0028,1052)",
             intercept}}) {
    switch (GetDoubles(item, a.tag, a.value, 1)) {
      case AttrState::kAbsent:
      case AttrState::kOk:
        break;
      case AttrState::kEmpty:
        return absl::InvalidArgumentError(
            absl::StrCat(what, ": ", a.name, " is present but empty"));
      case AttrState::kInvalid:
        return absl::InvalidArgumentError(
            absl::StrCat(what, ": ", a.name, " is not one finite number"));
    }
  }
  if (*slope == 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        what,
        ": RescaleSlope (0028,1053) is 0, which would map every stored "
        "value to the intercept"));
  }
  return absl::OkStatus();
}

// Checks that `frames` frames of pixel data are present. Native pixel data
// was not loaded (it is longer than the read limit), but its length field is
// known: a header claiming a huge image with little data is rejected before
// anything of the claimed size is allocated. For encapsulated data a
// fragment holds at most one frame, so the number of fragments bounds
// NumberOfFrames; decoded data is checked again after decoding.
absl::Status CheckPixelLength(DcmDataset& ds, const std::string& name,
                              const FileHeader& h, int64_t frames) {
  DcmElement* pixels = nullptr;
  ds.findAndGetElement(DCM_PixelData, pixels);
  if (DcmXfer(ds.getOriginalXfer()).isEncapsulated()) {
    DcmPixelData* data = dynamic_cast<DcmPixelData*>(pixels);
    DcmPixelSequence* sequence = nullptr;
    E_TransferSyntax xfer = EXS_Unknown;
    const DcmRepresentationParameter* param = nullptr;
    if (data != nullptr) {
      data->getOriginalRepresentationKey(xfer, param);
      data->getEncapsulatedRepresentation(xfer, param, sequence);
    }
    // The first item is the basic offset table.
    const int64_t fragments =
        sequence == nullptr ? 0 : static_cast<int64_t>(sequence->card()) - 1;
    if (fragments < frames) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s: encapsulated pixel data has %d fragment(s) for %d frame(s)",
          name, std::max<int64_t>(fragments, 0), frames));
    }
    return absl::OkStatus();
  }
  const int64_t needed =
      int64_t{h.rows} * h.columns * (h.layout.bits_allocated / 8) * frames;
  const Uint32 length = pixels == nullptr ? 0 : pixels->getLengthField();
  if (length == DCM_UndefinedLength || int64_t{length} < needed) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s: pixel data is too short: %d bytes, but %d frame(s) of %d x %d "
        "pixels of %d bits need %d",
        name, length == DCM_UndefinedLength ? 0 : int64_t{length}, frames,
        h.columns, h.rows, h.layout.bits_allocated, needed));
  }
  return absl::OkStatus();
}

// The item of functional group `tag` for one frame: the per-frame item's
// own, else the shared one, else null.
DcmItem* FunctionalGroup(DcmItem* per_frame, DcmItem* shared,
                         const DcmTagKey& tag) {
  DcmItem* item = nullptr;
  if (per_frame != nullptr &&
      per_frame->findAndGetSequenceItem(tag, item, 0).good() &&
      item != nullptr) {
    return item;
  }
  item = nullptr;
  if (shared != nullptr &&
      shared->findAndGetSequenceItem(tag, item, 0).good()) {
    return item;
  }
  return nullptr;
}

// Frame geometry of an enhanced multi-frame object.
absl::Status ReadMultiFrameAttributes(DcmDataset& ds, const std::string& name,
                                      Sint32 frames, FileHeader& h) {
  // NumberOfFrames bounds the per-frame items below, and the pixel length
  // check bounds it by the data actually present.
  DcmSequenceOfItems* per_frame = nullptr;
  ds.findAndGetSequence(DCM_PerFrameFunctionalGroupsSequence, per_frame);
  DcmItem* shared = nullptr;
  ds.findAndGetSequenceItem(DCM_SharedFunctionalGroupsSequence, shared, 0);
  const unsigned long items = per_frame == nullptr ? 0 : per_frame->card();
  if (per_frame == nullptr && shared == nullptr) {
    // Old-style multi-frame (e.g. ultrasound cine, secondary capture) has
    // no per-frame geometry: not a slice stack.
    h.kind = FileKind::kNotImage;
    return absl::OkStatus();
  }
  if (per_frame != nullptr && items != static_cast<unsigned long>(frames)) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s: %d frames but %d items in PerFrameFunctionalGroupsSequence", name,
        frames, items));
  }
  INTERSLICE_ASSIGN_OR_RETURN(h.layout, ReadPixelLayout(ds, name));
  INTERSLICE_RETURN_IF_ERROR(CheckPixelLength(ds, name, h, frames));
  h.frames.resize(frames);
  for (Sint32 f = 0; f < frames; ++f) {
    FrameGeometry& g = h.frames[f];
    DcmItem* own = per_frame == nullptr ? nullptr : per_frame->getItem(f);
    const std::string frame = absl::StrCat(name, " frame ", f + 1);
    DcmItem* position = FunctionalGroup(own, shared, DCM_PlanePositionSequence);
    DcmItem* orientation =
        FunctionalGroup(own, shared, DCM_PlaneOrientationSequence);
    if (position == nullptr || orientation == nullptr) {
      return absl::InvalidArgumentError(absl::StrCat(
          frame,
          ": no PlanePositionSequence or PlaneOrientationSequence in "
          "the functional groups"));
    }
    if (GetDoubles(*position, DCM_ImagePositionPatient, g.position.data(), 3) !=
        AttrState::kOk) {
      return absl::InvalidArgumentError(
          absl::StrCat(frame, ": missing or invalid ImagePositionPatient"));
    }
    if (GetDoubles(*orientation, DCM_ImageOrientationPatient,
                   g.orientation.data(), 6) != AttrState::kOk) {
      return absl::InvalidArgumentError(
          absl::StrCat(frame, ": missing or invalid ImageOrientationPatient"));
    }
    DcmItem* measures = FunctionalGroup(own, shared, DCM_PixelMeasuresSequence);
    if (measures == nullptr ||
        GetDoubles(*measures, DCM_PixelSpacing, g.pixel_spacing.data(), 2) !=
            AttrState::kOk ||
        !(g.pixel_spacing[0] > 0) || !(g.pixel_spacing[1] > 0)) {
      return absl::InvalidArgumentError(
          absl::StrCat(frame, ": missing or invalid PixelSpacing"));
    }
    if (f == 0) {
      GetDoubles(*measures, DCM_SliceThickness, &h.slice_thickness, 1);
      GetDoubles(*measures, DCM_SpacingBetweenSlices, &h.spacing_between_slices,
                 1);
    }
    // Without a Pixel Value Transformation the stored values are the
    // values (MR); a top-level rescale is honoured as a fallback.
    DcmItem* transform =
        FunctionalGroup(own, shared, DCM_PixelValueTransformationSequence);
    DcmItem& rescale = transform != nullptr ? *transform : ds;
    INTERSLICE_RETURN_IF_ERROR(
        ReadRescale(rescale, frame, &g.rescale_slope, &g.rescale_intercept));
    std::vector<std::string> volume;
    if (DcmItem* content =
            FunctionalGroup(own, shared, DCM_FrameContentSequence)) {
      const std::string stack = GetString(*content, DCM_StackID);
      if (!stack.empty()) volume.push_back(absl::StrCat("stack ", stack));
      Uint32 temporal = 0;
      if (content->findAndGetUint32(DCM_TemporalPositionIndex, temporal)
              .good()) {
        volume.push_back(absl::StrCat("temporal position ", temporal));
      }
    }
    for (const DcmTagKey& type_tag :
         {DCM_MRImageFrameTypeSequence, DCM_CTImageFrameTypeSequence}) {
      if (DcmItem* type = FunctionalGroup(own, shared, type_tag)) {
        std::string text = GetAllStrings(*type, DCM_FrameType);
        const std::string component =
            GetString(*type, DCM_ComplexImageComponent);
        if (!component.empty()) absl::StrAppend(&text, " (", component, ")");
        if (!text.empty()) volume.push_back(absl::StrCat("frame type ", text));
      }
    }
    g.volume = absl::StrJoin(volume, ", ");
  }
  // The top-level attributes describe frame 1, for messages and for the
  // consistency checks that compare headers.
  h.position = h.frames[0].position;
  h.orientation = h.frames[0].orientation;
  h.pixel_spacing = h.frames[0].pixel_spacing;
  h.rescale_slope = h.frames[0].rescale_slope;
  h.rescale_intercept = h.frames[0].rescale_intercept;
  return absl::OkStatus();
}

// Fills the image attributes of `h` from `ds`; returns the problem that makes
// the slice unusable, if any. Sets h.kind to kNotImage when the object is not
// a slice of a stack at all.
absl::Status ReadImageAttributes(DcmDataset& ds, const std::string& name,
                                 FileHeader& h) {
  Uint16 rows = 0, columns = 0;
  ds.findAndGetUint16(DCM_Rows, rows);
  ds.findAndGetUint16(DCM_Columns, columns);
  if (!ds.tagExists(DCM_PixelData) || rows == 0 || columns == 0) {
    h.kind = FileKind::kNotImage;
    return absl::OkStatus();
  }
  h.rows = rows;
  h.columns = columns;

  // Enhanced objects keep position, orientation, spacing and rescale in
  // functional groups, one set per frame; one is read like a stack of
  // single-frame slices.
  Sint32 frames = 1;
  if (ds.findAndGetSint32(DCM_NumberOfFrames, frames).good() && frames < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": invalid NumberOfFrames ", frames));
  }
  if (frames > 1 || ds.tagExists(DCM_PerFrameFunctionalGroupsSequence) ||
      ds.tagExists(DCM_SharedFunctionalGroupsSequence)) {
    return ReadMultiFrameAttributes(ds, name, frames, h);
  }

  const AttrState position =
      GetDoubles(ds, DCM_ImagePositionPatient, h.position.data(), 3);
  const AttrState orientation =
      GetDoubles(ds, DCM_ImageOrientationPatient, h.orientation.data(), 6);
  if (position == AttrState::kAbsent || position == AttrState::kEmpty ||
      orientation == AttrState::kAbsent || orientation == AttrState::kEmpty) {
    // Projection images, secondary captures, ...: not part of a stack.
    h.kind = FileKind::kNotImage;
    return absl::OkStatus();
  }
  if (position == AttrState::kInvalid) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": invalid ImagePositionPatient"));
  }
  if (orientation == AttrState::kInvalid) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": invalid ImageOrientationPatient"));
  }
  if (GetDoubles(ds, DCM_PixelSpacing, h.pixel_spacing.data(), 2) !=
          AttrState::kOk ||
      !(h.pixel_spacing[0] > 0) || !(h.pixel_spacing[1] > 0)) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": missing or invalid PixelSpacing"));
  }
  INTERSLICE_RETURN_IF_ERROR(
      ReadRescale(ds, name, &h.rescale_slope, &h.rescale_intercept));
  // Only used for a single slice; an invalid value falls back like a
  // missing one.
  if (GetDoubles(ds, DCM_SliceThickness, &h.slice_thickness, 1) !=
      AttrState::kOk) {
    h.slice_thickness = 0;
  }
  if (GetDoubles(ds, DCM_SpacingBetweenSlices, &h.spacing_between_slices, 1) !=
      AttrState::kOk) {
    h.spacing_between_slices = 0;
  }
  INTERSLICE_ASSIGN_OR_RETURN(h.layout, ReadPixelLayout(ds, name));

  return CheckPixelLength(ds, name, h, 1);
  return absl::OkStatus();
}

// The numbers of a multi-valued DS attribute rounded to 1e-4 (so that
// 1\0\0 and 1.000000\0.0\-0.0 agree), or its text when it is not
// numeric; "" when absent.
std::string CanonicalNumbers(DcmItem& item, const DcmTagKey& tag) {
  const std::string text = GetAllStrings(item, tag);
  if (text.empty()) return "";
  std::vector<std::string> parts;
  for (absl::string_view value : absl::StrSplit(text, '\\')) {
    double number = 0;
    if (!absl::SimpleAtod(value, &number) || !std::isfinite(number) ||
        std::abs(number) > 1e12) {
      return absl::StrCat("text ", text);
    }
    parts.push_back(absl::StrCat(std::llround(number * 1e4)));
  }
  return absl::StrJoin(parts, ",");
}

std::string CanonicalNumbers(const double* values, int n) {
  std::vector<std::string> parts;
  for (int i = 0; i < n; ++i) {
    parts.push_back(absl::StrCat(std::llround(values[i] * 1e4)));
  }
  return absl::StrJoin(parts, ",");
}

// FileHeader::series_key. Without a SeriesInstanceUID (anonymisers blank
// it), the files of one series are those that share what a series keeps
// constant and that is still there: FrameOfReferenceUID and Modality and
// SeriesNumber when present, ImageOrientationPatient, Rows and Columns, and
// PixelSpacing (enhanced multi-frame files: those of their first frame).
// Different series of one study differ in at least one of these in practice
// (another reconstruction has another size, spacing or orientation, or
// another series number); slices of one series never do. The key starts
// with a character no UID starts with, so inferred series never meet real
// ones.
std::string SeriesKey(DcmDataset& ds, const FileHeader& h) {
  if (!h.series_uid.empty()) return h.series_uid;
  const bool multiframe = !h.frames.empty();
  return absl::StrCat(
      "~for=", h.frame_of_reference_uid, "|modality=", h.modality,
      "|series=", h.series_number, "|orientation=",
      multiframe ? CanonicalNumbers(h.orientation.data(), 6)
                 : CanonicalNumbers(ds, DCM_ImageOrientationPatient),
      "|size=", GetString(ds, DCM_Columns), "x", GetString(ds, DCM_Rows),
      "|spacing=",
      multiframe ? CanonicalNumbers(h.pixel_spacing.data(), 2)
                 : CanonicalNumbers(ds, DCM_PixelSpacing));
}

// ---- Nesting depth pre-check -------------------------------------------

constexpr uint32_t kUndefinedLength = 0xffffffffu;
constexpr uint64_t kNoEnd = std::numeric_limits<uint64_t>::max();

// Bytes of a file, or of the deflated data set after its meta header.
class ByteSource {
 public:
  virtual ~ByteSource() = default;
  virtual bool Read(uint8_t* out, size_t n) = 0;
  virtual bool Skip(uint64_t n) = 0;
  uint64_t position() const { return position_; }

 protected:
  uint64_t position_ = 0;
};

class FileSource : public ByteSource {
 public:
  explicit FileSource(const std::string& path) : in_(path, std::ios::binary) {
    in_.seekg(0, std::ios::end);
    size_ = in_.good() ? static_cast<uint64_t>(in_.tellg()) : 0;
    in_.seekg(0);
  }
  bool ok() const { return in_.good(); }
  bool Read(uint8_t* out, size_t n) override {
    if (!in_.read(reinterpret_cast<char*>(out), n)) return false;
    position_ += n;
    return true;
  }
  bool Skip(uint64_t n) override {
    if (n > size_ - std::min(size_, position_)) return false;
    position_ += n;
    in_.seekg(static_cast<std::streamoff>(position_));
    return in_.good();
  }
  bool Seek(uint64_t to) {
    in_.clear();
    position_ = to;
    in_.seekg(static_cast<std::streamoff>(to));
    return in_.good();
  }

 private:
  std::ifstream in_;
  uint64_t size_ = 0;
};

class InflateSource : public ByteSource {
 public:
  explicit InflateSource(FileSource& file) : file_(file) {
    ok_ = inflateInit2(&z_, -MAX_WBITS) == Z_OK;  // raw deflate (PS3.5 A.5)
  }
  ~InflateSource() override { inflateEnd(&z_); }
  bool Read(uint8_t* out, size_t n) override {
    z_.next_out = out;
    z_.avail_out = static_cast<uInt>(n);
    while (ok_ && z_.avail_out > 0) {
      if (z_.avail_in == 0) {
        size_t got = 0;
        while (got < sizeof(in_) && file_.Read(in_ + got, 1)) ++got;
        if (got == 0) return false;
        z_.next_in = in_;
        z_.avail_in = static_cast<uInt>(got);
      }
      const int rc = inflate(&z_, Z_NO_FLUSH);
      if (rc != Z_OK && !(rc == Z_STREAM_END && z_.avail_out == 0)) {
        ok_ = false;
      }
    }
    if (!ok_) return false;
    position_ += n;
    return true;
  }
  bool Skip(uint64_t n) override {
    uint8_t scratch[4096];
    while (n > 0) {
      const size_t chunk = static_cast<size_t>(std::min<uint64_t>(n, 4096));
      if (!Read(scratch, chunk)) return false;
      n -= chunk;
    }
    return true;
  }

 private:
  FileSource& file_;
  z_stream z_{};
  bool ok_ = false;
  uint8_t in_[4096];
};

uint16_t U16(const uint8_t* b, bool big) {
  return big ? uint16_t(b[0] << 8 | b[1]) : uint16_t(b[1] << 8 | b[0]);
}
uint32_t U32(const uint8_t* b, bool big) {
  return big ? uint32_t{b[0]} << 24 | uint32_t{b[1]} << 16 |
                   uint32_t{b[2]} << 8 | b[3]
             : uint32_t{b[3]} << 24 | uint32_t{b[2]} << 16 |
                   uint32_t{b[1]} << 8 | b[0];
}

bool IsLongVr(const char vr[2]) {
  static const char* const kLong[] = {"OB", "OD", "OF", "OL", "OV", "OW", "SQ",
                                      "SV", "UC", "UN", "UR", "UT", "UV"};
  for (const char* l : kLong) {
    if (vr[0] == l[0] && vr[1] == l[1]) return true;
  }
  return false;
}

// Walks a data set without recursion, tracking how deeply sequences nest.
// Returns false when the depth exceeds max_depth; true otherwise, including
// when the stream ends or stops making sense (DCMTK reports those itself).
bool WalkDepth(ByteSource& in, bool explicit_vr, bool big_endian,
               int max_depth) {
  struct Container {
    bool is_item;
    uint64_t end;
    bool explicit_vr;
    bool big_endian;
  };
  std::vector<Container> open;
  int depth = 0;  // sequences open
  uint8_t b[8];
  while (true) {
    while (!open.empty() && open.back().end != kNoEnd &&
           in.position() >= open.back().end) {
      if (!open.back().is_item) --depth;
      open.pop_back();
    }
    const bool ex = open.empty() ? explicit_vr : open.back().explicit_vr;
    const bool big = open.empty() ? big_endian : open.back().big_endian;
    if (!in.Read(b, 4)) return true;
    const uint16_t group = U16(b, big), element = U16(b + 2, big);
    if (group == 0xfffe) {
      if (!in.Read(b, 4)) return true;
      const uint32_t length = U32(b, big);
      if (element == 0xe000) {
        open.push_back(
            {true, length == kUndefinedLength ? kNoEnd : in.position() + length,
             ex, big});
      } else if (element == 0xe00d) {
        if (!open.empty() && open.back().is_item) open.pop_back();
      } else if (element == 0xe0dd) {
        if (!open.empty() && open.back().is_item) open.pop_back();
        if (!open.empty() && !open.back().is_item) {
          open.pop_back();
          --depth;
        }
      }
      continue;
    }
    bool sequence = false;
    bool contents_implicit = !ex;
    uint32_t length = 0;
    if (ex) {
      if (!in.Read(b, 2)) return true;
      const char vr[2] = {static_cast<char>(b[0]), static_cast<char>(b[1])};
      if (IsLongVr(vr)) {
        if (!in.Read(b, 6)) return true;
        length = U32(b + 2, big);
      } else {
        if (!in.Read(b, 2)) return true;
        length = U16(b, big);
      }
      sequence = vr[0] == 'S' && vr[1] == 'Q';
      // DCMTK parses UN of undefined length as an implicit little endian
      // sequence (CP-246).
      if (vr[0] == 'U' && vr[1] == 'N' && length == kUndefinedLength) {
        sequence = true;
        contents_implicit = true;
      }
    } else {
      if (!in.Read(b, 4)) return true;
      length = U32(b, big);
      sequence = length == kUndefinedLength ||
                 DcmTag(group, element).getEVR() == EVR_SQ;
    }
    if (group == 0x7fe0 && element == 0x0010 && length == kUndefinedLength) {
      // Encapsulated pixel data: items of raw bytes until the delimiter.
      while (true) {
        if (!in.Read(b, 8)) return true;
        const uint32_t item_length = U32(b + 4, big);
        if (U16(b + 2, big) == 0xe0dd) break;
        if (item_length == kUndefinedLength || !in.Skip(item_length)) {
          return true;
        }
      }
      continue;
    }
    if (sequence) {
      if (++depth > max_depth) return false;
      open.push_back(
          {false, length == kUndefinedLength ? kNoEnd : in.position() + length,
           !contents_implicit, contents_implicit ? false : big});
      continue;
    }
    if (length == kUndefinedLength || !in.Skip(length)) return true;
  }
}

}  // namespace

absl::Status CheckSequenceDepth(const std::string& path, int max_depth) {
  FileSource file(path);
  if (!file.ok()) return absl::OkStatus();  // DCMTK reports it
  uint8_t b[8];
  bool explicit_vr = true, big_endian = false, deflated = false;
  std::string syntax;
  if (file.Skip(128) && file.Read(b, 4) && std::memcmp(b, "DICM", 4) == 0) {
    // File meta information: explicit VR little endian, group 0002.
    while (true) {
      const uint64_t start = file.position();
      if (!file.Read(b, 6)) return absl::OkStatus();
      if (U16(b, false) != 0x0002) {
        file.Seek(start);
        break;
      }
      const uint16_t element = U16(b + 2, false);
      const char vr[2] = {static_cast<char>(b[4]), static_cast<char>(b[5])};
      uint32_t length = 0;
      if (IsLongVr(vr)) {
        if (!file.Read(b, 6)) return absl::OkStatus();
        length = U32(b + 2, false);
      } else {
        if (!file.Read(b, 2)) return absl::OkStatus();
        length = U16(b, false);
      }
      if (element != 0x0010 || length > 64) {
        if (length == kUndefinedLength || !file.Skip(length)) {
          return absl::OkStatus();
        }
        continue;
      }
      std::string value(length, '\0');
      if (!file.Read(reinterpret_cast<uint8_t*>(value.data()), length)) {
        return absl::OkStatus();
      }
      syntax = std::string(absl::StripAsciiWhitespace(value.c_str()));
    }
    if (syntax == UID_LittleEndianImplicitTransferSyntax) explicit_vr = false;
    if (syntax == UID_BigEndianExplicitTransferSyntax) big_endian = true;
    if (syntax == UID_DeflatedExplicitVRLittleEndianTransferSyntax) {
      deflated = true;
    }
  } else {
    // No meta header: DCMTK guesses the encoding; so do we.
    file.Seek(0);
    if (!file.Read(b, 6)) return absl::OkStatus();
    explicit_vr = std::isupper(b[4]) && std::isupper(b[5]);
    file.Seek(0);
  }
  bool within = true;
  if (deflated) {
    InflateSource inflated(file);
    within = WalkDepth(inflated, true, false, max_depth);
  } else {
    within = WalkDepth(file, explicit_vr, big_endian, max_depth);
  }
  if (!within) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s: sequences nested more than %d levels deep; refused (hostile or "
        "corrupt file)",
        BaseName(path), max_depth));
  }
  return absl::OkStatus();
}

std::string BaseName(const std::string& path) {
  return std::filesystem::path(path).filename().string();
}

FileHeader ScanFile(const std::string& path) {
  FileHeader h;
  h.path = path;
  const std::string name = BaseName(path);

  // Before DCMTK sees the file: it would recurse once per nesting level.
  if (absl::Status depth = CheckSequenceDepth(path); !depth.ok()) {
    h.kind = FileKind::kNotDicom;
    h.problem = std::move(depth);
    return h;
  }
  DcmFileFormat file;
  const OFCondition loaded =
      file.loadFile(OFFilename(path.c_str()), EXS_Unknown, EGL_noChange,
                    kHeaderMaxReadLength, ERM_autoDetect);
  DcmDataset& ds = *file.getDataset();
  DcmMetaInfo& meta = *file.getMetaInfo();

  if (GetString(meta, DCM_MediaStorageSOPClassUID) ==
          UID_MediaStorageDirectoryStorage ||
      ds.tagExists(DCM_DirectoryRecordSequence)) {
    h.kind = FileKind::kDicomDir;
    return h;
  }

  h.series_uid = GetString(ds, DCM_SeriesInstanceUID);
  h.study_uid = GetString(ds, DCM_StudyInstanceUID);
  h.frame_of_reference_uid = GetString(ds, DCM_FrameOfReferenceUID);
  h.modality = GetString(ds, DCM_Modality);
  h.series_number = GetString(ds, DCM_SeriesNumber);
  h.sop_class_uid = GetString(ds, DCM_SOPClassUID);
  if (h.sop_class_uid.empty()) {
    // Some anonymisers blank the data set's UIDs but keep the meta header
    // (dcm2niix and GDCM fall back to it too).
    h.sop_class_uid = GetString(meta, DCM_MediaStorageSOPClassUID);
    h.sop_class_from_meta = !h.sop_class_uid.empty();
  }
  h.sop_instance_uid = GetString(ds, DCM_SOPInstanceUID);
  h.transfer_syntax_uid = GetString(meta, DCM_TransferSyntaxUID);

  if (loaded.bad()) {
    // DCMTK keeps what it parsed before the error. A file that got as far as
    // a SeriesInstanceUID (or, without one, as far as the image geometry
    // its series is inferred from) is a broken member of that series
    // (typically a truncated copy); dropping it silently could leave a gap
    // at the end of the stack that no spacing check would notice.
    if (h.series_uid.empty() &&
        !(ds.tagExists(DCM_Rows) && ds.tagExists(DCM_ImagePositionPatient) &&
          ds.tagExists(DCM_ImageOrientationPatient))) {
      h.kind = FileKind::kNotDicom;
    } else {
      h.kind = FileKind::kImage;
      h.problem = absl::InvalidArgumentError(absl::StrCat(
          name, ": truncated or unreadable DICOM file (", loaded.text(), ")"));
      h.series_key = SeriesKey(ds, h);
    }
    return h;
  }
  h.kind = FileKind::kImage;
  h.problem = ReadImageAttributes(ds, name, h);
  h.series_key = SeriesKey(ds, h);
  return h;
}

absl::StatusOr<PixelLayout> ReadPixelLayout(DcmItem& item,
                                            const std::string& name) {
  Uint16 samples = 1;
  if (item.findAndGetUint16(DCM_SamplesPerPixel, samples).good() &&
      samples != 1) {
    return absl::UnimplementedError(absl::StrCat(
        name, ": SamplesPerPixel is ", samples,
        " (colour); only greyscale images (SamplesPerPixel 1) are supported"));
  }
  const std::string photometric =
      GetString(item, DCM_PhotometricInterpretation);
  if (!photometric.empty() && photometric != "MONOCHROME1" &&
      photometric != "MONOCHROME2") {
    return absl::UnimplementedError(absl::StrCat(
        name, ": PhotometricInterpretation ", photometric,
        " is not supported; only MONOCHROME1 and MONOCHROME2 are"));
  }

  PixelLayout layout;
  Uint16 bits_allocated = 0;
  if (item.findAndGetUint16(DCM_BitsAllocated, bits_allocated).bad()) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": BitsAllocated is missing"));
  }
  if (bits_allocated != 8 && bits_allocated != 16 && bits_allocated != 32) {
    return absl::UnimplementedError(
        absl::StrCat(name, ": BitsAllocated ", bits_allocated,
                     " is not supported; only 8, 16 and 32 are"));
  }
  layout.bits_allocated = bits_allocated;
  Uint16 bits_stored = bits_allocated;
  item.findAndGetUint16(DCM_BitsStored, bits_stored);
  Uint16 high_bit = bits_stored - 1;
  item.findAndGetUint16(DCM_HighBit, high_bit);
  Uint16 representation = 0;
  item.findAndGetUint16(DCM_PixelRepresentation, representation);
  if (bits_stored < 1 || bits_stored > bits_allocated ||
      high_bit >= bits_allocated || high_bit + 1 < bits_stored) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": inconsistent BitsAllocated ", bits_allocated,
                     ", BitsStored ", bits_stored, ", HighBit ", high_bit));
  }
  if (representation > 1) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": invalid PixelRepresentation ", representation));
  }
  layout.bits_stored = bits_stored;
  layout.high_bit = high_bit;
  layout.is_signed = representation == 1;
  return layout;
}

}  // namespace dicom_internal
}  // namespace interslice

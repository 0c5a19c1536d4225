// PlanDerivedObjects: the UIDs, series numbers and descriptions of the
// objects one job writes, decided before any of them is written, so that the
// SEG and the Parametric Map can reference the intensity series' instances
// while all three are written in parallel.
#include <algorithm>
#include <cstdint>
#include <limits>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/strip.h"
#include "core/common/status_macros.h"
#include "core/dicom_out/dicom_out_internal.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/dicom_out/preview_series.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcmetinf.h"
#include "dcmtk/dcmdata/dcuid.h"

namespace interslice {
namespace {

// Series numbers when the source has none (the SEG's was 9001 before).
constexpr int kFallbackSeriesNumberBase = 9000;

// What identifies the source itself, whatever job runs on it, as lines of
// text: its SOP Instance UIDs (with the frame, for multi-frame sources);
// when an anonymiser blanked them, the MediaStorageSOPInstanceUIDs of its
// files' meta headers (anonymisers often leave those); else the digest of
// its pixels (DicomSeries::pixel_digest). Empty when none is there (a
// series made up in memory): nothing identifies it.
absl::StatusOr<std::string> SourceInstanceIdentity(const DicomSeries& source) {
  if (source.slices.empty()) return std::string();
  std::string lines;
  bool complete = true;
  for (const DicomSliceInfo& slice : source.slices) {
    if (slice.sop_instance_uid.empty()) complete = false;
    absl::StrAppend(&lines, "instance ", slice.sop_instance_uid, " frame ",
                    slice.frame, "\n");
  }
  if (complete) return lines;
  // The file meta headers, each file read once (not its data set).
  lines.clear();
  complete = true;
  std::map<std::string, std::string> media_uid_of_file;
  for (const DicomSliceInfo& slice : source.slices) {
    auto [it, inserted] = media_uid_of_file.try_emplace(slice.path);
    if (inserted) {
      DcmFileFormat file;
      OFString uid;
      if (file.loadFile(slice.path.c_str(), EXS_Unknown, EGL_noChange,
                        DCM_MaxReadLength, ERM_metaOnly)
              .good() &&
          file.getMetaInfo()
              ->findAndGetOFString(DCM_MediaStorageSOPInstanceUID, uid)
              .good()) {
        it->second = uid.c_str();
      }
    }
    if (it->second.empty()) complete = false;
    absl::StrAppend(&lines, "media instance ", it->second, " frame ",
                    slice.frame, "\n");
  }
  if (complete) return lines;
  if (!source.pixel_digest.empty()) {
    return absl::StrCat("pixels ", source.pixel_digest, " slices ",
                        source.slices.size(), "\n");
  }
  return std::string();
}

// Names UIDs within one job: deterministic (a name-based UUID of the job's
// own UID and the object's name) or random. The study and frame of
// reference a source lacks are named from the source alone (SourceUid), so
// that every job on it (`run`, `fill`) lands in the same study and frame.
class UidNamer {
 public:
  static absl::StatusOr<UidNamer> Create(const DicomSeries& source,
                                         const DicomWriteOptions& options) {
    UidNamer namer;
    namer.root_ = options.uid_root;
    INTERSLICE_ASSIGN_OR_RETURN(const std::string instances,
                                SourceInstanceIdentity(source));
    if (options.random_uids || instances.empty()) {
      // Validates the root as a side effect.
      INTERSLICE_RETURN_IF_ERROR(GenerateDicomUid(options.uid_root).status());
      namer.random_ = true;
      return namer;
    }
    // The source's identity: its instances (above), in volume order, the
    // series they belong to and the volume read.
    const std::string series = absl::StrCat(
        "study ", source.study_instance_uid, "\nseries ",
        source.series_instance_uid, "\nvolume ", source.volume, "\n");
    INTERSLICE_ASSIGN_OR_RETURN(
        namer.source_, DeriveDicomUid("", absl::StrCat("interslice source v1\n",
                                                       series, instances)));
    // The job's identity: the source's, the root and the job's parameters.
    // Hashed once into a UID that names the job; each object's UID is then
    // named from it. (The text is what it was before sources without SOP
    // Instance UIDs were named, so the UIDs of the others stay.)
    std::string name = "interslice derived objects v1\n";
    absl::StrAppend(&name, series, instances, "root ", options.uid_root,
                    "\nkey ", options.derivation_key, "\n");
    INTERSLICE_ASSIGN_OR_RETURN(namer.job_, DeriveDicomUid("", name));
    // Validates the root.
    INTERSLICE_RETURN_IF_ERROR(
        DeriveDicomUid(options.uid_root, namer.job_).status());
    return namer;
  }

  // An object of the job.
  absl::StatusOr<std::string> Uid(std::string_view object) const {
    if (random_) return GenerateDicomUid(root_);
    return DeriveDicomUid(root_, absl::StrCat(job_, "/", std::string(object)));
  }

  // Something of the source, the same for every job on it.
  absl::StatusOr<std::string> SourceUid(std::string_view what) const {
    if (random_) return GenerateDicomUid(root_);
    return DeriveDicomUid(root_, absl::StrCat(source_, "/", std::string(what)));
  }

 private:
  std::string root_;
  std::string source_;
  std::string job_;
  bool random_ = false;
};

// The source's SeriesNumber, if it has a usable one.
std::optional<int64_t> SourceSeriesNumber(DcmItem& header) {
  Sint32 number = 0;
  if (header.findAndGetSint32(DCM_SeriesNumber, number).good() && number >= 0) {
    return number;
  }
  return std::nullopt;
}

std::string ImageSopClass(const DicomSeries& source) {
  if (source.sop_class_uid == UID_CTImageStorage) return UID_CTImageStorage;
  if (source.sop_class_uid == UID_MRImageStorage) return UID_MRImageStorage;
  return UID_SecondaryCaptureImageStorage;
}

// Parameter sets per source series: 1000 numbers per source series, ten per
// set (the objects use base + 1 ... base + 6).
constexpr int64_t kParameterSlots = 100;
constexpr int64_t kSlotStride = 10;

// The parameter set's slot (dicom_writer.h, "Identity"): its name-based UUID
// (decimal digits after "2.25.") modulo kParameterSlots.
absl::StatusOr<int64_t> ParameterSlot(const std::string& parameter_set) {
  if (parameter_set.empty()) return 0;
  INTERSLICE_ASSIGN_OR_RETURN(
      const std::string uid,
      DeriveDicomUid(
          "", absl::StrCat("interslice parameter set v1\n", parameter_set)));
  int64_t slot = 0;
  for (char c : uid.substr(uid.rfind('.') + 1)) {
    slot = (slot * 10 + (c - '0')) % kParameterSlots;
  }
  return slot;
}

// The base of the derived series numbers (dicom_writer.h, "Identity"),
// leaving room for the last of them, the previews (preview_series.h).
absl::StatusOr<int64_t> SeriesNumberBase(DcmItem& header,
                                         const DicomWriteOptions& options) {
  constexpr int64_t kLast = kPreviewSeriesNumberOffset;
  int64_t base = options.series_number_base;
  if (base <= 0) {
    INTERSLICE_ASSIGN_OR_RETURN(const int64_t slot,
                                ParameterSlot(options.parameter_set));
    const std::optional<int64_t> number = SourceSeriesNumber(header);
    base = kFallbackSeriesNumberBase;
    // IS holds a signed 32-bit value; 1000 x a huge source number would not.
    if (number.has_value() && *number > 0 &&
        *number * 1000 + (kParameterSlots - 1) * kSlotStride + kLast <=
            std::numeric_limits<int32_t>::max()) {
      base = *number * 1000;
    }
    base += slot * kSlotStride;
  }
  if (base + kLast > std::numeric_limits<int32_t>::max()) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "series number base %d leaves no room for the derived series", base));
  }
  return base;
}

// The study and frame of reference every object of the job shares.
absl::Status SetStudyAndFrame(const DicomSeries& source, const UidNamer& namer,
                              DerivedObjectIdentity& object) {
  object.study_instance_uid = source.study_instance_uid;
  if (object.study_instance_uid.empty()) {
    INTERSLICE_ASSIGN_OR_RETURN(object.study_instance_uid,
                                namer.SourceUid("study"));
  }
  object.frame_of_reference_uid = source.frame_of_reference_uid;
  if (object.frame_of_reference_uid.empty()) {
    INTERSLICE_ASSIGN_OR_RETURN(object.frame_of_reference_uid,
                                namer.SourceUid("frame-of-reference"));
  }
  return absl::OkStatus();
}

// The source series as a radiologist finds it in the study's series list:
// "from #<SeriesNumber> <SeriesDescription>", either part alone when the
// other is missing, "" when both are. A description that is not printable
// ASCII is left out (the derived objects do not all carry the source's
// SpecificCharacterSet, and a cut could split a multi-byte character).
std::string SourceSeriesReference(DcmItem& header) {
  std::string text;
  const std::optional<int64_t> number = SourceSeriesNumber(header);
  if (number.has_value()) text = absl::StrCat("#", *number);
  OFString value;
  if (header.findAndGetOFString(DCM_SeriesDescription, value).good()) {
    const std::string description(absl::StripAsciiWhitespace(value.c_str()));
    const bool printable =
        std::all_of(description.begin(), description.end(),
                    [](char c) { return c >= 0x20 && c <= 0x7e; });
    if (!description.empty() && printable) {
      absl::StrAppend(&text, text.empty() ? "" : " ", description);
    }
  }
  return text.empty() ? text : absl::StrCat("from ", text);
}

// "<object> <summary>, from #<n> <source description>" (dicom_writer.h,
// "Identity"), leaving out what is empty; at most 64 characters (LO), cut
// from the end, so the object and the parameters always show.
std::string SeriesDescription(std::string_view object, std::string_view summary,
                              std::string_view source_reference) {
  std::string text(object);
  if (!summary.empty()) text.append(" ").append(summary);
  if (!source_reference.empty()) text.append(", ").append(source_reference);
  text = text.substr(0, 64);
  // No trailing blank or comma from the cut.
  while (!text.empty() && (text.back() == ' ' || text.back() == ',')) {
    text.pop_back();
  }
  return text;
}

}  // namespace

absl::StatusOr<std::string> DescribeDerivedSeries(const DicomSeries& source,
                                                  std::string_view object,
                                                  std::string_view summary) {
  INTERSLICE_ASSIGN_OR_RETURN(std::unique_ptr<DcmFileFormat> header,
                              dicom_out_internal::LoadSourceHeader(source));
  return SeriesDescription(object, summary,
                           SourceSeriesReference(*header->getDataset()));
}

absl::StatusOr<DerivedObjectIdentity> PlanPreviewSeries(
    const DicomSeries& source, const std::vector<std::string>& names,
    const DicomWriteOptions& options, const DerivedObjectIdentity* same_study) {
  if (names.empty()) {
    return absl::InvalidArgumentError("the preview series has no pictures");
  }
  for (size_t n = 0; n < names.size(); ++n) {
    for (size_t m = 0; m < n; ++m) {
      if (names[n] == names[m]) {
        return absl::InvalidArgumentError(absl::StrCat(
            "the preview series names the picture ", names[n], " twice"));
      }
    }
  }
  INTERSLICE_ASSIGN_OR_RETURN(const UidNamer namer,
                              UidNamer::Create(source, options));
  INTERSLICE_ASSIGN_OR_RETURN(std::unique_ptr<DcmFileFormat> header,
                              dicom_out_internal::LoadSourceHeader(source));
  INTERSLICE_ASSIGN_OR_RETURN(const int64_t base,
                              SeriesNumberBase(*header->getDataset(), options));
  DerivedObjectIdentity previews;
  if (same_study != nullptr) {
    previews.study_instance_uid = same_study->study_instance_uid;
    previews.frame_of_reference_uid = same_study->frame_of_reference_uid;
  } else {
    INTERSLICE_RETURN_IF_ERROR(SetStudyAndFrame(source, namer, previews));
  }
  INTERSLICE_ASSIGN_OR_RETURN(previews.series_instance_uid,
                              namer.Uid("previews/series"));
  for (const std::string& name : names) {
    INTERSLICE_ASSIGN_OR_RETURN(std::string uid,
                                namer.Uid(absl::StrCat("previews/", name)));
    previews.sop_instance_uids.push_back(std::move(uid));
  }
  previews.series_number = static_cast<int>(base + kPreviewSeriesNumberOffset);
  previews.sop_class_uid = UID_SecondaryCaptureImageStorage;
  previews.series_description =
      SeriesDescription("Previews", options.parameter_summary,
                        SourceSeriesReference(*header->getDataset()));
  return previews;
}

absl::StatusOr<DerivedObjects> PlanDerivedObjects(
    const DicomSeries& source, int64_t output_slices,
    const DicomWriteOptions& options) {
  if (output_slices < 1) {
    return absl::InvalidArgumentError("the output grid has no slices");
  }
  INTERSLICE_ASSIGN_OR_RETURN(const UidNamer namer,
                              UidNamer::Create(source, options));
  INTERSLICE_ASSIGN_OR_RETURN(std::unique_ptr<DcmFileFormat> header,
                              dicom_out_internal::LoadSourceHeader(source));

  INTERSLICE_ASSIGN_OR_RETURN(const int64_t base,
                              SeriesNumberBase(*header->getDataset(), options));
  // An anonymised source may have no study or frame of reference: the
  // job's objects then share ones named from the source alone (type 1 in
  // every IOD written here), the same for every job on it.
  DerivedObjects objects;
  INTERSLICE_RETURN_IF_ERROR(
      SetStudyAndFrame(source, namer, objects.intensity));
  for (DerivedObjectIdentity* o :
       {&objects.distance_map, &objects.segmentation, &objects.surface_stl}) {
    o->study_instance_uid = objects.intensity.study_instance_uid;
    o->frame_of_reference_uid = objects.intensity.frame_of_reference_uid;
  }
  DerivedObjectIdentity& intensity = objects.intensity;
  // The intensity series by its own key when there is one (shared by the
  // jobs whose other parameters differ: DicomWriteOptions::
  // intensity_derivation_key): its UIDs and its series numbers' slot.
  DicomWriteOptions intensity_options = options;
  if (!options.intensity_derivation_key.empty()) {
    intensity_options.derivation_key = options.intensity_derivation_key;
    intensity_options.parameter_set = options.intensity_derivation_key;
  }
  INTERSLICE_ASSIGN_OR_RETURN(const UidNamer intensity_namer,
                              UidNamer::Create(source, intensity_options));
  INTERSLICE_ASSIGN_OR_RETURN(
      const int64_t intensity_base,
      SeriesNumberBase(*header->getDataset(), intensity_options));
  INTERSLICE_ASSIGN_OR_RETURN(intensity.series_instance_uid,
                              intensity_namer.Uid("intensity/series"));
  intensity.sop_instance_uids.reserve(static_cast<size_t>(output_slices));
  for (int64_t k = 0; k < output_slices; ++k) {
    INTERSLICE_ASSIGN_OR_RETURN(
        std::string uid, intensity_namer.Uid(absl::StrCat("intensity/", k)));
    intensity.sop_instance_uids.push_back(std::move(uid));
  }
  intensity.series_number = static_cast<int>(intensity_base + 1);
  intensity.sop_class_uid = ImageSopClass(source);
  const std::string source_reference =
      SourceSeriesReference(*header->getDataset());
  intensity.series_description = SeriesDescription(
      "Interpolated",
      options.intensity_summary.empty() ? options.parameter_summary
                                        : options.intensity_summary,
      source_reference);

  DerivedObjectIdentity& distance = objects.distance_map;
  INTERSLICE_ASSIGN_OR_RETURN(distance.series_instance_uid,
                              namer.Uid("distance/series"));
  INTERSLICE_ASSIGN_OR_RETURN(std::string distance_uid,
                              namer.Uid("distance/instance"));
  distance.sop_instance_uids = {distance_uid};
  INTERSLICE_ASSIGN_OR_RETURN(distance.dimension_organization_uid,
                              namer.Uid("distance/dimensions"));
  distance.series_number = static_cast<int>(base + 2);
  distance.sop_class_uid = UID_ParametricMapStorage;
  distance.series_description = SeriesDescription(
      "Distance (mm)", options.parameter_summary, source_reference);

  DerivedObjectIdentity& seg = objects.segmentation;
  INTERSLICE_ASSIGN_OR_RETURN(seg.series_instance_uid, namer.Uid("seg/series"));
  INTERSLICE_ASSIGN_OR_RETURN(std::string seg_uid, namer.Uid("seg/instance"));
  seg.sop_instance_uids = {seg_uid};
  INTERSLICE_ASSIGN_OR_RETURN(seg.dimension_organization_uid,
                              namer.Uid("seg/dimensions"));
  seg.series_number = static_cast<int>(base + 3);
  seg.sop_class_uid = UID_SegmentationStorage;
  seg.series_description = SeriesDescription(
      "Segmentation", options.parameter_summary, source_reference);

  DerivedObjectIdentity& stl = objects.surface_stl;
  // "surface-stl" alone when nothing but the job's key shapes it, so that
  // those UIDs stay as they were.
  const std::string stl_name =
      options.surface_derivation_key.empty()
          ? std::string("surface-stl")
          : absl::StrCat("surface-stl[", options.surface_derivation_key, "]");
  INTERSLICE_ASSIGN_OR_RETURN(stl.series_instance_uid,
                              namer.Uid(absl::StrCat(stl_name, "/series")));
  INTERSLICE_ASSIGN_OR_RETURN(std::string stl_uid,
                              namer.Uid(absl::StrCat(stl_name, "/instance")));
  stl.sop_instance_uids = {stl_uid};
  stl.series_number = static_cast<int>(base + 4);
  stl.sop_class_uid = UID_EncapsulatedSTLStorage;
  stl.series_description = SeriesDescription(
      "Surface (STL)", options.parameter_summary, source_reference);
  return objects;
}

}  // namespace interslice

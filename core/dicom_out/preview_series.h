// The previews of a job (core/preview) as DICOM: a Secondary Capture image
// series (SOP Class 1.2.840.10008.5.1.4.1.1.7, one single-frame image per
// view) in the source's study, so that a radiologist sees in any PACS
// viewer what the job made (docs/dicom-output.md, "Previews").
//
// Why single-frame SC and not one Multi-frame True Color SC object: the
// views differ in size (a multi-frame object has one Rows x Columns), every
// PACS and viewer (OHIF included) shows SC images, and each view keeps its
// own PatientOrientation and description.
//
// Each image: SamplesPerPixel 3, PhotometricInterpretation RGB,
// PlanarConfiguration 0 (colour-by-pixel), 8 bits, native Little Endian
// Explicit; BurnedInAnnotation YES (the legend is in the pixels; it holds
// no patient data); ImageType DERIVED\SECONDARY; ConversionType WSD;
// Modality OT; PatientOrientation of the view; ImageComments and
// DerivationDescription say which view it is; InstanceNumber = position in
// `pictures` + 1. No Frame of Reference and no image plane: a picture is
// not in patient coordinates (the Frame of Reference copied with the
// patient and study is removed).
//
// References ("derived from the intensity series"): with `referenced` (the
// image series on the job's output grid the previews were drawn from: the
// intensity series the job writes, or the reference series itself when the
// grid is its own), SourceImageSequence lists, per picture, the image of
// that series it shows (a plane normal to the slices: image k), or every
// image (the other planes and the 3D view), purpose "Source image for image
// processing operation" (DCM 121322), and ReferencedSeriesSequence names the
// series. Without it, the source series' images (the one or two source
// slices nearest to plane k, or all) and the source series.
//
// Identity: PlanPreviewSeries, under the same job identity as
// PlanDerivedObjects: the same job names its previews the same, so sending
// them again replaces them. Series number base + 6 (base + 5 is a fill's
// RTSTRUCT), SeriesDescription "interslice previews".
#ifndef INTERSLICE_CORE_DICOM_OUT_PREVIEW_SERIES_H_
#define INTERSLICE_CORE_DICOM_OUT_PREVIEW_SERIES_H_

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/dicom/series_reader.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/geometry/volume.h"

namespace interslice {

// Series number offset of the previews from the series number base.
inline constexpr int kPreviewSeriesNumberOffset = 6;

// One picture: 8-bit RGB rows from the top, 3 bytes per pixel.
struct RgbPicture {
  std::string name;  // "axial", ...: names its UID, so keep it stable
  int width = 0, height = 0;
  const std::vector<uint8_t>* rgb = nullptr;  // not owned
  // ImageComments / DerivationDescription: what the picture shows (no
  // patient data).
  std::string description;
  // DICOM PatientOrientation, e.g. "L\P".
  std::string patient_orientation;
  // The output grid slice the picture shows when it is a plane of constant
  // slice index (an axial view), else unset.
  std::optional<int64_t> output_slice;
};

// The identity of the preview series for `names` (one SOP instance per
// name, in order): see "Identity" above. Its study (and frame of reference,
// unused by SC) are `same_study`'s when given: pass another object of the
// job, so that a source without a study (anonymised, a study made for the
// job; random when its UIDs are) keeps all its objects in one study. Errors
// as PlanDerivedObjects's; INVALID_ARGUMENT for no names or repeated ones.
absl::StatusOr<DerivedObjectIdentity> PlanPreviewSeries(
    const DicomSeries& source, const std::vector<std::string>& names,
    const DicomWriteOptions& options,
    const DerivedObjectIdentity* same_study = nullptr);

// Writes `pictures` as Secondary Capture images IM00001.dcm ... into
// `output_dir` (created if missing; written into a fresh sibling folder
// first and renamed into place, so a series never mixes two runs).
// `identity` is PlanPreviewSeries for their names; `grid` the output grid
// (for output_slice); `referenced` as above, may be null. Returns the paths
// in picture order. INVALID_ARGUMENT for a picture without pixels, of the
// wrong size or over 65535 pixels a side, or an identity that does not name
// one instance per picture; FAILED_PRECONDITION when the first source file
// cannot be read again; INTERNAL naming the path when writing fails.
absl::StatusOr<std::vector<std::string>> WritePreviewSeries(
    const DicomSeries& source, const Grid& grid,
    const std::vector<RgbPicture>& pictures,
    const DerivedObjectIdentity& identity,
    const DerivedObjectIdentity* referenced, const DicomWriteOptions& options,
    const std::string& output_dir);

}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_OUT_PREVIEW_SERIES_H_

// The enhanced layout of the intensity series (`--dicom-layout enhanced`):
// the whole derived intensity volume as ONE multi-frame instance, frame
// k + 1 = output slice k, instead of one image per slice
// (WriteIntensitySeries, the classic layout and the default):
// - a CT source: Enhanced CT Image (1.2.840.10008.5.1.4.1.1.2.1, DICOM
//   PS3.3 A.38);
// - an MR source (modality MR: MR Image, Enhanced MR or Legacy Converted
//   Enhanced MR Image): Enhanced MR Image (1.2.840.10008.5.1.4.1.1.4.1,
//   PS3.3 A.36.2).
// Written with DCMTK's dcmect (EctEnhancedCT) and dcmfg functional groups;
// DCMTK 3.6.7 has no Enhanced MR class, so the MR object is the same build
// with its MR-specific attributes and functional group written into the
// dataset (enhanced_series.cc). PACS and viewers that take enhanced objects
// (OHIF, 3D Slicer, dcm2niix, GDCM) load one file instead of hundreds.
//
// Same volume: every frame's ImagePositionPatient / ImageOrientationPatient /
// PixelSpacing and stored values (with the same RescaleSlope / Intercept,
// windows and PixelPaddingValue) equal the classic layout's image k (the
// geometry contract of dicom_writer.h holds frame by frame). For MR the
// frames' rescale is the identity when the classic MR images carry none.
//
// Any other modality (PT, XA, ...) is FAILED_PRECONDITION naming it.
#ifndef INTERSLICE_CORE_DICOM_OUT_ENHANCED_SERIES_H_
#define INTERSLICE_CORE_DICOM_OUT_ENHANCED_SERIES_H_

#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/dicom/series_reader.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/geometry/volume.h"

namespace interslice {

// File name of the enhanced instance inside the intensity folder
// (series-intensity/enhanced.dcm).
inline constexpr char kEnhancedIntensityFileName[] = "enhanced.dcm";

// The identity of the enhanced instance of a job whose classic intensity
// identity is `classic` (PlanDerivedObjects(...).intensity): the same
// series number, description, study and frame of reference; its own series,
// SOP instance and dimension organization UIDs, each derived from the
// classic series UID (so deterministic whenever that is, random under
// random_uids, and never the classic series' UIDs: a PACS that holds both
// layouts of a job keeps them apart). SOP class Enhanced CT Image Storage
// for a CT source, Enhanced MR Image Storage for an MR source.
// FAILED_PRECONDITION for a source of another modality (see above);
// INVALID_ARGUMENT for a malformed UID root or an empty classic identity.
absl::StatusOr<DerivedObjectIdentity> PlanEnhancedIntensity(
    const DicomSeries& source, const DerivedObjectIdentity& classic,
    const DicomWriteOptions& options);

// Writes `values` (modality values on the output grid, see dicom_writer.h)
// as the one enhanced instance named by `identity` (PlanEnhancedIntensity)
// to `path`, atomically (its folder must exist).
// - Shared functional groups: Pixel Measures, Plane Orientation, the image
//   frame type DERIVED\PRIMARY\VOLUME\RESAMPLED (CT Image Frame Type; MR
//   Image Frame Type with the source's ComplexImageComponent, default
//   MAGNITUDE, and AcquisitionContrast, default UNKNOWN), Pixel Value
//   Transformation (the classic layout's slope, intercept and type: "HU"
//   for CT, "US" for MR), Frame VOI LUT (the source's windows), Frame
//   Anatomy (from the source's Body Part Examined, PS3.16 Annex L; "Entire
//   body" when it names none we know); CT only: Irradiation Event
//   Identification (the source's, else a derived UID).
// - Per frame: Plane Position, Frame Content (dimension index k + 1 along
//   ImagePositionPatient, stack "1", in-stack position k + 1) and Derivation
//   Image (the one or two source slices nearest along the normal, with their
//   frame number when the source is multi-frame; derivation DCM 113085
//   "Spatial resampling", purpose DCM 121322).
// - Dimension Organization: one dimension, ImagePositionPatient in the Plane
//   Position Sequence; DimensionOrganizationType 3D.
// - Pixel data: options.intensity_encoding: native Explicit VR Little Endian
//   or RLE Lossless (one fragment per frame, DCMTK's RLE codec).
// FAILED_PRECONDITION for a source that is neither CT nor MR;
// INVALID_ARGUMENT for a bad grid, values, or an identity not planned for
// this source's modality, or pixel data over
// DICOM's 4 GiB element limit; FAILED_PRECONDITION when a source file cannot
// be read again; INTERNAL (naming the step) when DCMTK refuses a value or
// the file cannot be written.
absl::Status WriteEnhancedIntensity(const DicomSeries& source,
                                    const Volume<float>& values,
                                    const DerivedObjectIdentity& identity,
                                    const DicomWriteOptions& options,
                                    const std::string& path);

}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_OUT_ENHANCED_SERIES_H_

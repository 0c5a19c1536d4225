// Writing interslice results back to DICOM (DCMTK): the objects a PACS and
// its viewers are made for, all on the refined output grid of a job:
// - the intensity series: the source's modality values (HU for CT) resampled
//   from where each source slice really is (ResampleSourceSlices), as a CT or
//   MR image series (Secondary Capture for other modalities);
// - the mask as a binary DICOM Segmentation (SEG), and
// - the signed distance as a Parametric Map (float pixels, real-world value
//   mapping in millimetres).
// The SEG and the Parametric Map derive from the intensity series: frame k
// references image k of it (same position, same orientation, same frame of
// reference), so a viewer that opens the intensity series overlays them
// exactly, whether it places frames by reference or by position. See
// docs/dicom-output.md for why these objects and how viewers open them.
//
// Geometry contract (shared by every writer here):
// - `source` is what ReadDicomSeries returned; its files (slices[k].path) must
//   still be readable, because the Patient and Study modules are copied from
//   the first one (never invented, never logged).
// - The output grid is any grid (see core/geometry/volume.h) whose direction
//   equals the source grid's direction (to 1e-4): same row and column
//   directions, slices stacked along the source's normal n = row x column.
//   Its origin, size and spacing are free (an isotropic refinement of the
//   source, or a crop of it). Otherwise INVALID_ARGUMENT.
// - Slice k of the output is written at ImagePositionPatient = grid origin +
//   k * spacing[2] * n, with InstanceNumber k + 1 (frame k + 1 in multi-frame
//   objects), so numbers grow along n (the order our reader sorts in).
//   ImageOrientationPatient is the first two direction columns; PixelSpacing
//   = (spacing[1], spacing[0]) (row spacing first, as DICOM wants);
//   SliceThickness = SpacingBetweenSlices = spacing[2]. Reading the series
//   back with ReadDicomSeries (or ITK/GDCM) reproduces the grid.
//
// Identity (PlanDerivedObjects):
// - UIDs are derived, by default, from the source instances, the job's
//   parameters (options.derivation_key), the UID root and the object, as
//   name-based UUIDs (RFC 4122 version 5, SHA-1) under "2.25" (ITU-T X.667,
//   DICOM PS3.5 B.2), or the root followed by the UUID's decimal digits. So
//   the same job on the same source names its results the same, and sending
//   them to a PACS again replaces instead of duplicating. random_uids gives
//   fresh random UIDs every run. A source whose SOP Instance UIDs were
//   blanked by an anonymiser is identified instead by its files' meta
//   header MediaStorageSOPInstanceUIDs, else by the digest of its pixels
//   (DicomSeries::pixel_digest): its UIDs are as stable across reruns.
// - StudyInstanceUID, FrameOfReferenceUID and the Patient, General Study and
//   Patient Study modules (and SpecificCharacterSet) are copied from the first
//   source file; empty source values of conditional attributes are dropped
//   (so a source with DICOM errors of its own does not pass them on), and
//   type 2 attributes absent there are written empty. A source without a
//   StudyInstanceUID or FrameOfReferenceUID gets ones named from the source
//   alone (its instance identity above and the UID root, not the job): every
//   job on the same series (`run`, `fill`, a rerun) puts its objects in the
//   same study and frame of reference; another series gets others.
// - Series numbers: options.series_number_base, else 1000 x the source's
//   SeriesNumber (else 9000) + 10 x the parameter set's slot; the intensity
//   series gets base + 1, the distance map base + 2, the SEG base + 3, the
//   Encapsulated STL mesh base + 4, a fill's RTSTRUCT base + 5 and the
//   previews base + 6 (preview_series.h). The slot (0..99) is the name-based
//   UUID of options.parameter_set (uid.h DeriveDicomUid) modulo 100, so a
//   rerun with the same parameters gets the same numbers (and, with the same
//   derivation_key, the same UIDs: a PACS replaces the results), and another
//   parameter set other numbers except with probability 1/100 (then the
//   descriptions, and always the UIDs, still differ). Empty parameter_set
//   or an explicit series_number_base: slot 0. A base that leaves no room
//   for base + 6 in a DICOM IS (signed 32 bits) is INVALID_ARGUMENT; 1000 x
//   a source number that does not is replaced by 9000.
// - Series descriptions, read at a glance in a study's series list: the
//   object in words ("Segmentation", "Interpolated", "Distance (mm)",
//   "Surface (STL)", "Previews"), then " " and the options' summary when
//   given, then ", from #<source SeriesNumber> <source SeriesDescription>"
//   (either alone when the other is missing; a source description that is
//   not printable ASCII is left out), cut at the 64 characters of an LO
//   from the end, e.g. "Segmentation >=300 HU, 0.5 mm, smooth, from #3
//   HEAD 5MM".
// - Equipment (Manufacturer etc.) describes interslice, the creator of the
//   derived objects, not the scanner.
//
// Errors: INVALID_ARGUMENT for bad inputs (grid mismatch, wrong voxel count,
// non-finite values, values that cannot be encoded, a malformed UID root);
// FAILED_PRECONDITION when a source file cannot be read again; INTERNAL (with
// the output path and the system's reason) when the output folder or a file
// cannot be created or written. Messages never contain patient data.
#ifndef INTERSLICE_CORE_DICOM_OUT_DICOM_WRITER_H_
#define INTERSLICE_CORE_DICOM_OUT_DICOM_WRITER_H_

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/dicom/series_reader.h"
#include "core/geometry/volume.h"

namespace interslice {

struct DicomWriteOptions {
  // Root for the new UIDs (digits and dots, no leading zeros in a component,
  // at most 40 characters so that 24 digits fit into the 64-character
  // limit). Empty means "2.25." + UUID.
  std::string uid_root;
  // Fresh random UIDs on every run instead of UIDs derived from the source
  // and the job (see "Identity" above).
  bool random_uids = false;
  // What, besides the source instances and the root, identifies the result:
  // the job's parameters in a canonical text (the pipeline writes threshold,
  // method, grid and so on). Two jobs with the same key on the same source
  // get the same UIDs.
  std::string derivation_key;
  // What, besides derivation_key, shapes the Encapsulated STL alone (the
  // pipeline: its own mesh simplification when not the default): it names
  // the STL's UIDs and no other object's. Empty = nothing more.
  std::string surface_derivation_key;
  // What shapes the intensity series alone (the pipeline: the grid, the ROI,
  // the intensity method, ... but not the thresholds or the solver). When
  // given, it replaces derivation_key and parameter_set for the intensity
  // series: its UIDs and its series numbers' slot; so jobs on one source
  // that differ only in what does not change a grey value share one
  // intensity series (a PACS keeps one copy). Empty = derivation_key.
  std::string intensity_derivation_key;
  // First of the series numbers of the derived objects (see "Identity");
  // <= 0 derives it from the source's SeriesNumber and parameter_set.
  int series_number_base = 0;
  // Results of other parameters told apart (see "Identity"): the parameters
  // that pick the series numbers' slot (the pipeline: method, thresholds,
  // output grid, ...; empty = slot 0), and a short text of them in words for
  // the series descriptions of the segmentation, distance map, mesh and
  // previews (">=300 HU, 0.5 mm, smooth"; empty = none), and of the
  // intensity series ("0.5 mm, motion-compensated"; empty = the same as the
  // others'): what it depends on, not the thresholds. Keep them within 30
  // characters and free of patient data.
  std::string parameter_set;
  std::string parameter_summary;
  std::string intensity_summary;
  // Start of DerivationDescription; the writer appends what the content is
  // (and, for intensity, the interpolator). Keep it free of patient data.
  std::string derivation_description =
      "interslice shape-based interpolation (Csebfalvi et al. 2001)";
  // SoftwareVersions of the creating equipment.
  std::string software_version = "interslice";
  // Pixel data of the intensity series: kNative (default) = Explicit VR
  // Little Endian; kRleLossless = encapsulated RLE Lossless
  // (1.2.840.10008.1.2.5, DCMTK's RLE codec): the same stored values, which
  // every DICOM decoder restores exactly, in fewer bytes (about 0.6 of
  // native on the CT phantom, docs/speed/whole-job-notes.md). Only the
  // intensity series is affected: the SEG's 1-bit frames and the Parametric
  // Map's Float Pixel Data stay native (DCMTK's RLE encoder takes 8/16-bit
  // samples only, and Float Pixel Data has no encapsulated transfer syntax).
  enum class PixelEncoding { kNative, kRleLossless };
  PixelEncoding intensity_encoding = PixelEncoding::kNative;
  // How the intensity series' values between source slices were made, for
  // what the series says of itself: kLinear (ResampleSourceSlices) or kMorph
  // (core/morph MorphIntensity: carried along the motion between the source
  // slices). It changes the DerivationDescription and, for kMorph, the
  // SourceImageSequence of an output slice between two source slices also
  // lists their outer neighbours, whose values shape it (the value tangents).
  enum class IntensityInterpolation { kLinear, kMorph };
  IntensityInterpolation intensity_interpolation =
      IntensityInterpolation::kLinear;
};

// The identity of one derived object: series UID, SOP instance UIDs (one per
// output slice for an image series, one for a multi-frame object), series
// number and description.
struct DerivedObjectIdentity {
  std::string series_instance_uid;
  std::vector<std::string> sop_instance_uids;
  int series_number = 0;
  std::string series_description;
  // SOP Class UID of the instances.
  std::string sop_class_uid;
  // Dimension Organization UID (multi-frame objects only).
  std::string dimension_organization_uid;
  // The study and frame of reference the object belongs to: the source's,
  // or (for an anonymised source that has none) one made for the job and
  // shared by all its objects, so that they stay together and valid.
  std::string study_instance_uid;
  std::string frame_of_reference_uid;
};

// The identities of every object one job may write.
struct DerivedObjects {
  DerivedObjectIdentity intensity;     // one instance per output slice
  DerivedObjectIdentity distance_map;  // Parametric Map, one instance
  DerivedObjectIdentity segmentation;  // SEG, one instance
  // The surface mesh as Encapsulated STL (core/dicom_out/encapsulated_stl.h),
  // one instance, series number base + 4.
  DerivedObjectIdentity surface_stl;
};

// The series description of another derived object of the source (a fill's
// structure set): `object`, `summary` and the source series, as "Identity"
// above says. FAILED_PRECONDITION when the first source file cannot be read
// again.
absl::StatusOr<std::string> DescribeDerivedSeries(const DicomSeries& source,
                                                  std::string_view object,
                                                  std::string_view summary);

// Names the derived objects of a job whose output grid has `output_slices`
// slices (see "Identity" above). INVALID_ARGUMENT for a malformed UID root
// or output_slices < 1; FAILED_PRECONDITION when the first source file
// cannot be read again (for its SeriesNumber).
absl::StatusOr<DerivedObjects> PlanDerivedObjects(
    const DicomSeries& source, int64_t output_slices,
    const DicomWriteOptions& options);

// The source's modality values on `target`, computed from where each source
// slice really is: `image` holds the source slices in order (after gantry
// tilt resampling and any region-of-interest crop: its in-plane size, spacing,
// direction and in-plane origin must equal the target's, to 1e-3 mm and
// 1e-4), and `positions_mm[k]` is the true position of image slice k along
// the normal n (strictly increasing; the z spacing of image.grid is ignored,
// so uneven gaps and missing slices are placed right). Target slice k at
// position p (along n) is the linear blend of the two source slices that
// bracket p, the nearest source slice within half a target spacing beyond the
// first or last, and the outside value beyond that: `pixel_padding` if given,
// else the image's minimum (air). Linear, because it never overshoots (no
// ringing at bone/air edges across 5 mm slices) and is exact on the source
// slices; written here because ITK's resamplers need a regular source grid,
// which an uneven series is not. `pixel_padding` is a value the source uses
// to mark pixels outside the scanned field (DICOM PixelPaddingValue, in
// modality units): a blend that involves such a pixel is padding too, so
// padding never bleeds into the anatomy. INVALID_ARGUMENT for mismatched
// grids or positions; CANCELLED / DEADLINE_EXCEEDED from context. Threads:
// context.threads; the result does not depend on them.
absl::StatusOr<Volume<float>> ResampleSourceSlices(
    const Volume<float>& image, const std::vector<double>& positions_mm,
    const Grid& target, std::optional<float> pixel_padding,
    const ComputeContext& context);

// ResampleSourceSlices on the part `box` of `target` only: the same values
// at those voxels, on CropGrid(target, box), computing only them (e.g. one
// plane for a preview; the source image is cropped in-plane to the box).
// INVALID_ARGUMENT for a box not valid for `target`, else as
// ResampleSourceSlices.
absl::StatusOr<Volume<float>> ResampleSourceSlicesInBox(
    const Volume<float>& image, const std::vector<double>& positions_mm,
    const Grid& target, const VoxelBox& box, std::optional<float> pixel_padding,
    const ComputeContext& context);

// The source's first display window (WindowCenter / WindowWidth of the first
// source file), modality units, if it has one with a positive width.
// FAILED_PRECONDITION when the first source file cannot be read again.
struct SourceWindow {
  double center = 0;
  double width = 0;
};
absl::StatusOr<std::optional<SourceWindow>> SourceDisplayWindow(
    const DicomSeries& source);

// The source's pixel padding, in modality units (PixelPaddingValue x
// RescaleSlope + RescaleIntercept of the first source slice), if it has one.
// FAILED_PRECONDITION when the first source file cannot be read again.
absl::StatusOr<std::optional<float>> SourcePixelPadding(
    const DicomSeries& source);

// Writes `values` (modality values on the output grid, see the contract
// above; usually from ResampleSourceSlices) as a derived single-frame image
// series into `output_dir` (created if missing), one file per slice named
// IM00001.dcm, IM00002.dcm, ... in InstanceNumber order, each written to a
// temporary name and renamed into place. Files of the same names are
// replaced; other files are left alone, so use a folder per series. Returns
// the paths written, in slice order. `identity` is
// PlanDerivedObjects(...).intensity.
//
// IOD: CT Image Storage when the source is CT Image Storage, MR Image Storage
// when it is MR Image Storage (their type 1/2 acquisition attributes, e.g.
// KVP or ScanningSequence, are copied from the source), otherwise Secondary
// Capture Image Storage with the Image Plane module added (a standard
// extended SOP class; our reader needs the plane). ImageType is
// DERIVED\SECONDARY\AXIAL (CT), DERIVED\SECONDARY\OTHER (MR) or
// DERIVED\SECONDARY (SC). Stored with the first source slice's RescaleSlope
// and RescaleIntercept (rounded to the nearest stored value; uint16 if every
// stored value is >= 0, else int16; the slope is raised along 1-2-5 steps
// only if a value does not fit). RescaleType "HU" for CT. MR images get
// RescaleSlope/Intercept only when not the identity (standard extended: the
// MR IOD has no Modality LUT). The source's windows (every WindowCenter /
// WindowWidth pair and their explanations) are kept, else the data range;
// the source's PixelPaddingValue is kept (in the same stored units) when
// present. SourceImageSequence (per slice: the one or two source slices
// nearest along n, purpose DCM 121322) and ReferencedSeriesSequence (every
// source instance) point back to the source. Little Endian Explicit,
// uncompressed.
absl::StatusOr<std::vector<std::string>> WriteIntensitySeries(
    const DicomSeries& source, const Volume<float>& values,
    const DerivedObjectIdentity& identity, const DicomWriteOptions& options,
    const std::string& output_dir);

// A coded concept (CodeValue, CodingSchemeDesignator, CodeMeaning).
struct CodedConcept {
  std::string value;
  std::string scheme;
  std::string meaning;
};

// The one segment of a job's SEG: SegmentLabel, SegmentedPropertyCategory
// (DICOM PS3.16 CID 7150 "Segmentation Property Categories") and
// SegmentedPropertyType. The default is only what WriteSegmentation needs to
// be called; a job names its segment with DescribeThresholdSegment.
struct SegmentDescription {
  std::string label = "Bone";
  CodedConcept category = {"85756007", "SCT", "Tissue"};
  CodedConcept type = {"272673000", "SCT", "Bone"};
  std::string algorithm_name = "interslice";
  // The segment's display colour (sRGB, 0..255 each), written as its
  // RecommendedDisplayCIELabValue (PS3.3 C.8.20.2): without one, viewers
  // (OHIF) warn and pick a colour of their own. Default: bone as 3D Slicer's
  // GenericAnatomyColors shows it.
  std::array<uint8_t, 3> rgb = {241, 214, 145};
};

// The codes DescribeThresholdSegment chooses from. Bone: SNOMED CT
// 272673000 "Bone structure" (CID 7166 "Common Tissue Segmentation Types"
// meaning "Bone") in category SCT 85756007 "Tissue" (CID 7150). Anything
// else: SNOMED CT 91723000 "Anatomical structure", the root of SNOMED CT's
// anatomy hierarchy and CID 7150's "Anatomical Structure" category, as both
// category and type: true of any region a threshold cuts out of a body
// without claiming what tissue it is.
inline constexpr char kBoneCodeValue[] = "272673000";
inline constexpr char kTissueCodeValue[] = "85756007";
inline constexpr char kAnatomicalStructureCodeValue[] = "91723000";

// Below this lower threshold (HU) a CT region is not called bone: the
// cancellous bone of the skull and spine starts at about 200-300 HU, while
// contrast-enhanced vessels and soft tissue reach 100-200 HU.
inline constexpr double kBoneThresholdHu = 200;

// A coded concept as a person writes it: "scheme:value:meaning", e.g.
// "SCT:272673000:Bone" (the meaning may contain ':'). The scheme must be a
// valid DICOM CS designator (1-16 of A-Z, 0-9, space, '_'; e.g. SCT, DCM,
// FMA, LN, RADLEX, 99LOCAL), the value a valid SH (1-16 characters, no
// backslash or control character), the meaning a valid LO (1-64, no
// backslash or control character). INVALID_ARGUMENT saying which part is
// wrong (never echoing the text).
absl::StatusOr<CodedConcept> ParseCodedConcept(std::string_view text);

// INVALID_ARGUMENT unless `label` is a valid SegmentLabel (LO: 1-64
// characters, no backslash or control character).
absl::Status ValidateSegmentLabel(std::string_view label);

// The segment of a threshold job on `source` (object = lower <= value
// (<= upper), modality units):
// - `code` given: type = code, category Tissue for the tissue codes above
//   (bone, tissue), else Anatomical Structure; label = `label`, else the
//   code's meaning.
// - no code: Bone (SCT 272673000, category Tissue) only for CT with lower
//   >= kBoneThresholdHu; otherwise "Region above N <units>" ("Region N to M
//   <units>" with an upper threshold) coded Anatomical Structure, where the
//   units are HU for CT, else the first source file's RescaleType (0028,1054;
//   an LO, kept whole, e.g. "SIGNAL INTENSITY (UNITLESS)") or Units
//   (0054,1001, e.g. BQML for PET), else "units". `label` replaces the
//   label, not the code.
// The colour: SegmentDescription's default (bone) for the bone type, else
// the colour a fill gives its first label (label_segmentation.h
// DefaultLabelSegment(1)).
// FAILED_PRECONDITION when the first source file cannot be read again;
// INVALID_ARGUMENT for a label that is not a valid SegmentLabel, or, without
// `label`, when the units make "Region ..." longer than the 64 characters a
// SegmentLabel holds (never cut: the message says to name the segment).
absl::StatusOr<SegmentDescription> DescribeThresholdSegment(
    const DicomSeries& source, double lower, std::optional<double> upper,
    std::string_view label, const std::optional<CodedConcept>& code);

// Writes `mask` (nonzero = inside; on the output grid, see the contract
// above) as a binary DICOM Segmentation with one segment (SegmentAlgorithmType
// AUTOMATIC), atomically, to `path` (its folder must exist). `identity` is
// PlanDerivedObjects(...).segmentation and `referenced` its .intensity: the
// intensity series on the same grid, which the SEG derives from.
// - The segment: `segment`'s label, category and type codes, and its colour
//   as RecommendedDisplayCIELabValue (converted as the fill's SEG converts
//   its colours, label_segmentation.h SegmentCieLab).
// - One frame per output slice, in slice order, empty slices included, so
//   that the frames tile the whole output grid and a reader needs nothing but
//   the SEG to rebuild it. Shared functional groups: PixelMeasures (as in the
//   intensity series), PlaneOrientationPatient; per frame:
//   PlanePositionPatient, FrameContent (dimension indices: segment number,
//   then slice k + 1 along ImagePositionPatient) and DerivationImage (image
//   k of the intensity series, purpose "Source image for image processing
//   operation").
// - ReferencedSeriesSequence lists every instance of the intensity series;
//   FrameOfReferenceUID and study are the source's (the intensity series has
//   them too).
absl::Status WriteSegmentation(const DicomSeries& source,
                               const Volume<uint8_t>& mask,
                               const DerivedObjectIdentity& identity,
                               const DerivedObjectIdentity& referenced,
                               const SegmentDescription& segment,
                               const DicomWriteOptions& options,
                               const std::string& path);

// Writes the signed distance field (mm, positive inside; on the output grid)
// as a Parametric Map (DCMTK dcmpmap), one multi-frame instance with 32-bit
// float pixel data, atomically, to `path` (its folder must exist). The Real
// World Value Mapping says the values are millimetres (UCUM "mm") of a signed
// distance; frames, functional groups, dimensions and references are
// organised as for WriteSegmentation (frame k references image k of the
// intensity series `referenced`). INVALID_ARGUMENT for non-finite values.
absl::Status WriteDistanceMap(const DicomSeries& source,
                              const Volume<float>& distance,
                              const DerivedObjectIdentity& identity,
                              const DerivedObjectIdentity& referenced,
                              const DicomWriteOptions& options,
                              const std::string& path);

// A few lines of text to write beside mesh files (e.g. surface.txt): vertices
// are DICOM patient coordinates (LPS, mm) of the source's Frame of Reference
// (its UID is included), triangles are counter-clockwise seen from outside,
// and how to convert to RAS. Contains UIDs but no patient data.
std::string MeshConventionNote(const DicomSeries& source);

// A new UID under `root` (empty: "2.25." + UUID); INVALID_ARGUMENT if `root`
// is malformed or too long. Exposed for callers that name other objects of
// the same job.
absl::StatusOr<std::string> GenerateDicomUid(const std::string& root);

// The UID named by `name` under `root`: a name-based UUID (RFC 4122 version
// 5: SHA-1 of interslice's namespace UUID and `name`) as "2.25." + its
// decimal value when `root` is empty, else `root` + "." + as many of those
// decimal digits as fit into 64 characters. The same name and root always
// give the same UID. INVALID_ARGUMENT if `root` is malformed or too long.
absl::StatusOr<std::string> DeriveDicomUid(const std::string& root,
                                           std::string_view name);

}  // namespace interslice

#endif  // INTERSLICE_CORE_DICOM_OUT_DICOM_WRITER_H_

// The wire spec <-> the core specs: defaults as the command line's, round
// trips, refusals that name the wire field, and every option table row
// pointing at a field the wire really has.
#include "job/wire.h"

#include <string>
#include <vector>

#include "gmock/gmock.h"
#include "google/protobuf/descriptor.h"
#include "gtest/gtest.h"
#include "job/errors.h"
#include "job/job.h"
#include "job/options.h"

namespace interslice::job {
namespace {

using ::testing::HasSubstr;

TEST(WireTest, DefaultsMatchTheCli) {
  v1::JobSpec p;
  EXPECT_FALSE(JobSpecFromWire(p).ok());  // threshold is required
  p.set_threshold(300);
  absl::StatusOr<JobSpec> spec = JobSpecFromWire(p);
  ASSERT_TRUE(spec.ok()) << spec.status();
  EXPECT_EQ(spec->solver.method, SolverMethod::kConjugateGradient);
  EXPECT_EQ(spec->solver.max_iterations, 15);
  EXPECT_EQ(spec->volume_formats, std::vector<std::string>{"nii"});
  EXPECT_EQ(spec->mesh_formats, std::vector<std::string>{"stl"});
  // Previews: PNG unless the wire says otherwise, as on the command line.
  EXPECT_EQ(spec->preview_formats, std::vector<std::string>{"png"});
  p.mutable_previews();  // present and empty: none
  EXPECT_TRUE(JobSpecFromWire(p)->preview_formats.empty());
  p.mutable_previews()->add_formats(v1::PREVIEW_FORMAT_DICOM);
  EXPECT_EQ(JobSpecFromWire(p)->preview_formats,
            std::vector<std::string>{"dicom"});
  p.mutable_previews()->add_formats(static_cast<v1::PreviewFormat>(7));
  EXPECT_THAT(std::string(JobSpecFromWire(p).status().message()),
              HasSubstr("spec.previews.formats: unknown format 7"));
  p.clear_previews();
  p.set_tolerance(1e-3);
  EXPECT_EQ(JobSpecFromWire(p)->solver.max_iterations, 100000);
  p.mutable_outputs();  // present and empty: no files
  EXPECT_TRUE(JobSpecFromWire(p)->mesh_formats.empty());
  p.set_strict_spacing(true);
  p.set_strict_frame_of_reference(true);
  p.set_uid_root("1.2.3");
  p.mutable_segmentation()->set_enabled(true);
  p.set_multiframe_volume("stack 1");
  auto mapped = JobSpecFromWire(p);
  ASSERT_TRUE(mapped.ok()) << mapped.status();
  EXPECT_TRUE(mapped->strict_spacing);
  EXPECT_TRUE(mapped->strict_frame_of_reference);
  EXPECT_TRUE(mapped->write_seg);
  EXPECT_EQ(mapped->uid_root, "1.2.3");
  EXPECT_EQ(mapped->multiframe_volume, "stack 1");
  p.set_method(v1::SOLVER_METHOD_MORPH);
  EXPECT_EQ(JobSpecFromWire(p)->solver.method, SolverMethod::kMorph);
  p.mutable_derived_series()->add_contents("mask");
  EXPECT_EQ(JobSpecFromWire(p)->output_series,
            std::vector<std::string>{"mask"});
  p.mutable_derived_series()->add_contents("bogus");
  EXPECT_EQ(JobSpecFromWire(p).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(WireTest, UncompressedNiftiAndRleIntensityMap) {
  v1::JobSpec p;
  p.set_threshold(300);
  p.mutable_outputs()->add_volume_formats(v1::VOLUME_FORMAT_NIFTI_UNCOMPRESSED);
  p.mutable_outputs()->add_volume_formats(v1::VOLUME_FORMAT_NIFTI);
  absl::StatusOr<JobSpec> spec = JobSpecFromWire(p);
  ASSERT_TRUE(spec.ok()) << spec.status();
  EXPECT_EQ(spec->volume_formats,
            (std::vector<std::string>{"nii-uncompressed", "nii"}));
  EXPECT_EQ(spec->dicom_compression, "none");
  p.mutable_derived_series()->set_pixel_compression(
      v1::DICOM_PIXEL_COMPRESSION_RLE_LOSSLESS);
  EXPECT_EQ(JobSpecFromWire(p)->dicom_compression, "rle");
  p.mutable_derived_series()->set_pixel_compression(
      v1::DICOM_PIXEL_COMPRESSION_NONE);
  EXPECT_EQ(JobSpecFromWire(p)->dicom_compression, "none");
  p.mutable_derived_series()->set_pixel_compression(
      static_cast<v1::DicomPixelCompression>(99));
  EXPECT_EQ(JobSpecFromWire(p).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(MediaTypeForArtifact("distance.nii"), "application/octet-stream");
}

// DicomSeriesOutput.layout: unspecified and CLASSIC are the classic layout,
// ENHANCED the one Enhanced CT instance; an unknown value names the option.
TEST(WireTest, DicomLayoutMaps) {
  v1::JobSpec p;
  p.set_threshold(300);
  EXPECT_EQ(JobSpecFromWire(p)->dicom_layout, "classic");
  EXPECT_EQ(ToWire(*JobSpecFromWire(p)).derived_series().layout(),
            v1::DICOM_LAYOUT_UNSPECIFIED);
  p.mutable_derived_series()->set_layout(v1::DICOM_LAYOUT_ENHANCED);
  EXPECT_EQ(JobSpecFromWire(p)->dicom_layout, "enhanced");
  EXPECT_EQ(ToWire(*JobSpecFromWire(p)).derived_series().layout(),
            v1::DICOM_LAYOUT_ENHANCED);
  p.mutable_derived_series()->set_layout(v1::DICOM_LAYOUT_CLASSIC);
  EXPECT_EQ(JobSpecFromWire(p)->dicom_layout, "classic");
  p.mutable_derived_series()->set_layout(static_cast<v1::DicomLayout>(7));
  const absl::Status bad = JobSpecFromWire(p).status();
  EXPECT_EQ(bad.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(ErrorOptionKey(bad), "dicom_layout");
}

// Each table row names its wire field by path ("spec.derived_series.
// series_number"): the path must resolve in interslice.v1.JobSpec, so the
// table cannot drift from the proto.
template <typename Options>
void ExpectWireFieldsExist(std::span<const OptionDef<Options>> table) {
  for (const OptionDef<Options>& def : table) {
    if ((def.doors & kWire) == 0) continue;
    absl::string_view path = def.wire;
    ASSERT_TRUE(path.substr(0, 5) == "spec.") << def.key;
    path.remove_prefix(5);
    const google::protobuf::Descriptor* message = v1::JobSpec::descriptor();
    const google::protobuf::FieldDescriptor* field = nullptr;
    while (!path.empty()) {
      ASSERT_NE(message, nullptr) << def.wire;
      const size_t dot = path.find('.');
      const std::string name(path.substr(0, dot));
      field = message->FindFieldByName(name);
      ASSERT_NE(field, nullptr) << def.key << ": no field " << def.wire;
      message = field->message_type();
      path = dot == absl::string_view::npos ? "" : path.substr(dot + 1);
    }
  }
}

TEST(WireTest, EveryOptionNamesAWireField) {
  ExpectWireFieldsExist(InterpolationOptionTable());
  ExpectWireFieldsExist(FillOptionTable());
}

// Whatever the command line (or a rule) builds goes over the wire and comes
// back as the same spec: the server runs what the client asked for.
TEST(WireTest, InterpolationSpecsRoundTrip) {
  std::vector<InterpolationOptions> cases(4);
  for (InterpolationOptions& o : cases) {
    o.inputs = {"in"};
    o.out = "out";
    o.threshold = 300;
  }
  cases[1].upper = 2000.5;
  cases[1].method = "direct";
  cases[1].roi = "1,2,0,100,120,5";
  cases[1].spacing = 0.7;
  cases[1].output_series = "intensity,distance,mask";
  cases[1].seg = true;
  cases[1].segment_label = "Skull";
  cases[1].segment_code = "SCT:272673000:Bone";
  cases[1].dicom_compression = "rle";
  cases[1].dicom_layout = "enhanced";
  cases[1].series_number_base = 2147483641;
  cases[1].previews = "png,dicom";
  cases[1].slab_deconvolution = true;
  cases[1].intensity_method = "linear";
  cases[1].volume = "nii-uncompressed,nrrd";
  cases[1].mesh = "obj";
  cases[1].dicom_mesh_max_mb = 0;  // no cap
  cases[2].method = "morph";
  cases[2].factor = 4;
  cases[2].tolerance = 1e-4;
  cases[2].energy_units = "mm";
  cases[2].band = 2.5;
  cases[2].adaptivity = 0.5;
  cases[2].uid_root = "1.2.826.0.1.3680043.10.1";
  cases[2].random_uids = true;
  cases[2].series_uid = "1.2.3";
  cases[2].multiframe_volume = "stack 1";
  cases[2].strict_spacing = true;
  cases[2].strict_frame_of_reference = true;
  cases[2].dicom_mesh_adaptivity = 0.25;
  cases[2].dicom_mesh_max_mb = 12.5;
  // A box in mm with fractions and negative coordinates, corners reversed.
  cases[2].roi_mm = "120.25,-30.5,-71.125,-80.75,44.1,12.3";
  cases[3].method = "linear";
  cases[3].iterations = 0;
  cases[3].mesh = "none";
  cases[3].volume = "none";
  cases[3].previews = "none";
  for (size_t n = 0; n < cases.size(); ++n) {
    absl::StatusOr<JobSpec> spec = BuildJobSpec(cases[n]);
    ASSERT_TRUE(spec.ok()) << n << ": " << spec.status();
    const v1::JobSpec wire = ToWire(*spec);
    absl::StatusOr<JobSpec> back = JobSpecFromWire(wire);
    ASSERT_TRUE(back.ok()) << n << ": " << back.status();
    EXPECT_EQ(ToWire(*back).SerializeAsString(), wire.SerializeAsString()) << n;
    EXPECT_EQ(back->lower_threshold, spec->lower_threshold);
    EXPECT_EQ(back->upper_threshold, spec->upper_threshold);
    EXPECT_EQ(back->solver.method, spec->solver.method);
    EXPECT_EQ(back->solver.max_iterations, spec->solver.max_iterations);
    EXPECT_EQ(back->solver.tolerance, spec->solver.tolerance);
    EXPECT_EQ(back->z_resolution.factor, spec->z_resolution.factor);
    EXPECT_EQ(back->z_resolution.spacing_mm, spec->z_resolution.spacing_mm);
    EXPECT_EQ(back->output_series, spec->output_series);
    EXPECT_EQ(back->volume_formats, spec->volume_formats);
    EXPECT_EQ(back->mesh_formats, spec->mesh_formats);
    EXPECT_EQ(back->preview_formats, spec->preview_formats);
    EXPECT_EQ(back->slab_deconvolution, spec->slab_deconvolution);
    EXPECT_EQ(back->strict_frame_of_reference, spec->strict_frame_of_reference);
    EXPECT_EQ(back->intensity_method, spec->intensity_method);
    EXPECT_EQ(back->series_number_base, spec->series_number_base);
    EXPECT_EQ(back->series_instance_uid, spec->series_instance_uid);
    EXPECT_EQ(back->segment_label, spec->segment_label);
    EXPECT_EQ(back->segment_code, spec->segment_code);
    EXPECT_EQ(back->dicom_mesh_adaptivity, spec->dicom_mesh_adaptivity);
    EXPECT_EQ(back->dicom_mesh_max_mb, spec->dicom_mesh_max_mb) << n;
    EXPECT_EQ(back->roi_mm.has_value(), spec->roi_mm.has_value()) << n;
    if (spec->roi_mm.has_value()) {
      EXPECT_EQ(back->roi_mm->min, spec->roi_mm->min);
      EXPECT_EQ(back->roi_mm->max, spec->roi_mm->max);
    }
    EXPECT_TRUE(back->inputs.empty());
    EXPECT_TRUE(back->output_dir.empty());
  }
}

// The Encapsulated STL's size cap: 25 MB when absent, 0 kept as "no cap",
// out of range refused naming the field, and refused for fills.
TEST(WireTest, DicomMeshMaxMbDefaultsRangeAndFills) {
  v1::JobSpec p;
  p.set_threshold(300);
  EXPECT_EQ(JobSpecFromWire(p)->dicom_mesh_max_mb, kDefaultDicomMeshMaxMb);
  EXPECT_EQ(kDefaultDicomMeshMaxMb, 25);
  p.set_dicom_mesh_max_mb(0);
  EXPECT_EQ(JobSpecFromWire(p)->dicom_mesh_max_mb, 0);
  p.set_dicom_mesh_max_mb(7.5);
  EXPECT_EQ(JobSpecFromWire(p)->dicom_mesh_max_mb, 7.5);
  for (double bad : {-1.0, 0.01, 5000.0}) {
    p.set_dicom_mesh_max_mb(bad);
    EXPECT_THAT(std::string(JobSpecFromWire(p).status().message()),
                HasSubstr("dicom_mesh_max_mb"))
        << bad;
  }
  v1::JobSpec fill;
  fill.mutable_fill()->set_segmentation_file("labels.nrrd");
  fill.set_dicom_mesh_max_mb(10);
  EXPECT_THAT(std::string(FillOptionsFromWire(fill).status().message()),
              HasSubstr("dicom_mesh_max_mb"));
}

TEST(WireTest, RoiMmReachesTheSpecAndIsRefusedForFills) {
  InterpolationOptions o;
  o.inputs = {"in"};
  o.out = "out";
  o.threshold = 300;
  o.roi_mm = "120.25,-30.5,-71.125,-80.75,44.1,12.3";
  absl::StatusOr<JobSpec> spec = BuildJobSpec(o);
  ASSERT_TRUE(spec.ok()) << spec.status();
  const v1::JobSpec wire = ToWire(*spec);
  ASSERT_TRUE(wire.has_roi_mm());
  EXPECT_FALSE(wire.has_roi());
  EXPECT_DOUBLE_EQ(wire.roi_mm().x0(), -80.75);
  EXPECT_DOUBLE_EQ(wire.roi_mm().x1(), 120.25);
  EXPECT_DOUBLE_EQ(wire.roi_mm().z0(), -71.125);
  EXPECT_DOUBLE_EQ(wire.roi_mm().z1(), 12.3);
  v1::JobSpec fill;
  fill.mutable_fill()->set_segmentation_file("labels.nrrd");
  *fill.mutable_roi_mm() = wire.roi_mm();
  absl::StatusOr<FillJobOptions> refused = FillOptionsFromWire(fill);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(refused.status().message()),
              ::testing::HasSubstr("spec.roi_mm"));
}

TEST(WireTest, FillSpecsRoundTripAndRefuseInterpolationFields) {
  FillJobOptions o;
  o.segmentation = "labels.nrrd";
  o.reference = {"series"};
  o.out = "out";
  o.labels = "2,1";
  o.key_slices = "0,4,9";
  o.method = "cg";
  o.iterations = 40;
  o.factor = 2;
  o.mesh = "ply";
  o.volume = "nii,nrrd";
  o.rtstruct = false;
  o.seg = true;
  o.previews = "dicom";
  absl::StatusOr<FillJobSpec> spec = BuildFillJobSpec(o);
  ASSERT_TRUE(spec.ok()) << spec.status();
  const v1::JobSpec wire = ToWire(*spec, "labels.nrrd");
  EXPECT_TRUE(IsFillSpec(wire));
  EXPECT_EQ(wire.fill().segmentation_file(), "labels.nrrd");
  absl::StatusOr<FillJobSpec> back = FillJobSpecFromWire(wire);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(ToWire(*back, "labels.nrrd").SerializeAsString(),
            wire.SerializeAsString());
  EXPECT_EQ(back->fill.labels, (std::vector<int>{2, 1}));
  EXPECT_EQ(back->write_rtstruct, std::optional<bool>(false));
  EXPECT_EQ(back->preview_formats, std::vector<std::string>{"dicom"});
  // auto is the wire's unset method.
  o.method = "auto";
  const v1::JobSpec automatic = ToWire(*BuildFillJobSpec(o), "x.nrrd");
  EXPECT_EQ(automatic.method(), v1::SOLVER_METHOD_UNSPECIFIED);
  EXPECT_EQ(FillJobSpecFromWire(automatic)->fill.method, FillMethod::kAuto);

  v1::JobSpec bad = wire;
  bad.set_threshold(300);
  EXPECT_THAT(std::string(FillJobSpecFromWire(bad).status().message()),
              HasSubstr("spec.threshold is not used by fill jobs"));
  bad = wire;
  bad.set_strict_frame_of_reference(true);
  EXPECT_THAT(
      std::string(FillJobSpecFromWire(bad).status().message()),
      HasSubstr("spec.strict_frame_of_reference is not used by fill jobs"));
  // The morph fills too (per label, core/labels).
  bad = wire;
  bad.set_method(v1::SOLVER_METHOD_MORPH);
  absl::StatusOr<FillJobSpec> morph = FillJobSpecFromWire(bad);
  ASSERT_TRUE(morph.ok()) << morph.status();
  EXPECT_EQ(morph->fill.solver.method, SolverMethod::kMorph);
  bad = wire;
  bad.mutable_fill()->clear_segmentation_file();
  EXPECT_THAT(std::string(FillJobSpecFromWire(bad).status().message()),
              HasSubstr("spec.fill.segmentation_file is required"));
  bad = wire;
  bad.mutable_fill()->add_key_slices(-3);
  EXPECT_THAT(std::string(FillJobSpecFromWire(bad).status().message()),
              HasSubstr("spec.fill.key_slices: -3 is not a slice index"));
}

// The label names travel as the name of a file uploaded with the job; the
// local path never goes over the wire.
TEST(WireTest, LabelNamesAreAnUploadedFileOfTheirOwn) {
  FillJobOptions o;
  o.segmentation = "labels.nrrd";
  o.reference = {"series"};
  o.out = "out";
  o.label_names = "/home/someone/names.csv";
  absl::StatusOr<FillJobSpec> spec = BuildFillJobSpec(o);
  ASSERT_TRUE(spec.ok()) << spec.status();
  const v1::JobSpec wire = ToWire(*spec, "labels.nrrd", "names/names.csv");
  EXPECT_EQ(wire.fill().label_names_file(), "names/names.csv");
  EXPECT_EQ(wire.SerializeAsString().find("/home/someone"), std::string::npos);
  absl::StatusOr<FillJobSpec> back = FillJobSpecFromWire(wire);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_TRUE(back->label_names.empty());  // the server's path comes later
  EXPECT_EQ(ToWire(*spec, "labels.nrrd").fill().label_names_file(), "");

  v1::JobSpec bad = wire;
  bad.mutable_fill()->set_label_names_file("names.xlsx");
  EXPECT_THAT(std::string(FillJobSpecFromWire(bad).status().message()),
              HasSubstr("spec.fill.label_names_file: must name a colour "
                        "table (.csv, .txt) or a JSON sidecar (.json)"));
  bad.mutable_fill()->set_label_names_file("labels.nrrd");
  EXPECT_THAT(std::string(FillJobSpecFromWire(bad).status().message()),
              HasSubstr("spec.fill.label_names_file names the segmentation's "
                        "file"));
}

TEST(WireTest, UnknownEnumValuesNameTheirField) {
  v1::JobSpec p;
  p.set_threshold(300);
  p.set_method(static_cast<v1::SolverMethod>(42));
  EXPECT_THAT(std::string(JobSpecFromWire(p).status().message()),
              HasSubstr("spec.method: unknown method 42"));
  p.clear_method();
  p.set_energy_units(static_cast<v1::EnergyUnits>(9));
  EXPECT_THAT(std::string(JobSpecFromWire(p).status().message()),
              HasSubstr("spec.energy_units: unknown units 9"));
  p.clear_energy_units();
  p.mutable_outputs()->add_mesh_formats(static_cast<v1::MeshFormat>(77));
  EXPECT_THAT(std::string(JobSpecFromWire(p).status().message()),
              HasSubstr("spec.outputs.mesh_formats: unknown format 77"));
  p.clear_outputs();
  p.mutable_derived_series()->set_enabled(true);
  EXPECT_THAT(std::string(JobSpecFromWire(p).status().message()),
              HasSubstr("spec.derived_series.enabled is not used"));
}

TEST(WireTest, TerminalStates) {
  EXPECT_TRUE(IsTerminalState(v1::JOB_STATE_SUCCEEDED));
  EXPECT_TRUE(IsTerminalState(v1::JOB_STATE_FAILED));
  EXPECT_TRUE(IsTerminalState(v1::JOB_STATE_CANCELLED));
  EXPECT_FALSE(IsTerminalState(v1::JOB_STATE_QUEUED));
  EXPECT_FALSE(IsTerminalState(v1::JOB_STATE_RUNNING));
  EXPECT_FALSE(IsTerminalState(v1::JOB_STATE_UPLOADING));
}

}  // namespace
}  // namespace interslice::job

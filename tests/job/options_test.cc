// The option tables: one row per option, each reachable from every door it
// claims, and BuildJobSpec / BuildFillJobSpec as the one check.
#include "job/options.h"

#include <set>
#include <string>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "job/errors.h"
#include "job/wire.h"

namespace interslice::job {
namespace {

using ::testing::HasSubstr;

InterpolationOptions Minimal() {
  InterpolationOptions o;
  o.inputs = {"in"};
  o.out = "out";
  o.threshold = 300;
  return o;
}

FillJobOptions MinimalFill() {
  FillJobOptions o;
  o.segmentation = "labels.nii.gz";
  o.reference = {"series"};
  o.out = "out";
  return o;
}

template <typename Options>
void ExpectTableIsConsistent(std::span<const OptionDef<Options>> table) {
  std::set<absl::string_view> keys;
  for (const OptionDef<Options>& def : table) {
    EXPECT_TRUE(keys.insert(def.key).second) << "repeated key " << def.key;
    EXPECT_FALSE(def.help.empty()) << def.key;
    EXPECT_NE(def.doors, 0u) << def.key;
    EXPECT_EQ(def.key.find('-'), absl::string_view::npos)
        << def.key << ": keys use '_' (the command line turns it into '-')";
    EXPECT_EQ(FindOption(table, def.key), &def);
  }
}

TEST(OptionTableTest, KeysAreUniqueAndDocumented) {
  ExpectTableIsConsistent(InterpolationOptionTable());
  ExpectTableIsConsistent(FillOptionTable());
  EXPECT_EQ(FindOption(InterpolationOptionTable(), "no_such_option"), nullptr);
  EXPECT_EQ(CommandLineName("energy_units"), "--energy-units");
}

// Every option set by its key (as the rules file and any door that has text
// does) reaches the core spec as the typed value would.
TEST(OptionTableTest, SetOptionByKeyGivesTheSameSpecAsTypedValues) {
  InterpolationOptions typed = Minimal();
  typed.upper = 2000;
  typed.method = "direct";
  typed.iterations = 20;
  typed.energy_units = "mm";
  typed.factor = 3;
  typed.roi = "1,2,0,100,120,5";
  typed.output_series = "intensity,mask";
  typed.seg = true;
  typed.dicom_compression = "rle";
  typed.dicom_layout = "enhanced";
  typed.uid_root = "1.2.826.0.1.3680043.10.1";
  typed.series_number_base = 4000;
  typed.strict_spacing = true;
  typed.strict_frame_of_reference = true;
  typed.band = 3.5;
  typed.adaptivity = 0.25;
  typed.mesh = "stl,ply";
  typed.volume = "nrrd";
  typed.previews = "dicom,png";
  InterpolationOptions by_key = Minimal();
  for (auto [key, text] : std::vector<std::pair<std::string, std::string>>{
           {"upper", "2000"},
           {"method", "direct"},
           {"iterations", "20"},
           {"energy_units", "mm"},
           {"factor", "3"},
           {"roi", "1,2,0,100,120,5"},
           {"output_series", "intensity,mask"},
           {"seg", "true"},
           {"dicom_compression", "rle"},
           {"dicom_layout", "enhanced"},
           {"uid_root", "1.2.826.0.1.3680043.10.1"},
           {"series_number_base", "4000"},
           {"strict_spacing", "yes"},
           {"strict_frame_of_reference", "true"},
           {"band", "3.5"},
           {"adaptivity", "0.25"},
           {"mesh", "stl,ply"},
           {"volume", "nrrd"},
           {"previews", "dicom,png"}}) {
    ASSERT_TRUE(SetOption(by_key, key, text).ok()) << key;
  }
  absl::StatusOr<JobSpec> a = BuildJobSpec(typed);
  absl::StatusOr<JobSpec> b = BuildJobSpec(by_key);
  ASSERT_TRUE(a.ok()) << a.status();
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_EQ(ToWire(*a).SerializeAsString(), ToWire(*b).SerializeAsString());
  EXPECT_EQ(a->solver.method, SolverMethod::kDirect);
  EXPECT_EQ(a->solver.units, EnergyUnits::kMillimetre);
  EXPECT_EQ(a->z_resolution.factor, 3);
  EXPECT_EQ(a->series_number_base, 4000);
  EXPECT_TRUE(a->strict_frame_of_reference);
  EXPECT_FALSE(BuildJobSpec(Minimal())->strict_frame_of_reference);
  EXPECT_EQ(a->dicom_layout, "enhanced");
  EXPECT_EQ(BuildJobSpec(Minimal())->dicom_layout, "classic");
  EXPECT_EQ(a->mesh_formats, (std::vector<std::string>{"stl", "ply"}));
  EXPECT_EQ(a->preview_formats, (std::vector<std::string>{"dicom", "png"}));
  // The default on every door: PNG; "none" turns them off; a fill the same.
  EXPECT_EQ(BuildJobSpec(Minimal())->preview_formats,
            std::vector<std::string>{"png"});
  ASSERT_TRUE(SetOption(by_key, "previews", "none").ok());
  EXPECT_TRUE(BuildJobSpec(by_key)->preview_formats.empty());
  ASSERT_TRUE(SetOption(by_key, "previews", "gif").ok());
  EXPECT_EQ(ErrorOptionKey(BuildJobSpec(by_key).status()), "previews");
  EXPECT_EQ(BuildFillJobSpec(MinimalFill())->preview_formats,
            std::vector<std::string>{"png"});
}

// roi_mm: the rules file's and the wire's text form reaches the spec as a
// box whatever the corners' order; it excludes roi and refuses malformed
// text, each error naming the option.
TEST(OptionTableTest, RoiMmByKeyBuildsTheBoxAndExcludesRoi) {
  InterpolationOptions o = Minimal();
  ASSERT_TRUE(SetOption(o, "roi_mm", " 10.5,-20,30, -4,7.25,-1e1 ").ok());
  absl::StatusOr<JobSpec> spec = BuildJobSpec(o);
  ASSERT_TRUE(spec.ok()) << spec.status();
  ASSERT_TRUE(spec->roi_mm.has_value());
  EXPECT_EQ(spec->roi_mm->min, (Vec3{-4, -20, -10}));
  EXPECT_EQ(spec->roi_mm->max, (Vec3{10.5, 7.25, 30}));
  EXPECT_FALSE(spec->roi.has_value());
  EXPECT_FALSE(BuildJobSpec(Minimal())->roi_mm.has_value());

  o.roi = "0,0,0,10,10,2";
  absl::Status both = BuildJobSpec(o).status();
  EXPECT_EQ(both.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(ErrorOptionKey(both), "roi_mm");
  EXPECT_THAT(ErrorMessageWithoutKey(both), HasSubstr("combined with roi"));

  for (const char* bad :
       {"1,2,3,4,5", "1,2,3,4,5,x", "1,2,3,4,5,inf", "1,2,3,4,5,6,7"}) {
    InterpolationOptions b = Minimal();
    b.roi_mm = bad;
    absl::Status s = BuildJobSpec(b).status();
    EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument) << bad;
    EXPECT_EQ(ErrorOptionKey(s), "roi_mm") << bad;
  }
}

TEST(OptionTableTest, SetOptionRefusesWrongTypesAndUnknownKeys) {
  InterpolationOptions o = Minimal();
  absl::Status s = SetOption(o, "threshold", "high");
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(ErrorOptionKey(s), "threshold");
  EXPECT_THAT(ErrorMessageWithoutKey(s), HasSubstr("expected a number"));
  EXPECT_THAT(std::string(SetOption(o, "iterations", "1.5").message()),
              HasSubstr("expected an integer"));
  EXPECT_THAT(std::string(SetOption(o, "seg", "maybe").message()),
              HasSubstr("expected true or false"));
  EXPECT_THAT(std::string(SetOption(o, "thresh", "1").message()),
              HasSubstr("unknown option"));
  FillJobOptions f = MinimalFill();
  EXPECT_TRUE(SetOption(f, "rtstruct", "false").ok());
  EXPECT_EQ(f.rtstruct, std::optional<bool>(false));
}

TEST(BuildJobSpecTest, ErrorsNameTheOption) {
  struct Case {
    std::string key, value, message;
  };
  for (const Case& c : std::vector<Case>{
           {"method", "fast", "unknown method 'fast'"},
           {"energy_units", "inch", "unknown units 'inch'"},
           {"iterations", "-1", "must be >= 0"},
           {"tolerance", "0", "must be positive"},
           {"factor", "0", "must be 1..1024"},
           {"spacing", "-1", "must be positive"},
           {"band", "0", "must be positive"},
           {"adaptivity", "2", "must be in [0, 1]"},
           {"roi", "1,2,3", "expected six integers"},
           {"output_series", "intensity,bogus", "unknown value 'bogus'"},
           {"mesh", "vrml", "unknown value 'vrml'"},
           {"volume", "mha", "unknown value 'mha'"},
           {"dicom_compression", "jpeg", "unknown value 'jpeg'"},
           {"dicom_layout", "multiframe", "unknown value 'multiframe'"},
           {"series_number_base", "0", "must be between 1 and 2147483641"},
           {"upper", "-5000", "not below the threshold"},
       }) {
    InterpolationOptions o = Minimal();
    ASSERT_TRUE(SetOption(o, c.key, c.value).ok()) << c.key;
    absl::StatusOr<JobSpec> spec = BuildJobSpec(o);
    ASSERT_FALSE(spec.ok()) << c.key;
    EXPECT_EQ(ErrorOptionKey(spec.status()), c.key) << spec.status();
    EXPECT_THAT(ErrorMessageWithoutKey(spec.status()), HasSubstr(c.message))
        << c.key;
  }
  InterpolationOptions both = Minimal();
  both.factor = 2;
  both.spacing = 1;
  EXPECT_THAT(std::string(BuildJobSpec(both).status().message()),
              HasSubstr("alternatives"));
  InterpolationOptions none = Minimal();
  none.threshold.reset();
  EXPECT_EQ(ErrorOptionKey(BuildJobSpec(none).status()), "threshold");
}

// Issue 26: the SEG's segment is named by --segment-label / --segment-code
// (rules and wire alike), each checked, and only where a SEG is written.
TEST(BuildJobSpecTest, SegmentLabelAndCode) {
  InterpolationOptions o = Minimal();
  o.seg = true;
  ASSERT_TRUE(SetOption(o, "segment_label", "Brain").ok());
  ASSERT_TRUE(SetOption(o, "segment_code", "SCT:12738006:Brain").ok());
  absl::StatusOr<JobSpec> spec = BuildJobSpec(o);
  ASSERT_TRUE(spec.ok()) << spec.status();
  EXPECT_EQ(spec->segment_label, "Brain");
  EXPECT_EQ(spec->segment_code, "SCT:12738006:Brain");
  // mask in output_series writes the SEG too.
  InterpolationOptions mask = Minimal();
  mask.output_series = "mask";
  mask.segment_label = "Brain";
  EXPECT_TRUE(BuildJobSpec(mask).ok());

  struct Case {
    std::string key, value, message;
  };
  for (const Case& c : std::vector<Case>{
           {"segment_label", std::string(65, 'x'), "1-64 characters"},
           {"segment_label", "a\\b", "without backslash"},
           {"segment_code", "SCT:12738006", "scheme:value:meaning"},
           {"segment_code", "sct:12738006:Brain", "coding scheme"},
           {"segment_code", "SCT::Brain", "code value"},
           {"segment_code", "SCT:12738006:", "code meaning"},
       }) {
    InterpolationOptions bad = Minimal();
    bad.seg = true;
    ASSERT_TRUE(SetOption(bad, c.key, c.value).ok()) << c.key;
    absl::StatusOr<JobSpec> refused = BuildJobSpec(bad);
    ASSERT_FALSE(refused.ok()) << c.value;
    EXPECT_EQ(ErrorOptionKey(refused.status()), c.key) << refused.status();
    EXPECT_THAT(ErrorMessageWithoutKey(refused.status()), HasSubstr(c.message))
        << c.value;
  }
  // Without a SEG a segment name would be silently ignored: refused.
  for (const char* key : {"segment_label", "segment_code"}) {
    InterpolationOptions no_seg = Minimal();
    ASSERT_TRUE(SetOption(no_seg, key, "SCT:12738006:Brain").ok());
    absl::StatusOr<JobSpec> refused = BuildJobSpec(no_seg);
    ASSERT_FALSE(refused.ok()) << key;
    EXPECT_EQ(ErrorOptionKey(refused.status()), key);
    EXPECT_THAT(ErrorMessageWithoutKey(refused.status()),
                HasSubstr("no SEG is written"));
  }
}

// The derived objects are numbered base + 1 ... base + 6 (the previews): the
// largest base whose + 6 is still a DICOM IS (signed 32-bit) is accepted,
// one more is not, by every door and by the core itself before anything
// runs.
TEST(BuildJobSpecTest, SeriesNumberBaseLeavesRoomForSixObjects) {
  InterpolationOptions o = Minimal();
  o.series_number_base = kMaxSeriesNumberBase;
  ASSERT_TRUE(BuildJobSpec(o).ok());
  EXPECT_EQ(kMaxSeriesNumberBase + 6, 2147483647);
  o.series_number_base = kMaxSeriesNumberBase + 1;
  EXPECT_EQ(ErrorOptionKey(BuildJobSpec(o).status()), "series_number_base");
  v1::JobSpec wire;
  wire.set_threshold(300);
  wire.mutable_derived_series()->set_series_number(2147483642);
  EXPECT_THAT(std::string(JobSpecFromWire(wire).status().message()),
              HasSubstr("spec.derived_series.series_number: must be between"));
  JobSpec core;
  core.inputs = {"in"};
  core.output_dir = "out";
  core.series_number_base = 2147483642;
  EXPECT_EQ(ValidateJobSpec(core).code(), absl::StatusCode::kInvalidArgument);
  core.series_number_base = 2147483641;
  EXPECT_TRUE(ValidateJobSpec(core).ok());
  core.uid_root = "1.2.x";
  EXPECT_EQ(ValidateJobSpec(core).code(), absl::StatusCode::kInvalidArgument);
}

TEST(ErrorsTest, EachDoorNamesTheOptionInItsOwnWords) {
  InterpolationOptions o = Minimal();
  o.energy_units = "inch";
  const absl::Status error = BuildJobSpec(o).status();
  EXPECT_EQ(ForDoor(error, ErrorDoor::kCommandLine).message(),
            "--energy-units: unknown units 'inch' (choose from voxel, mm)");
  EXPECT_EQ(ForDoor(error, ErrorDoor::kRulesJob).message(),
            "job.energy_units: unknown units 'inch' (choose from voxel, mm)");
  EXPECT_EQ(ForDoor(error, ErrorDoor::kWire).message(),
            "spec.energy_units: unknown units 'inch' (choose from voxel, mm)");
  o = Minimal();
  o.series_number_base = 0;
  EXPECT_THAT(
      std::string(
          ForDoor(BuildJobSpec(o).status(), ErrorDoor::kWire).message()),
      HasSubstr("spec.derived_series.series_number: "));
  FillJobOptions f = MinimalFill();
  f.labels = "0";
  const absl::Status fill_error = BuildFillJobSpec(f).status();
  EXPECT_EQ(ForDoor(fill_error, ErrorDoor::kRulesFill).message(),
            "fill.labels: 0 is not a label (1..65535)");
  EXPECT_EQ(ForDoor(fill_error, ErrorDoor::kWire, /*fill=*/true).message(),
            "spec.fill.labels: 0 is not a label (1..65535)");
  EXPECT_EQ(ForDoor(fill_error, ErrorDoor::kCommandLine).message(),
            "--labels: 0 is not a label (1..65535)");
  // Errors without a key pass unchanged.
  const absl::Status plain = absl::NotFoundError("no such file");
  EXPECT_EQ(ForDoor(plain, ErrorDoor::kCommandLine), plain);
}

TEST(BuildFillJobSpecTest, LabelsSlicesAndMethods) {
  FillJobOptions o = MinimalFill();
  o.labels = "1,3,7";
  o.key_slices = "0-8:4,10";
  o.method = "direct";
  absl::StatusOr<FillJobSpec> spec = BuildFillJobSpec(o);
  ASSERT_TRUE(spec.ok()) << spec.status();
  EXPECT_EQ(spec->fill.labels, (std::vector<int>{1, 3, 7}));
  EXPECT_EQ(*spec->fill.key_slices, (std::vector<int64_t>{0, 4, 8, 10}));
  EXPECT_EQ(spec->fill.method, FillMethod::kSolver);
  EXPECT_EQ(spec->fill.solver.method, SolverMethod::kDirect);
  o.method = "auto";
  EXPECT_EQ(BuildFillJobSpec(o)->fill.method, FillMethod::kAuto);
  // The label names' reader is chosen by the extension, in any case.
  for (const char* names : {"n.csv", "N.TXT", "dir/n.Json"}) {
    o.label_names = names;
    absl::StatusOr<FillJobSpec> named = BuildFillJobSpec(o);
    ASSERT_TRUE(named.ok()) << names << ": " << named.status();
    EXPECT_EQ(named->label_names, names);
  }
  for (auto [key, value, message] :
       std::vector<std::tuple<std::string, std::string, std::string>>{
           {"labels", "1,1", "label 1 is repeated"},
           {"labels", "70000", "is not a label"},
           {"key_slices", "3,3", "slice 3 is repeated"},
           {"key_slices", "5-2", "is not a slice index"},
           {"method", "fast", "unknown method 'fast'"},
           {"volume", "nii-uncompressed", "unknown value"},
           {"label_names", "names.xlsx", "must name a colour table (.csv"},
       }) {
    FillJobOptions bad = MinimalFill();
    ASSERT_TRUE(SetOption(bad, key, value).ok()) << key;
    absl::StatusOr<FillJobSpec> refused = BuildFillJobSpec(bad);
    ASSERT_FALSE(refused.ok()) << key;
    EXPECT_EQ(ErrorOptionKey(refused.status()), key);
    EXPECT_THAT(std::string(refused.status().message()), HasSubstr(message));
  }
}

TEST(ParseSliceListTest, RangesStepsAndBounds) {
  EXPECT_EQ(*ParseSliceList("0,5,12"), (std::vector<int64_t>{0, 5, 12}));
  EXPECT_EQ(*ParseSliceList("2-4"), (std::vector<int64_t>{2, 3, 4}));
  EXPECT_EQ(*ParseSliceList("0-40:20"), (std::vector<int64_t>{0, 20, 40}));
  EXPECT_FALSE(ParseSliceList("").ok());
  EXPECT_FALSE(ParseSliceList("a").ok());
  EXPECT_FALSE(ParseSliceList("1-2:0").ok());
  EXPECT_FALSE(ParseSliceList("-1").ok());
  // A range can not name more than 2^20 slices (no unbounded allocation).
  EXPECT_FALSE(ParseSliceList("0-2000000000").ok());
}

}  // namespace
}  // namespace interslice::job

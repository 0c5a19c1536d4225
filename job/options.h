// The job options: every door (the command line, a DICOM node's rules file,
// the wire spec of the gRPC service) names a job's parameters with the same
// keys, and this is the one place that maps them to the core specs
// (core/pipeline JobSpec for interpolation, core/labels FillJobSpec for
// fills) and checks them.
//
// An option's key is its rules-file key ("energy_units"); on the command line
// it is "--" + the key with '-' for '_' ("--energy-units"), on the wire the
// field of interslice.v1.JobSpec the table names ("spec.energy_units"). The
// option structs hold the values as a person typed them (text, numbers,
// flags); BuildJobSpec / BuildFillJobSpec turn them into a core spec or an
// error that names the option by its key (job/errors.h), which each door then
// says in its own words.
//
// Defaults are the structs' initial values: the same for every door (a
// door that wants other defaults, like a fill rule's `seg: true`, sets them
// before it applies what the person wrote).
#ifndef INTERSLICE_JOB_OPTIONS_H_
#define INTERSLICE_JOB_OPTIONS_H_

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <variant>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "core/labels/fill_job.h"
#include "core/pipeline/pipeline.h"

namespace interslice::job {

// Where an option may be given.
enum Door : unsigned {
  kCommandLine = 1,
  kRulesFile = 2,
  kWire = 4,
  kEveryDoor = kCommandLine | kRulesFile | kWire,
};

// What an option's value looks like as a person writes it. A rules file may
// write kList, kIntegerList, kBox and kMmBox values as YAML lists or as the
// command line's comma-separated text.
enum class ValueKind {
  kNumber,       // 300, -0.5
  kInteger,      // 15
  kText,         // cg, 1.2.826.0.1
  kList,         // stl,ply (names)
  kIntegerList,  // 1,3,7 (or slice ranges 0-40:5 where the option says so)
  kBox,          // x0,y0,z0,x1,y1,z1 (six integers)
  kMmBox,        // x0,y0,z0,x1,y1,z1 (six numbers, mm)
  kFlag,         // true / false
};

// Raw values of an interpolation job (`interslice run`, `interpolate`,
// `submit`; a rule's `job:`; the wire spec without `fill`).
struct InterpolationOptions {
  // Supplied by the door, not options: the DICOM files or folders and the
  // output folder.
  std::vector<std::string> inputs;
  std::string out;

  std::string series_uid;
  std::optional<double> threshold;
  std::optional<double> upper;
  std::string roi;     // "x0,y0,z0,x1,y1,z1"
  std::string roi_mm;  // "x0,y0,z0,x1,y1,z1", LPS mm, corners in any order
  std::string method = "cg";
  std::optional<int64_t> iterations;
  std::optional<double> tolerance;
  std::string energy_units = "voxel";
  std::optional<int64_t> factor;
  std::optional<double> spacing;
  bool strict_spacing = false;
  bool strict_frame_of_reference = false;
  bool slab_deconvolution = false;
  std::string output_series;  // "mask,distance,intensity"
  bool seg = false;
  std::string segment_label;
  std::string segment_code;  // "scheme:value:meaning"
  std::string dicom_compression = "none";
  std::string dicom_layout = "classic";
  std::string intensity_method = "morph";
  std::string uid_root;
  bool random_uids = false;
  std::optional<int64_t> series_number_base;
  std::string multiframe_volume;
  std::optional<double> band;
  double adaptivity = 0;
  // The Encapsulated STL's own adaptivity; unset: the core's default
  // (core/pipeline kDefaultDicomMeshAdaptivity).
  std::optional<double> dicom_mesh_adaptivity;
  // The Encapsulated STL's size cap, MB; unset: the core's default
  // (core/pipeline kDefaultDicomMeshMaxMb).
  std::optional<double> dicom_mesh_max_mb;
  std::string mesh = "stl";
  std::string volume = "nii";
  // Previews (core/pipeline JobSpec::preview_formats): PNG by default, on
  // every door: four small pictures (~0.4 MB) that show a person what the
  // job made; DICOM into the study only when asked, because it adds a
  // series to the patient's record.
  std::string previews = "png";
};

// Raw values of a fill job (`interslice fill`; a rule's `fill:`; the wire
// spec with `fill`).
struct FillJobOptions {
  // Supplied by the door: the segmentation file, the reference series' files
  // or folders and the output folder.
  std::string segmentation;
  std::vector<std::string> reference;
  std::string out;

  std::string series_uid;
  std::string labels;      // "1,3,7"; empty = every label
  std::string key_slices;  // "0,5,12" or ranges "0-40:5"
  std::string method = "auto";
  std::optional<int64_t> iterations;
  std::optional<double> tolerance;
  std::string energy_units = "voxel";
  std::optional<int64_t> factor;
  std::optional<double> spacing;
  std::optional<double> band;
  double adaptivity = 0;
  std::string mesh = "stl";
  std::string volume = "nii";
  bool seg = false;
  std::optional<bool> rtstruct;  // unset: on for RTSTRUCT input
  std::string intensity_method = "morph";
  std::string uid_root;
  bool random_uids = false;
  std::string previews = "png";  // as InterpolationOptions::previews
  // A label map's names, colours and codes (a .csv/.txt colour table or
  // .json sidecar): a path on the command line, the uploaded file's name on
  // the wire. Not a rules-file key: DICOM input names its own segments.
  std::string label_names;
};

// One row of an option table: the option's key, where the wire carries it,
// what it looks like, its help text, the doors that take it and the member
// of the options struct that holds it.
template <typename Options>
struct OptionDef {
  using Member =
      std::variant<std::string Options::*, bool Options::*, double Options::*,
                   std::optional<double> Options::*,
                   std::optional<int64_t> Options::*,
                   std::optional<bool> Options::*>;
  absl::string_view key;
  absl::string_view wire;  // e.g. "spec.derived_series.series_number"
  ValueKind kind;
  Member member;
  absl::string_view help;
  unsigned doors = kEveryDoor;
  bool required = false;  // the job cannot run without it
};

std::span<const OptionDef<InterpolationOptions>> InterpolationOptionTable();
std::span<const OptionDef<FillJobOptions>> FillOptionTable();

// The row of `key`, or null.
const OptionDef<InterpolationOptions>* FindOption(
    std::span<const OptionDef<InterpolationOptions>> table,
    absl::string_view key);
const OptionDef<FillJobOptions>* FindOption(
    std::span<const OptionDef<FillJobOptions>> table, absl::string_view key);

// "--energy-units" for "energy_units".
std::string CommandLineName(absl::string_view key);

// Sets the option `key` from its text (a number, an integer, true/false, or
// text and comma-separated lists as written). INVALID_ARGUMENT naming the key
// for an unknown key or a value of the wrong type; values are checked
// further by Build*.
absl::Status SetOption(InterpolationOptions& options, absl::string_view key,
                       absl::string_view text);
absl::Status SetOption(FillJobOptions& options, absl::string_view key,
                       absl::string_view text);

// The core spec, or INVALID_ARGUMENT naming the option (job/errors.h) for
// anything malformed; then the core's own check (ValidateJobSpec,
// ValidateFillJobSpec), whose errors name the core field.
absl::StatusOr<JobSpec> BuildJobSpec(const InterpolationOptions& options);
absl::StatusOr<FillJobSpec> BuildFillJobSpec(const FillJobOptions& options);

// A slice list: comma-separated indices and ranges "a-b" (inclusive) or
// "a-b:step". INVALID_ARGUMENT naming the bad item (key "key_slices").
absl::StatusOr<std::vector<int64_t>> ParseSliceList(absl::string_view text);

// The largest series number base: the derived objects are numbered base + 1
// ... base + 6 (the previews), which must stay a DICOM IS (a signed 32-bit
// integer).
inline constexpr int64_t kMaxSeriesNumberBase = 2147483647 - 6;

}  // namespace interslice::job

#endif  // INTERSLICE_JOB_OPTIONS_H_

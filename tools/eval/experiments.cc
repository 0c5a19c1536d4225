#include "tools/eval/experiments.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <set>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"
#include "core/common/status_macros.h"
#include "core/dicom/series_reader.h"
#include "core/morph/morph.h"
#include "core/slab/slab_deconvolution.h"
#include "core/stack/stacking.h"
#include "core/surface/surface.h"
#include "tools/eval/metrics.h"
#include "tools/eval/reconstruct.h"
#include "tools/eval/shapes.h"

namespace interslice::eval {
namespace {

using json = nlohmann::json;
using Clock = std::chrono::steady_clock;

double Seconds(Clock::time_point since) {
  return std::chrono::duration<double>(Clock::now() - since).count();
}

// JSON has no inf/nan: write them as strings.
json Num(double x) {
  if (std::isnan(x)) return "nan";
  if (std::isinf(x)) return x > 0 ? "inf" : "-inf";
  return x;
}

std::string CsvCell(const json& v) {
  if (v.is_string()) return v.get<std::string>();
  if (v.is_null()) return "";
  return v.dump();
}

// A method name -> solver options ("nearest" has none).
struct Method {
  std::string name;
  bool nearest = false;
  // Diagnostic probe: the grey values of the two neighbouring original
  // slices blended linearly in z, minus the threshold (no distance maps).
  bool grey_linear = false;
  bool morph = false;  // registration-based stacking (core/morph) first
  bool component_filter = false;  // RemoveUnsupportedComponents after
  // The morph's trajectory and values (MorphOptions::trajectory, values).
  MorphTrajectory trajectory = MorphTrajectory::kPiecewiseLinear;
  MorphValues values = MorphValues::kCatmullRom;
  SolverOptions solver;
};

absl::StatusOr<Method> ParseMethod(const std::string& name,
                                   const EvalOptions& o) {
  Method m;
  m.name = name;
  std::string base = name;
  if (absl::EndsWith(name, "-mm")) {
    m.solver.units = EnergyUnits::kMillimetre;
    base = name.substr(0, name.size() - 3);
  }
  // morph-smooth[pos|ss|mono]...: the same methods on the cubic (C1 in z)
  // trajectory, values by Catmull-Rom; "pos" blends the values linearly
  // (only the trajectory is C1), "ss" by smoothstep. "morph-smooth" alone is
  // the cubic morph with the component filter and no refinement (it needs none
  // for the crease).
  if (absl::StartsWith(base, "morph-smooth")) {
    m.trajectory = MorphTrajectory::kCubic;
    std::string rest = base.substr(12);
    if (absl::StartsWith(rest, "pos")) {
      m.values = MorphValues::kLinear;
      rest = rest.substr(3);
    } else if (absl::StartsWith(rest, "ss")) {
      m.values = MorphValues::kSmoothstep;
      rest = rest.substr(2);
    } else if (absl::StartsWith(rest, "mono")) {
      m.values = MorphValues::kMonotone;
      rest = rest.substr(4);
    }
    if (rest.empty()) {
      m.morph = true;
      m.component_filter = true;
      m.solver.method = SolverMethod::kLinear;
      return m;
    }
    if (rest == "-raw" || absl::StartsWith(rest, "-fid")) {
      base = absl::StrCat("morph", rest);
    } else {
      return absl::InvalidArgumentError(absl::StrCat(
          "unknown method '", name,
          "' (morph-smooth[pos|ss|mono], morph-smooth[pos|ss|mono]-raw, "
          "morph-smooth[pos|ss|mono]-fidL[t][c])"));
    }
  }
  if (base == "nearest") {
    m.nearest = true;
  } else if (base == "grey-linear") {
    m.grey_linear = true;
  } else if (base == "linear") {
    m.solver.method = SolverMethod::kLinear;
  } else if (base == "cg15") {
    m.solver.method = SolverMethod::kConjugateGradient;
    m.solver.max_iterations = o.cg_iterations;
    m.solver.tolerance = 0;
  } else if (base == "cgtol") {
    m.solver.method = SolverMethod::kConjugateGradient;
    m.solver.max_iterations = o.cg_max_iterations;
    m.solver.tolerance = o.cg_tolerance;
  } else if (base == "direct") {
    m.solver.method = SolverMethod::kDirect;
  } else if (base == "morph-raw") {
    // The registration-based stacking alone (no refinement).
    m.morph = true;
    m.solver.method = SolverMethod::kLinear;
  } else if (base == "morph") {
    // The shipped method, as the pipeline runs it (--method morph): the
    // default trajectory and values, the refinement only if the defaults
    // ask for it, then the component filter. (The piecewise morph shipped
    // before is morph-fid0.3tc.)
    const MorphOptions defaults;
    m.morph = true;
    m.component_filter = true;
    m.trajectory = defaults.trajectory;
    m.values = defaults.values;
    m.solver.method =
        defaults.refine ? SolverMethod::kMorph : SolverMethod::kLinear;
    m.solver.fidelity = defaults.refine ? defaults.fidelity : 0;
    m.solver.fidelity_taper = defaults.fidelity_taper;
  } else if (absl::StartsWith(base, "morph-fid")) {
    // morph-fidL: morph, then the direct solver with fidelity L.
    m.morph = true;
    m.solver.method = SolverMethod::kDirect;
    std::string number = base.substr(9);
    if (absl::EndsWith(number, "c")) {
      m.component_filter = true;
      number.pop_back();
    }
    if (absl::EndsWith(number, "t")) {
      m.solver.fidelity_taper = true;
      number.pop_back();
    }
    if (!absl::SimpleAtod(number, &m.solver.fidelity))
      return absl::InvalidArgumentError("morph-fidL needs a number L");
  } else {
    return absl::InvalidArgumentError(absl::StrCat(
        "unknown method '", name,
        "' (nearest, linear, cg15, cgtol, direct, morph-raw, morph, "
        "morph-fidL[t][c], morph-smooth[pos|ss|mono][-raw|-fidL[t][c]]; "
        "optionally "
        "with -mm)"));
  }
  return m;
}

// One reconstruction problem with its ground truth on the output grid.
struct Case {
  std::string experiment;
  int factor = 1;
  Volume<float> originals;   // grey original slices, uniformly spaced
  Volume<float> truth_grey;  // on the output grid; truth = grey >= level
  float level = 0;           // threshold of truth_grey and originals
  ContourOptions contour;
  std::vector<uint8_t> eval_slices;  // output slices compared
  std::vector<std::string> methods;
  int64_t sagittal_i = -1, coronal_j = -1;  // reformat planes (-1: none)
  int64_t slab_k0 = -1, slab_k1 = -1;       // topology slab (-1: none)
  bool write_slab_axials = false;
  std::function<double(double, double, double)> analytic;  // artificial only
  std::string curve_tag;  // convergence curves of CG runs go under this tag
};

std::vector<float> SagittalPlane(const Volume<float>& v, int64_t i) {
  const Index3 n = v.grid.size;
  std::vector<float> out(n[2] * n[1]);
  for (int64_t k = 0; k < n[2]; ++k)
    for (int64_t j = 0; j < n[1]; ++j) out[k * n[1] + j] = v.at(i, j, k);
  return out;
}
std::vector<float> CoronalPlane(const Volume<float>& v, int64_t j) {
  const Index3 n = v.grid.size;
  std::vector<float> out(n[2] * n[0]);
  for (int64_t k = 0; k < n[2]; ++k)
    for (int64_t i = 0; i < n[0]; ++i) out[k * n[0] + i] = v.at(i, j, k);
  return out;
}
std::vector<float> AxialPlane(const Volume<float>& v, int64_t k) {
  const int64_t plane = v.grid.SliceVoxelCount();
  return std::vector<float>(v.data.begin() + k * plane,
                            v.data.begin() + (k + 1) * plane);
}

absl::Status WritePlanes(const Case& c, const std::string& method,
                         const Volume<float>& value, Recorder& rec) {
  const Grid& g = value.grid;
  json tags = {
      {"experiment", c.experiment}, {"k", c.factor}, {"method", method}};
  const std::string stem =
      absl::StrCat(c.experiment, "_k", c.factor, "_", method);
  if (c.sagittal_i >= 0) {
    tags["plane"] = "sagittal";
    tags["index"] = c.sagittal_i;
    INTERSLICE_RETURN_IF_ERROR(rec.WritePlane(
        stem + "_sagittal", tags, SagittalPlane(value, c.sagittal_i), g.size[2],
        g.size[1], g.spacing[2], g.spacing[1]));
  }
  if (c.coronal_j >= 0) {
    tags["plane"] = "coronal";
    tags["index"] = c.coronal_j;
    INTERSLICE_RETURN_IF_ERROR(rec.WritePlane(
        stem + "_coronal", tags, CoronalPlane(value, c.coronal_j), g.size[2],
        g.size[0], g.spacing[2], g.spacing[0]));
  }
  if (c.write_slab_axials && c.slab_k0 >= 0) {
    for (int64_t k = c.slab_k0; k < c.slab_k1; ++k) {
      if (!c.eval_slices[k]) continue;
      tags["plane"] = "axial";
      tags["index"] = k;
      INTERSLICE_RETURN_IF_ERROR(rec.WritePlane(
          absl::StrCat(stem, "_axial", k), tags, AxialPlane(value, k),
          g.size[1], g.size[0], g.spacing[1], g.spacing[0]));
    }
  }
  return absl::OkStatus();
}

json ComponentsJson(const Components& c) {
  return {{"count", c.count},
          {"count_ge100", c.count_ge100},
          {"largest", c.largest}};
}

absl::Status RunCase(const Case& c, const EvalOptions& o, Recorder& rec) {
  ComputeContext context;
  context.threads = o.threads;
  const auto t0 = Clock::now();
  INTERSLICE_ASSIGN_OR_RETURN(
      Stacked stacked,
      ContourAndStack(c.originals, c.contour, c.factor, context));
  const double stack_seconds = Seconds(t0);
  if (stacked.field.grid.size != c.truth_grey.grid.size) {
    return absl::InternalError(absl::StrCat(
        c.experiment, ": output grid ", stacked.field.grid.DebugString(),
        " does not match the ground truth ", c.truth_grey.grid.DebugString()));
  }
  const Mask truth = Threshold(c.truth_grey, c.level);
  const Volume<float> truth_map = BoundaryDistanceMap(truth);
  const Components truth_components = CountComponents(truth);
  Components truth_slab;
  if (c.slab_k0 >= 0)
    truth_slab = CountComponentsInSlab(truth, c.slab_k0, c.slab_k1);
  int64_t evaluated = 0;
  for (uint8_t e : c.eval_slices) evaluated += e;
  std::fprintf(stderr,
               "[%s k=%d] grid %lldx%lldx%lld, %lld slices evaluated, "
               "contour+stack %.1f s\n",
               c.experiment.c_str(), c.factor,
               static_cast<long long>(truth.grid.size[0]),
               static_cast<long long>(truth.grid.size[1]),
               static_cast<long long>(truth.grid.size[2]),
               static_cast<long long>(evaluated), stack_seconds);
  {
    Volume<float> shifted = c.truth_grey;
    for (float& v : shifted.data) v -= c.level;
    INTERSLICE_RETURN_IF_ERROR(WritePlanes(c, "truth", shifted, rec));
    if (std::getenv("INTERSLICE_EVAL_DUMP") != nullptr) {
      // Debugging aid: the ground truth's grey values minus the threshold.
      std::ofstream dump(
          absl::StrCat(std::getenv("INTERSLICE_EVAL_DUMP"), "/", c.experiment,
                       "_k", c.factor, "_truth.f32"),
          std::ios::binary);
      dump.write(reinterpret_cast<const char*>(shifted.data.data()),
                 static_cast<std::streamsize>(shifted.data.size() * 4));
      // And the original (key) slices' grey values, as read.
      std::ofstream keys(
          absl::StrCat(std::getenv("INTERSLICE_EVAL_DUMP"), "/", c.experiment,
                       "_k", c.factor, "_originals.f32"),
          std::ios::binary);
      keys.write(reinterpret_cast<const char*>(c.originals.data.data()),
                 static_cast<std::streamsize>(c.originals.data.size() * 4));
    }
  }

  for (const std::string& name : c.methods) {
    INTERSLICE_ASSIGN_OR_RETURN(const Method method, ParseMethod(name, o));
    const auto tm = Clock::now();
    Volume<float> value;  // >= 0 is the object
    json row = {
        {"experiment", c.experiment},
        {"k", c.factor},
        {"method", name},
        {"units", method.nearest
                      ? "-"
                      : std::string(EnergyUnitsName(method.solver.units))}};
    std::vector<json> curve;
    if (method.grey_linear) {
      value.grid = stacked.field.grid;
      value.data.resize(value.grid.VoxelCount());
      const int64_t plane = value.grid.SliceVoxelCount();
      const int n = c.factor;
      const int64_t last = c.originals.grid.size[2] - 1;
      for (int64_t k = 0; k < value.grid.size[2]; ++k) {
        const int64_t s = std::min<int64_t>(k / n, last);
        const int64_t s1 = std::min<int64_t>(s + 1, last);
        const float t = static_cast<float>(k - s * n) / n;
        for (int64_t v = 0; v < plane; ++v)
          value.data[k * plane + v] =
              (1 - t) * c.originals.data[s * plane + v] +
              t * c.originals.data[s1 * plane + v] - c.level;
      }
      row["solve_seconds"] = 0;
    } else if (method.nearest) {
      // Nearest original slice (ties go to the lower slice), as a +-1 field.
      value.grid = stacked.field.grid;
      value.data.resize(value.grid.VoxelCount());
      const int64_t plane = value.grid.SliceVoxelCount();
      const int n = c.factor;
      for (int64_t k = 0; k < value.grid.size[2]; ++k) {
        const int64_t s = (k + (n - 1) / 2) / n;
        for (int64_t v = 0; v < plane; ++v)
          value.data[k * plane + v] =
              c.originals.data[s * plane + v] >= c.level ? 1.0f : -1.0f;
      }
      row["solve_seconds"] = 0;
    } else {
      ComputeContext solve_context = context;
      solve_context.progress = [&](const ProgressEvent& e) {
        if (e.iteration < 0) return;
        curve.push_back({{"iteration", e.iteration},
                         {"relative_residual", Num(e.relative_residual)},
                         {"energy", Num(e.energy)}});
      };
      Stacked morphed;
      const Stacked* source = &stacked;
      double morph_seconds = 0;
      if (method.morph) {
        const auto tmorph = Clock::now();
        MorphOptions mo;
        mo.trajectory = method.trajectory;
        mo.values = method.values;
        // Sensitivity runs only (docs/eval): override the registration.
        if (const char* e = std::getenv("MORPH_LEVELS"))
          mo.levels = std::atoi(e);
        if (const char* e = std::getenv("MORPH_ITS"))
          mo.iterations = std::atoi(e);
        if (const char* e = std::getenv("MORPH_SIGMA"))
          mo.field_sigma_px = std::atof(e);
        if (const char* e = std::getenv("MORPH_CLIP"))
          mo.clip_mm = std::atof(e);
        if (const char* e = std::getenv("MORPH_DS"))
          mo.downsample = std::atoi(e);
        INTERSLICE_ASSIGN_OR_RETURN(
            MorphedField mf,
            StackMorph(
                stacked.maps,
                UniformStackPlan(stacked.maps.grid.size[2],
                                 stacked.maps.grid.spacing[2], stacked.factor),
                mo, int64_t{1} << 31, context));
        morphed.field = std::move(mf.stacked.field);
        morphed.fixed_slices = std::move(mf.stacked.fixed_slices);
        morphed.factor = mf.stacked.factor;
        morph_seconds = Seconds(tmorph);
        row["morph_seconds"] = morph_seconds;
        row["morph_mean_displacement_mm"] = mf.statistics.mean_displacement_mm;
        row["morph_max_displacement_mm"] = mf.statistics.max_displacement_mm;
        source = &morphed;
      }
      INTERSLICE_ASSIGN_OR_RETURN(
          Refined refined, Refine(*source, method.solver, solve_context));
      value = std::move(refined.field);
      if (method.component_filter) {
        const auto tfilter = Clock::now();
        INTERSLICE_ASSIGN_OR_RETURN(
            const int64_t removed,
            RemoveUnsupportedComponents(value, stacked.fixed_slices, 1e-3f,
                                        context));
        row["components_removed"] = removed;
        morph_seconds += Seconds(tfilter);
      }
      const SolverResult& r = refined.result;
      row["iterations"] = r.iterations;
      row["relative_residual"] = Num(r.relative_residual);
      row["initial_energy"] = Num(r.initial_energy);
      row["energy"] = Num(r.energy);
      row["converged"] = r.converged;
      // For the morph methods: registration + solve (+ component filter).
      row["solve_seconds"] = refined.seconds + morph_seconds;
      row["max_iterations"] = method.solver.max_iterations;
      row["tolerance"] = method.solver.tolerance;
      row["crease"] = Num(CreaseIndex(value, stacked.fixed_slices));
      if (method.solver.method == SolverMethod::kConjugateGradient) {
        rec.AddConvergence(
            {{"experiment", c.curve_tag.empty() ? c.experiment : c.curve_tag},
             {"k", c.factor},
             {"method", name},
             {"iteration", 0},
             {"relative_residual", 1.0},
             {"energy", Num(r.initial_energy)}});
        for (json& p : curve) {
          p["experiment"] = c.curve_tag.empty() ? c.experiment : c.curve_tag;
          p["k"] = c.factor;
          p["method"] = name;
          rec.AddConvergence(std::move(p));
        }
      }
    }
    const Mask mask = Threshold(value, 0.0f);
    if (std::getenv("INTERSLICE_EVAL_DUMP") != nullptr) {
      // Debugging aid: the whole field as raw float32 (i fastest).
      std::ofstream dump(
          absl::StrCat(std::getenv("INTERSLICE_EVAL_DUMP"), "/", c.experiment,
                       "_k", c.factor, "_", name, ".f32"),
          std::ios::binary);
      dump.write(reinterpret_cast<const char*>(value.data.data()),
                 static_cast<std::streamsize>(value.data.size() * 4));
    }
    row["dice"] = Num(DiceOnSlices(mask, truth, c.eval_slices));
    const SurfaceDistances sd = SurfaceDistancesOnSlices(
        mask, BoundaryDistanceMap(mask), truth, truth_map, c.eval_slices);
    row["hd95_mm"] = Num(sd.hd95);
    row["hdmax_mm"] = Num(sd.hdmax);
    row["msd_mm"] = Num(sd.msd);
    row["surface_samples"] = sd.samples;
    row["components"] = ComponentsJson(CountComponents(mask));
    row["truth_components"] = ComponentsJson(truth_components);
    if (c.slab_k0 >= 0) {
      row["slab"] = {{"k0", c.slab_k0}, {"k1", c.slab_k1}};
      row["slab_components"] =
          ComponentsJson(CountComponentsInSlab(mask, c.slab_k0, c.slab_k1));
      row["truth_slab_components"] = ComponentsJson(truth_slab);
    }
    row["evaluated_slices"] = evaluated;
    if (c.analytic && !method.nearest && !method.grey_linear) {
      // Surface error of the mesh against the analytic shape (as the test).
      INTERSLICE_ASSIGN_OR_RETURN(const Mesh mesh,
                                  ExtractSurface(value, {}, context));
      double sum = 0, worst = 0;
      for (const auto& v : mesh.vertices) {
        const double e = std::abs(c.analytic(v[0], v[1], v[2]));
        sum += e;
        worst = std::max(worst, e);
      }
      row["mesh_mean_error_mm"] =
          Num(sum / std::max<size_t>(1, mesh.vertices.size()));
      row["mesh_max_error_mm"] = Num(worst);
      row["mesh_triangles"] = mesh.triangles.size();
    }
    INTERSLICE_RETURN_IF_ERROR(WritePlanes(c, name, value, rec));
    row["total_seconds"] = Seconds(tm);
    std::fprintf(stderr, "  %-10s %s (%.1f s)\n", name.c_str(),
                 row.dump().c_str(), Seconds(tm));
    rec.AddRow(std::move(row));
  }
  return absl::OkStatus();
}

absl::StatusOr<DicomSeries> ReadSeries(const std::string& dir,
                                       const EvalOptions& o) {
  ComputeContext context;
  context.threads = o.threads;
  return ReadDicomSeries({dir}, {}, context);
}

absl::StatusOr<VoxelBox> ChooseRoi(const Volume<float>& image,
                                   const EvalOptions& o) {
  const Index3 n = image.grid.size;
  VoxelBox box{{0, 0, 0}, n};
  if (o.roi == "full") return box;
  if (o.roi != "auto") {
    std::vector<std::string> parts = absl::StrSplit(o.roi, ',');
    int64_t v[4];
    if (parts.size() != 4 || !absl::SimpleAtoi(parts[0], &v[0]) ||
        !absl::SimpleAtoi(parts[1], &v[1]) ||
        !absl::SimpleAtoi(parts[2], &v[2]) ||
        !absl::SimpleAtoi(parts[3], &v[3]))
      return absl::InvalidArgumentError(
          "--roi must be auto, full or i0,i1,j0,j1");
    box.begin = {v[0], v[2], 0};
    box.end = {v[1], v[3], n[2]};
    INTERSLICE_RETURN_IF_ERROR(ValidateVoxelBox(box, image.grid));
    return box;
  }
  int64_t i0 = n[0], i1 = -1, j0 = n[1], j1 = -1;
  for (int64_t k = 0; k < n[2]; ++k)
    for (int64_t j = 0; j < n[1]; ++j)
      for (int64_t i = 0; i < n[0]; ++i)
        if (image.at(i, j, k) >= o.threshold) {
          i0 = std::min(i0, i);
          i1 = std::max(i1, i);
          j0 = std::min(j0, j);
          j1 = std::max(j1, j);
        }
  if (i1 < 0)
    return absl::FailedPreconditionError(absl::StrFormat(
        "no voxel of the series reaches the threshold %g", o.threshold));
  const int64_t m = o.roi_margin;
  box.begin = {std::max<int64_t>(0, i0 - m), std::max<int64_t>(0, j0 - m), 0};
  box.end = {std::min(n[0], i1 + m + 1), std::min(n[1], j1 + m + 1), n[2]};
  return box;
}

json GridJson(const Grid& g) {
  return {{"size", g.size},
          {"spacing", g.spacing},
          {"origin", g.origin},
          {"direction", g.direction}};
}

// The original slices first, k, 2k, ... of `image` as a volume with k times
// the slice spacing.
Volume<float> KeepEveryKth(const Volume<float>& image, int k) {
  const int64_t count = (image.grid.size[2] - 1) / k + 1;
  Volume<float> out;
  out.grid = image.grid;
  out.grid.size[2] = count;
  out.grid.spacing[2] = image.grid.spacing[2] * k;
  const int64_t plane = image.grid.SliceVoxelCount();
  out.data.resize(count * plane);
  for (int64_t s = 0; s < count; ++s)
    std::copy(image.data.begin() + s * k * plane,
              image.data.begin() + (s * k + 1) * plane,
              out.data.begin() + s * plane);
  return out;
}

Volume<float> Slices(const Volume<float>& image, int64_t k0, int64_t k1) {
  return CropVolume(
      image,
      VoxelBox{{0, 0, k0}, {image.grid.size[0], image.grid.size[1], k1}});
}

// Centre of mass (i, j) of the thresholded volume.
std::pair<int64_t, int64_t> CentreOfMass(const Volume<float>& v, float level) {
  double si = 0, sj = 0, n = 0;
  const Index3 s = v.grid.size;
  for (int64_t k = 0; k < s[2]; ++k)
    for (int64_t j = 0; j < s[1]; ++j)
      for (int64_t i = 0; i < s[0]; ++i)
        if (v.at(i, j, k) >= level) {
          si += i;
          sj += j;
          n += 1;
        }
  if (n == 0) return {s[0] / 2, s[1] / 2};
  return {static_cast<int64_t>(std::lround(si / n)),
          static_cast<int64_t>(std::lround(sj / n))};
}

// Highest slice holding object voxels (-1 if none).
int64_t TopSlice(const Volume<float>& v, float level) {
  const int64_t plane = v.grid.SliceVoxelCount();
  for (int64_t k = v.grid.size[2] - 1; k >= 0; --k)
    for (int64_t p = 0; p < plane; ++p)
      if (v.data[k * plane + p] >= level) return k;
  return -1;
}

struct ThinSeries {
  Volume<float> image;  // cropped to the ROI
  VoxelBox roi;
  DicomSeries series;  // header info (image released)
};

absl::StatusOr<ThinSeries> LoadThin(const EvalOptions& o, Recorder& rec) {
  const auto t0 = Clock::now();
  INTERSLICE_ASSIGN_OR_RETURN(DicomSeries series, ReadSeries(o.thin_dir, o));
  INTERSLICE_ASSIGN_OR_RETURN(VoxelBox roi, ChooseRoi(series.image, o));
  ThinSeries thin;
  thin.image = CropVolume(series.image, roi);
  thin.roi = roi;
  rec.meta()["thin"] = {
      {"dir", o.thin_dir},
      {"grid", GridJson(series.image.grid)},
      {"roi_begin", roi.begin},
      {"roi_end", roi.end},
      {"roi_mode", o.roi},
      {"frame_of_reference_uid", series.frame_of_reference_uid}};
  series.image = Volume<float>();
  thin.series = std::move(series);
  std::fprintf(stderr, "thin series read and cropped in %.1f s: ROI %s\n",
               Seconds(t0), thin.image.grid.DebugString().c_str());
  return thin;
}

}  // namespace

Recorder::Recorder(std::string out_dir) : out_dir_(std::move(out_dir)) {}

absl::Status Recorder::WritePlane(const std::string& name, const json& tags,
                                  const std::vector<float>& data, int64_t rows,
                                  int64_t cols, double row_mm, double col_mm) {
  std::filesystem::create_directories(out_dir_ + "/raw");
  const std::string file = "raw/" + name + ".f32";
  std::ofstream out(out_dir_ + "/" + file, std::ios::binary);
  out.write(reinterpret_cast<const char*>(data.data()),
            static_cast<std::streamsize>(data.size() * sizeof(float)));
  if (!out) return absl::InternalError("cannot write " + file);
  json entry = tags;
  entry["file"] = file;
  entry["rows"] = rows;
  entry["cols"] = cols;
  entry["row_mm"] = row_mm;
  entry["col_mm"] = col_mm;
  planes_.push_back(std::move(entry));
  return absl::OkStatus();
}

absl::Status Recorder::Finish() {
  std::filesystem::create_directories(out_dir_);
  {
    std::ofstream out(out_dir_ + "/results.json");
    json all = {
        {"meta", meta_}, {"metrics", rows_}, {"convergence", convergence_}};
    out << all.dump(1) << "\n";
  }
  {
    std::ofstream out(out_dir_ + "/planes.json");
    out << planes_.dump(1) << "\n";
  }
  {
    // Flat CSV: nested objects become a.b columns.
    std::vector<std::string> columns;
    std::vector<std::vector<std::pair<std::string, std::string>>> flat;
    for (const json& row : rows_) {
      std::vector<std::pair<std::string, std::string>> cells;
      for (const auto& [key, value] : row.items()) {
        if (value.is_object()) {
          for (const auto& [k2, v2] : value.items())
            cells.push_back({key + "." + k2, CsvCell(v2)});
        } else {
          cells.push_back({key, CsvCell(value)});
        }
      }
      for (const auto& [key, value] : cells)
        if (std::find(columns.begin(), columns.end(), key) == columns.end())
          columns.push_back(key);
      flat.push_back(std::move(cells));
    }
    std::ofstream out(out_dir_ + "/metrics.csv");
    for (size_t c = 0; c < columns.size(); ++c)
      out << (c ? "," : "") << columns[c];
    out << "\n";
    for (const auto& cells : flat) {
      for (size_t c = 0; c < columns.size(); ++c) {
        if (c) out << ",";
        for (const auto& [key, value] : cells)
          if (key == columns[c]) out << value;
      }
      out << "\n";
    }
  }
  {
    std::ofstream out(out_dir_ + "/convergence.csv");
    out << "experiment,k,method,iteration,relative_residual,energy\n";
    for (const json& p : convergence_)
      out << CsvCell(p["experiment"]) << "," << CsvCell(p["k"]) << ","
          << CsvCell(p["method"]) << "," << CsvCell(p["iteration"]) << ","
          << CsvCell(p["relative_residual"]) << "," << CsvCell(p["energy"])
          << "\n";
  }
  return absl::OkStatus();
}

absl::Status RunDropK(const EvalOptions& o, Recorder& rec) {
  INTERSLICE_ASSIGN_OR_RETURN(ThinSeries thin, LoadThin(o, rec));
  const Volume<float>& image = thin.image;
  const auto [ci, cj] = CentreOfMass(image, o.threshold);
  for (int k : o.ks) {
    if (k < 2 || (image.grid.size[2] - 1) / k < 1)
      return absl::InvalidArgumentError(absl::StrCat("bad k ", k));
    Case c;
    c.experiment = "dropk";
    c.factor = k;
    c.originals = KeepEveryKth(image, k);
    const int64_t out_slices = (c.originals.grid.size[2] - 1) * k + 1;
    c.truth_grey = Slices(image, 0, out_slices);
    c.level = o.threshold;
    c.contour.lower = o.threshold;
    c.eval_slices.resize(out_slices);
    for (int64_t z = 0; z < out_slices; ++z) c.eval_slices[z] = z % k != 0;
    c.methods = o.methods;
    c.sagittal_i = ci;
    c.coronal_j = cj;
    const int64_t top = TopSlice(c.truth_grey, o.threshold);
    const int64_t slab = std::lround(o.top_slab_mm / image.grid.spacing[2]);
    c.slab_k0 = std::max<int64_t>(0, top - slab + 1);
    c.slab_k1 = top + 1;
    c.write_slab_axials = (k == 8);
    INTERSLICE_RETURN_IF_ERROR(RunCase(c, o, rec));
  }
  return absl::OkStatus();
}

absl::Status RunThickToThin(const EvalOptions& o, Recorder& rec) {
  INTERSLICE_ASSIGN_OR_RETURN(ThinSeries thin, LoadThin(o, rec));
  INTERSLICE_ASSIGN_OR_RETURN(DicomSeries thick, ReadSeries(o.thick_dir, o));
  const Grid& tg = thin.series.image.grid;  // released; use meta instead
  (void)tg;
  const Grid thin_grid = thin.image.grid;  // cropped: origin moved in-plane
  if (thick.frame_of_reference_uid != thin.series.frame_of_reference_uid)
    return absl::FailedPreconditionError(
        "thick and thin series have different FrameOfReferenceUIDs");
  // The thick series must share the thin one's in-plane grid; crop it alike.
  Volume<float> thick_image = CropVolume(
      thick.image,
      VoxelBox{{thin.roi.begin[0], thin.roi.begin[1], 0},
               {thin.roi.end[0], thin.roi.end[1], thick.image.grid.size[2]}});
  const Grid& kg = thick_image.grid;
  const Vec3 normal = thin_grid.Axis(2);
  for (int c = 0; c < 9; ++c)
    if (std::abs(kg.direction[c] - thin_grid.direction[c]) > 1e-4)
      return absl::FailedPreconditionError("orientations differ");
  for (int c = 0; c < 2; ++c)
    if (std::abs(kg.spacing[c] - thin_grid.spacing[c]) > 1e-4)
      return absl::FailedPreconditionError("pixel spacings differ");
  double offset_mm = 0, inplane = 0;
  for (int c = 0; c < 3; ++c) {
    const double d = kg.origin[c] - thin_grid.origin[c];
    offset_mm += d * normal[c];
  }
  for (int c = 0; c < 3; ++c) {
    const double d = kg.origin[c] - thin_grid.origin[c] - offset_mm * normal[c];
    inplane += d * d;
  }
  if (std::sqrt(inplane) > 0.01)
    return absl::FailedPreconditionError("in-plane origins differ");
  const double ratio = kg.spacing[2] / thin_grid.spacing[2];
  const int factor = static_cast<int>(std::lround(ratio));
  const double off = offset_mm / thin_grid.spacing[2];
  const int64_t k_off = std::lround(off);
  if (std::abs(ratio - factor) > 0.01 || std::abs(off - k_off) > 0.01 ||
      factor < 1)
    return absl::FailedPreconditionError(absl::StrFormat(
        "thick slices (spacing %g mm, offset %g mm) are not on thin slice "
        "positions (spacing %g mm)",
        kg.spacing[2], offset_mm, thin_grid.spacing[2]));
  const int64_t out_slices = (kg.size[2] - 1) * factor + 1;
  if (k_off < 0 || k_off + out_slices > thin_grid.size[2])
    return absl::FailedPreconditionError(
        "the thick series reaches beyond the thin one");
  Case c;
  c.experiment = "thick";
  c.factor = factor;
  c.originals = std::move(thick_image);
  if (const char* slab = std::getenv("INTERSLICE_EVAL_SLAB_MM")) {
    // Candidate probe (docs/eval/candidates.md, "Slab deconvolution"): the
    // thick slices replaced by their slab deconvolution before any method.
    SlabDeconvolutionOptions so;
    so.slab_thickness_mm = std::atof(slab);
    so.factor = factor;
    ComputeContext sc;
    sc.threads = o.threads;
    INTERSLICE_ASSIGN_OR_RETURN(SlabDeconvolution sd,
                                DeconvolveSlabs(c.originals, so, sc));
    std::fprintf(stderr,
                 "slab deconvolution %g mm: %d iterations, residual %.2f -> "
                 "%.2f\n",
                 so.slab_thickness_mm, sd.iterations, sd.initial_rms,
                 sd.final_rms);
    c.originals = std::move(sd.slices);
  }
  c.truth_grey = Slices(thin.image, k_off, k_off + out_slices);
  // The output grid starts at the thick series' origin: same as the thin
  // slice k_off (checked above), so only the origin differs by rounding.
  c.truth_grey.grid.origin = c.originals.grid.origin;
  c.truth_grey.grid.spacing[2] = c.originals.grid.spacing[2] / factor;
  c.level = o.threshold;
  c.contour.lower = o.threshold;
  c.eval_slices.assign(out_slices, 1);  // every thin position
  c.methods = o.methods;
  const auto [ci, cj] = CentreOfMass(c.truth_grey, o.threshold);
  c.sagittal_i = ci;
  c.coronal_j = cj;
  rec.meta()["thick"] = {{"dir", o.thick_dir},
                         {"grid", GridJson(kg)},
                         {"factor", factor},
                         {"thin_slice_offset", k_off},
                         {"thin_slices_compared", out_slices}};
  return RunCase(c, o, rec);
}

namespace {

Volume<float> SampleShape(
    const std::function<double(double, double, double)>& shape, int64_t slices,
    int step) {
  Volume<float> v;
  v.grid.size = {kShapeSize, kShapeSize, slices};
  v.grid.spacing = {1, 1, static_cast<double>(step)};
  v.data.resize(v.grid.VoxelCount());
  for (int64_t s = 0; s < slices; ++s)
    for (int j = 0; j < kShapeSize; ++j)
      for (int i = 0; i < kShapeSize; ++i)
        v.at(i, j, s) = static_cast<float>(shape(i, j, s * step));
  return v;
}

}  // namespace

absl::Status RunArtificial(const EvalOptions& o, Recorder& rec) {
  struct Shape {
    const char* name;
    double (*f)(double, double, double);
  };
  for (const Shape& shape :
       {Shape{"sphere", &Sphere}, Shape{"tubes", &TubeCross}}) {
    constexpr int kFactor = 8;
    constexpr int64_t kOut = 65;
    Case c;
    c.experiment = absl::StrCat("artificial-", shape.name);
    c.factor = kFactor;
    c.originals = SampleShape(shape.f, (kOut - 1) / kFactor + 1, kFactor);
    c.truth_grey = SampleShape(shape.f, kOut, 1);
    c.level = 0;
    c.contour.lower = 0;
    c.contour.band_radius_mm = 2.0 * kShapeSize;
    c.eval_slices.resize(kOut);
    for (int64_t z = 0; z < kOut; ++z) c.eval_slices[z] = z % kFactor != 0;
    c.methods.clear();
    for (const std::string& m : o.methods)
      if (!absl::EndsWith(m, "-mm")) c.methods.push_back(m);  // isotropic
    c.sagittal_i = kShapeSize / 2;
    c.coronal_j = kShapeSize / 2;
    c.analytic = shape.f;
    INTERSLICE_RETURN_IF_ERROR(RunCase(c, o, rec));
  }
  return absl::OkStatus();
}

absl::Status RunConvergence(const EvalOptions& o, Recorder& rec) {
  // The paper's Figure 5: CG on the sphere with z resolution raised by 2, 4
  // and 8 (65 output slices each), run to a tight tolerance.
  EvalOptions tight = o;
  tight.cg_tolerance = 1e-7;
  tight.cg_max_iterations = 1000;
  for (int factor : {2, 4, 8}) {
    constexpr int64_t kOut = 65;
    Case c;
    c.experiment = "fig5-sphere";
    c.curve_tag = "fig5-sphere";
    c.factor = factor;
    c.originals = SampleShape(&Sphere, (kOut - 1) / factor + 1, factor);
    c.truth_grey = SampleShape(&Sphere, kOut, 1);
    c.level = 0;
    c.contour.lower = 0;
    c.contour.band_radius_mm = 2.0 * kShapeSize;
    c.eval_slices.resize(kOut);
    for (int64_t z = 0; z < kOut; ++z) c.eval_slices[z] = z % factor != 0;
    c.methods = {"cgtol", "direct"};
    INTERSLICE_RETURN_IF_ERROR(RunCase(c, tight, rec));
  }
  return absl::OkStatus();
}

}  // namespace interslice::eval

// interslice_grey_eval: the intensity harness of issue 23 (scripts/
// eval-intensity.sh runs it on every series and tools/eval/grey_report.py
// writes docs/eval/intensity.md). Drop-k on one real series: keep every k-th
// slice, rebuild the withheld ones by each interpolator of the derived
// intensity series, and compare with the truth (tools/eval/grey_metrics.h):
// RMSE and PSNR inside the body, in homogeneous soft tissue, in bands around
// bone and skin edges; mean SSIM inside the body; 10-90% rise distance across
// bone and skin edges. Sagittal and coronal planes go to raw/ for figures.
//
//   interslice_grey_eval --series DIR --name NAME --out DIR [--ks 2,4,8]
//       [--methods linear,catmull-rom,morph] [--bone HU] [--body LEVEL]
//       [--soft LO,HI] [--threads N]
//
// Methods: linear (ResampleSourceSlices, today's series), catmull-rom and
// pchip-z (in place along z), morph (MorphIntensity defaults), and ablations:
// morph-maps (registration by the bone's distance maps), morph-bwd (key
// slice s+1 sampled through the backward field), morph-nofallback,
// morph-nopair (without the pair check),
// morph-linvals (values blended linearly along the trajectory). GREY_*
// environment variables override the morph's settings for sensitivity runs (see
// ApplyOverrides).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <optional>
#include <string>
#include <vector>

#include "CLI/CLI.hpp"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "core/common/status_macros.h"
#include "core/dicom/series_reader.h"
#include "core/dicom_out/dicom_writer.h"
#include "core/morph/intensity_morph.h"
#include "core/sdf/signed_distance.h"
#include "itkBinaryFillholeImageFilter.h"
#include "itkGradientRecursiveGaussianImageFilter.h"
#include "itkImage.h"
#include "nlohmann/json.hpp"
#include "tools/eval/grey_metrics.h"
#include "tools/eval/metrics.h"

namespace interslice::eval {
namespace {

using json = nlohmann::json;
using Clock = std::chrono::steady_clock;

double Seconds(Clock::time_point since) {
  return std::chrono::duration<double>(Clock::now() - since).count();
}

struct Options {
  std::string series, name, out;
  std::vector<int> ks = {2, 4, 8};
  std::vector<std::string> methods = {"linear", "catmull-rom", "morph"};
  double bone = 300;   // edge level of the bone edges (HU)
  double body = -500;  // body = truth >= body (holes filled per slice)
  std::string soft = "-100,100";       // homogeneous soft tissue value range
  double homogeneous_gradient = 0.01;  // x dynamic range per mm
  int threads = 0;
  int margin = 8;
};

void ApplyOverrides(IntensityMorphOptions& o) {
  auto num = [](const char* name, double& value) {
    if (const char* e = std::getenv(name)) value = std::atof(e);
  };
  auto integer = [](const char* name, int& value) {
    if (const char* e = std::getenv(name)) value = std::atoi(e);
  };
  num("GREY_SCALE", o.grey_scale);
  num("GREY_JAC", o.min_jacobian);
  num("GREY_GLOW", o.gain_low);
  num("GREY_QLOW", o.ratio_low);
  num("GREY_QHIGH", o.ratio_high);
  num("GREY_GHIGH", o.gain_high);
  num("GREY_RSIGMA", o.residual_sigma_px);
  num("GREY_PAIR_TOL", o.pair_tolerance_noise);
  num("GREY_PAIR_SIGMA", o.pair_sigma_px);
  num("GREY_PAIR_STATIC", o.pair_static_noise);
  num("GREY_SIGMA", o.demons.field_sigma_px);
  integer("GREY_ITS", o.demons.iterations);
  integer("GREY_DS", o.demons.downsample);
  integer("GREY_LEVELS", o.demons.levels);
}

absl::StatusOr<IntensityMorphOptions> MethodOptions(const std::string& name) {
  IntensityMorphOptions o;
  if (name == "catmull-rom" || name == "pchip-z") {
    o.register_slices = false;
    o.values =
        name == "pchip-z" ? MorphValues::kMonotone : MorphValues::kCatmullRom;
    return o;
  }
  ApplyOverrides(o);
  if (name == "morph") return o;
  if (name == "morph-maps") {
    o.registration = IntensityRegistration::kDistanceMaps;
  } else if (name == "morph-bwd") {
    o.backward_fields = true;
  } else if (name == "morph-nofallback") {
    o.gain_low = -2e6;
    o.gain_high = -1e6;
    o.ratio_low = 1e6;
    o.ratio_high = 2e6;
    o.min_jacobian = 1e-9;
    o.max_gap_ratio = 1e9;
    o.pair_check = false;
  } else if (name == "morph-maps-nofallback") {
    o.registration = IntensityRegistration::kDistanceMaps;
    o.gain_low = -2e6;
    o.gain_high = -1e6;
    o.ratio_low = 1e6;
    o.ratio_high = 2e6;
    o.min_jacobian = 1e-9;
    o.max_gap_ratio = 1e9;
    o.pair_check = false;
  } else if (name == "morph-nopair") {
    o.pair_check = false;
  } else if (name == "morph-cr") {
    o.values = MorphValues::kCatmullRom;
  } else if (name == "morph-linvals") {
    o.values = MorphValues::kLinear;
  } else {
    return absl::InvalidArgumentError(absl::StrCat("unknown method ", name));
  }
  return o;
}

// Body: truth >= level, holes filled slice by slice (ITK).
std::vector<uint8_t> BodyMask(const Volume<float>& truth, double level) {
  using Mask2 = itk::Image<uint8_t, 2>;
  const int64_t nx = truth.grid.size[0], ny = truth.grid.size[1];
  const int64_t plane = nx * ny;
  std::vector<uint8_t> body(truth.data.size(), 0);
  for (int64_t k = 0; k < truth.grid.size[2]; ++k) {
    Mask2::Pointer m = Mask2::New();
    Mask2::RegionType region;
    region.SetSize({static_cast<itk::SizeValueType>(nx),
                    static_cast<itk::SizeValueType>(ny)});
    m->SetRegions(region);
    m->Allocate();
    uint8_t* buffer = m->GetBufferPointer();
    for (int64_t v = 0; v < plane; ++v)
      buffer[v] = truth.data[k * plane + v] >= level ? 1 : 0;
    auto fill = itk::BinaryFillholeImageFilter<Mask2>::New();
    fill->SetInput(m);
    fill->SetForegroundValue(1);
    fill->Update();
    const uint8_t* filled = fill->GetOutput()->GetBufferPointer();
    std::copy(filled, filled + plane, body.begin() + k * plane);
  }
  return body;
}

// Smoothed gradient of the truth in LPS, per mm (ITK, sigma in mm).
std::vector<Vec3> Gradient(const Volume<float>& v, double sigma_mm) {
  using Image = itk::Image<float, 3>;
  using Filter = itk::GradientRecursiveGaussianImageFilter<Image>;
  Image::Pointer image = Image::New();
  Image::RegionType region;
  region.SetSize({static_cast<itk::SizeValueType>(v.grid.size[0]),
                  static_cast<itk::SizeValueType>(v.grid.size[1]),
                  static_cast<itk::SizeValueType>(v.grid.size[2])});
  image->SetRegions(region);
  Image::SpacingType spacing;
  for (int a = 0; a < 3; ++a) spacing[a] = v.grid.spacing[a];
  image->SetSpacing(spacing);
  image->Allocate();
  std::copy(v.data.begin(), v.data.end(), image->GetBufferPointer());
  auto filter = Filter::New();
  filter->SetInput(image);
  filter->SetSigma(sigma_mm);
  filter->Update();
  const auto* g = filter->GetOutput()->GetBufferPointer();
  std::vector<Vec3> out(v.data.size());
  const Vec3 ax[3] = {v.grid.Axis(0), v.grid.Axis(1), v.grid.Axis(2)};
  for (size_t i = 0; i < out.size(); ++i)
    for (int c = 0; c < 3; ++c)
      out[i][c] = g[i][0] * ax[0][c] + g[i][1] * ax[1][c] + g[i][2] * ax[2][c];
  return out;
}

// Edge points: boundary voxels of truth >= level on evaluated slices (a face
// neighbour in the slice below the level), every stride-th, with the unit
// gradient direction.
struct EdgePoint {
  Vec3 p, n;
};
std::vector<EdgePoint> EdgePoints(const Volume<float>& truth,
                                  const std::vector<Vec3>& gradient,
                                  const std::vector<uint8_t>& eval_slices,
                                  double level, int64_t max_points) {
  const Index3 n = truth.grid.size;
  std::vector<int64_t> candidates;
  for (int64_t k = 0; k < n[2]; ++k) {
    if (!eval_slices[k]) continue;
    for (int64_t j = 1; j + 1 < n[1]; ++j)
      for (int64_t i = 1; i + 1 < n[0]; ++i) {
        if (truth.at(i, j, k) < level) continue;
        if (truth.at(i - 1, j, k) < level || truth.at(i + 1, j, k) < level ||
            truth.at(i, j - 1, k) < level || truth.at(i, j + 1, k) < level)
          candidates.push_back(truth.grid.LinearIndex(i, j, k));
      }
  }
  const int64_t stride = std::max<int64_t>(
      1, static_cast<int64_t>(candidates.size()) / max_points);
  std::vector<EdgePoint> points;
  for (size_t c = 0; c < candidates.size(); c += stride) {
    const int64_t v = candidates[c];
    const Vec3 g = gradient[v];
    const double len = std::sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]);
    if (!(len > 0)) continue;
    const int64_t plane = truth.grid.SliceVoxelCount();
    const int64_t k = v / plane, j = (v % plane) / n[0], i = v % n[0];
    points.push_back({truth.grid.IndexToPhysical({static_cast<double>(i),
                                                  static_cast<double>(j),
                                                  static_cast<double>(k)}),
                      {g[0] / len, g[1] / len, g[2] / len}});
  }
  return points;
}

double Median(std::vector<double> v) {
  if (v.empty()) return std::nan("");
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

double Quantile(std::vector<float> v, double q) {
  if (v.empty()) return 0;
  const size_t i = static_cast<size_t>(q * (v.size() - 1));
  std::nth_element(v.begin(), v.begin() + i, v.end());
  return v[i];
}

std::vector<float> Plane(const Volume<float>& v, bool sagittal, int64_t index) {
  const Index3 n = v.grid.size;
  const int64_t cols = sagittal ? n[1] : n[0];
  std::vector<float> out(n[2] * cols);
  for (int64_t k = 0; k < n[2]; ++k)
    for (int64_t c = 0; c < cols; ++c)
      out[k * cols + c] = sagittal ? v.at(index, c, k) : v.at(c, index, k);
  return out;
}

absl::Status Run(const Options& o) {
  ComputeContext context;
  context.threads = o.threads;
  std::filesystem::create_directories(o.out + "/raw");
  INTERSLICE_ASSIGN_OR_RETURN(DicomSeries series,
                              ReadDicomSeries({o.series}, {}, context));
  INTERSLICE_ASSIGN_OR_RETURN(const std::optional<float> padding,
                              SourcePixelPadding(series));
  // Crop in-plane to the body's bounding box (+ margin): the air around it
  // only costs time.
  const Volume<float>& full = series.image;
  const Index3 fn = full.grid.size;
  int64_t i0 = fn[0], i1 = -1, j0 = fn[1], j1 = -1;
  for (int64_t k = 0; k < fn[2]; ++k)
    for (int64_t j = 0; j < fn[1]; ++j)
      for (int64_t i = 0; i < fn[0]; ++i)
        if (full.at(i, j, k) >= o.body &&
            !(padding.has_value() && full.at(i, j, k) == *padding)) {
          i0 = std::min(i0, i);
          i1 = std::max(i1, i);
          j0 = std::min(j0, j);
          j1 = std::max(j1, j);
        }
  if (i1 < 0) return absl::FailedPreconditionError("no body found");
  const VoxelBox roi{{std::max<int64_t>(0, i0 - o.margin),
                      std::max<int64_t>(0, j0 - o.margin), 0},
                     {std::min(fn[0], i1 + o.margin + 1),
                      std::min(fn[1], j1 + o.margin + 1), fn[2]}};
  const Volume<float> image = CropVolume(full, roi);
  std::vector<double> positions;
  for (const DicomSliceInfo& s : series.slices)
    positions.push_back(s.position_along_normal);
  std::vector<double> soft;
  for (absl::string_view part : absl::StrSplit(o.soft, ','))
    soft.push_back(std::atof(std::string(part).c_str()));
  json results = {
      {"series", o.name},
      {"dir", o.series},
      {"modality", series.modality},
      {"grid", {{"size", image.grid.size}, {"spacing", image.grid.spacing}}},
      {"gantry_tilt_degrees", series.gantry_tilt_degrees},
      {"padding", padding.has_value() ? json(*padding) : json()},
      {"bone", o.bone},
      {"body", o.body},
      {"soft", soft},
      {"rows", json::array()},
      {"planes", json::array()}};
  const int64_t plane = image.grid.SliceVoxelCount();
  for (int k : o.ks) {
    const int64_t keys_count = (image.grid.size[2] - 1) / k + 1;
    if (keys_count < 2) continue;
    const int64_t out_slices = (keys_count - 1) * k + 1;
    Volume<float> keys;
    keys.grid = image.grid;
    keys.grid.size[2] = keys_count;
    keys.grid.spacing[2] = image.grid.spacing[2] * k;
    keys.data.resize(keys_count * plane);
    std::vector<double> key_positions;
    for (int64_t s = 0; s < keys_count; ++s) {
      std::copy(image.data.begin() + s * k * plane,
                image.data.begin() + (s * k + 1) * plane,
                keys.data.begin() + s * plane);
      key_positions.push_back(positions[s * k]);
    }
    const Volume<float> truth = CropVolume(
        image, VoxelBox{{0, 0, 0},
                        {image.grid.size[0], image.grid.size[1], out_slices}});
    std::vector<uint8_t> eval_slices(out_slices);
    for (int64_t z = 0; z < out_slices; ++z) eval_slices[z] = z % k != 0;
    // Regions on the evaluated slices.
    const std::vector<uint8_t> body_all = BodyMask(truth, o.body);
    std::vector<uint8_t> body(truth.data.size(), 0);
    std::vector<float> body_values;
    for (int64_t z = 0; z < out_slices; ++z) {
      if (!eval_slices[z]) continue;
      for (int64_t v = z * plane; v < (z + 1) * plane; ++v)
        if (body_all[v]) {
          body[v] = 1;
          body_values.push_back(truth.data[v]);
        }
    }
    const double range =
        Quantile(body_values, 0.999) - Quantile(body_values, 0.001);
    const std::vector<Vec3> gradient = Gradient(truth, 1.0);
    std::vector<uint8_t> homogeneous(truth.data.size(), 0),
        bone_band(truth.data.size(), 0), skin_band(truth.data.size(), 0);
    for (size_t v = 0; v < truth.data.size(); ++v) {
      if (!body[v]) continue;
      const Vec3& g = gradient[v];
      const double gm = std::sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]);
      const float t = truth.data[v];
      if (gm < o.homogeneous_gradient * range &&
          (soft.size() != 2 || (t >= soft[0] && t <= soft[1])))
        homogeneous[v] = 1;
    }
    // Edge bands: evaluated voxels within ~2 mm of the edge level's crossing
    // (the smoothed gradient there is the edge's): |truth - level| / |grad|.
    auto band = [&](double level, std::vector<uint8_t>& out, bool in_body) {
      for (int64_t z = 0; z < out_slices; ++z) {
        if (!eval_slices[z]) continue;
        for (int64_t v = z * plane; v < (z + 1) * plane; ++v) {
          if (in_body && !body_all[v]) continue;
          const Vec3& g = gradient[v];
          const double gm = std::sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]);
          if (gm > 0 && std::abs(truth.data[v] - level) / gm <= 2.0) out[v] = 1;
        }
      }
    };
    if (const char* dump = std::getenv("GREY_DUMP")) {
      // Debugging aid: the homogeneous soft-tissue mask (uint8) on the grid.
      std::ofstream(absl::StrCat(dump, "/", o.name, "_k", k, "_homogeneous.u8"),
                    std::ios::binary)
          .write(reinterpret_cast<const char*>(homogeneous.data()),
                 homogeneous.size());
    }
    band(o.bone, bone_band, true);
    band(o.body, skin_band, false);
    const std::vector<EdgePoint> bone_points =
        EdgePoints(truth, gradient, eval_slices, o.bone, 4000);
    const std::vector<EdgePoint> skin_points =
        EdgePoints(truth, gradient, eval_slices, o.body, 4000);
    auto rises = [&](const Volume<float>& v,
                     const std::vector<EdgePoint>& pts) {
      std::vector<std::optional<double>> r(pts.size());
      for (size_t q = 0; q < pts.size(); ++q)
        r[q] = RiseDistance(v, pts[q].p, pts[q].n, 4.0, 0.05);
      return r;
    };
    const auto truth_bone = rises(truth, bone_points);
    const auto truth_skin = rises(truth, skin_points);
    // Distance maps of the key slices, for morph-maps.
    ContourOptions contour;
    contour.lower = static_cast<float>(o.bone);
    INTERSLICE_ASSIGN_OR_RETURN(
        const Volume<float> maps,
        ComputeSliceDistanceMaps(keys, contour, context));
    const int64_t sagittal = truth.grid.size[0] / 2;
    const int64_t coronal = truth.grid.size[1] / 2;
    if (k == 4 || k == 8) {
      for (bool sag : {true, false}) {
        const std::string file = absl::StrCat(
            "raw/k", k, "_truth_", sag ? "sagittal" : "coronal", ".f32");
        const std::vector<float> data =
            Plane(truth, sag, sag ? sagittal : coronal);
        std::ofstream(o.out + "/" + file, std::ios::binary)
            .write(reinterpret_cast<const char*>(data.data()), data.size() * 4);
        results["planes"].push_back(
            {{"k", k},
             {"method", "truth"},
             {"plane", sag ? "sagittal" : "coronal"},
             {"file", file},
             {"rows", out_slices},
             {"cols", sag ? truth.grid.size[1] : truth.grid.size[0]},
             {"row_mm", truth.grid.spacing[2]},
             {"col_mm", truth.grid.spacing[sag ? 1 : 0]}});
      }
    }
    for (const std::string& method : o.methods) {
      const auto t0 = Clock::now();
      Volume<float> result;
      json row = {{"series", o.name}, {"k", k}, {"method", method}};
      if (method == "linear") {
        INTERSLICE_ASSIGN_OR_RETURN(
            result, ResampleSourceSlices(keys, key_positions, truth.grid,
                                         padding, context));
      } else {
        INTERSLICE_ASSIGN_OR_RETURN(const IntensityMorphOptions mo,
                                    MethodOptions(method));
        INTERSLICE_ASSIGN_OR_RETURN(
            MorphedIntensity mi, MorphIntensity(keys, key_positions, truth.grid,
                                                padding, &maps, mo, context));
        result = std::move(mi.values);
        row["fallback_fraction"] = mi.statistics.fallback_fraction;
        row["noise_sigma"] = mi.statistics.noise_sigma;
        row["gaps_not_registered"] = mi.statistics.gaps_not_registered;
        row["mean_displacement_mm"] = mi.statistics.mean_displacement_mm;
        row["max_displacement_mm"] = mi.statistics.max_displacement_mm;
      }
      row["seconds"] = Seconds(t0);
      if (const char* dump = std::getenv("GREY_DUMP")) {
        // Debugging aid: the whole result (and the truth) as raw float32.
        std::ofstream(
            absl::StrCat(dump, "/", o.name, "_k", k, "_", method, ".f32"),
            std::ios::binary)
            .write(reinterpret_cast<const char*>(result.data.data()),
                   result.data.size() * 4);
        std::ofstream(absl::StrCat(dump, "/", o.name, "_k", k, "_truth.f32"),
                      std::ios::binary)
            .write(reinterpret_cast<const char*>(truth.data.data()),
                   truth.data.size() * 4);
      }
      // Key slices must be the source's.
      bool keys_identical = true;
      for (int64_t s = 0; s < keys_count; ++s)
        keys_identical &= std::equal(keys.data.begin() + s * plane,
                                     keys.data.begin() + (s + 1) * plane,
                                     result.data.begin() + s * k * plane);
      row["keys_identical"] = keys_identical;
      auto scores = [&](const std::vector<uint8_t>& mask) {
        const ErrorScores e = ErrorOnMask(result, truth, mask, range);
        return json{{"rmse", e.rmse}, {"psnr", e.psnr}, {"voxels", e.voxels}};
      };
      row["body"] = scores(body);
      row["homogeneous"] = scores(homogeneous);
      row["bone_band"] = scores(bone_band);
      row["skin_band"] = scores(skin_band);
      double ssim_sum = 0;
      int64_t ssim_count = 0;
      for (int64_t z = 0; z < out_slices; ++z) {
        if (!eval_slices[z]) continue;
        AccumulateSsim(result.data.data() + z * plane,
                       truth.data.data() + z * plane, truth.grid.size[0],
                       truth.grid.size[1], body.data() + z * plane, range,
                       &ssim_sum, &ssim_count);
      }
      row["ssim"] = ssim_count > 0 ? ssim_sum / ssim_count : 0;
      auto rise_json =
          [&](const std::vector<EdgePoint>& pts,
              const std::vector<std::optional<double>>& truth_rise) {
            const auto r = rises(result, pts);
            std::vector<double> all, oblique, truth_all, truth_oblique;
            int64_t undefined = 0;
            for (size_t q = 0; q < pts.size(); ++q) {
              if (!truth_rise[q].has_value()) continue;
              if (!r[q].has_value()) {
                ++undefined;
                continue;
              }
              all.push_back(*r[q]);
              truth_all.push_back(*truth_rise[q]);
              // Edges whose normal leans out of the slice plane: where z
              // interpolation decides the edge.
              if (std::abs(pts[q].n[0] * truth.grid.Axis(2)[0] +
                           pts[q].n[1] * truth.grid.Axis(2)[1] +
                           pts[q].n[2] * truth.grid.Axis(2)[2]) >= 0.5) {
                oblique.push_back(*r[q]);
                truth_oblique.push_back(*truth_rise[q]);
              }
            }
            return json{{"median_mm", Median(all)},
                        {"truth_median_mm", Median(truth_all)},
                        {"oblique_median_mm", Median(oblique)},
                        {"truth_oblique_median_mm", Median(truth_oblique)},
                        {"points", all.size()},
                        {"oblique_points", oblique.size()},
                        {"undefined", undefined}};
          };
      row["bone_rise"] = rise_json(bone_points, truth_bone);
      row["skin_rise"] = rise_json(skin_points, truth_skin);
      row["dynamic_range"] = range;
      std::fprintf(stderr, "%s k=%d %s %s\n", o.name.c_str(), k, method.c_str(),
                   row.dump().c_str());
      results["rows"].push_back(row);
      if (k == 4 || k == 8) {
        for (bool sag : {true, false}) {
          const std::string file =
              absl::StrCat("raw/k", k, "_", method, "_",
                           sag ? "sagittal" : "coronal", ".f32");
          const std::vector<float> data =
              Plane(result, sag, sag ? sagittal : coronal);
          std::ofstream(o.out + "/" + file, std::ios::binary)
              .write(reinterpret_cast<const char*>(data.data()),
                     data.size() * 4);
          results["planes"].push_back(
              {{"k", k},
               {"method", method},
               {"plane", sag ? "sagittal" : "coronal"},
               {"file", file},
               {"rows", out_slices},
               {"cols", sag ? truth.grid.size[1] : truth.grid.size[0]},
               {"row_mm", truth.grid.spacing[2]},
               {"col_mm", truth.grid.spacing[sag ? 1 : 0]}});
        }
      }
      std::ofstream(o.out + "/results.json") << results.dump(1) << "\n";
    }
  }
  std::ofstream(o.out + "/results.json") << results.dump(1) << "\n";
  return absl::OkStatus();
}

}  // namespace
}  // namespace interslice::eval

int main(int argc, char** argv) {
  interslice::eval::Options o;
  CLI::App app{"interslice intensity harness (drop-k, grey values)"};
  app.add_option("--series", o.series, "thin series folder")->required();
  app.add_option("--name", o.name, "series name in the report")->required();
  app.add_option("--out", o.out, "output folder")->required();
  app.add_option("--ks", o.ks, "drop-k factors")->delimiter(',');
  app.add_option("--methods", o.methods, "interpolators")->delimiter(',');
  app.add_option("--bone", o.bone, "bone edge level (modality units)");
  app.add_option("--body", o.body, "body level (modality units)");
  app.add_option("--soft", o.soft,
                 "homogeneous soft tissue range lo,hi ('' = any)");
  app.add_option("--homogeneous-gradient", o.homogeneous_gradient,
                 "homogeneous: smoothed gradient below this x range per mm");
  app.add_option("--threads", o.threads, "threads (0 = all)");
  CLI11_PARSE(app, argc, argv);
  interslice::QuietDicomToolkitLogging();
  interslice::eval::SetItkThreads(o.threads);
  const absl::Status status = interslice::eval::Run(o);
  if (!status.ok()) {
    std::fprintf(stderr, "%s\n", status.ToString().c_str());
    return 1;
  }
  return 0;
}

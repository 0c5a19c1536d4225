#include "core/morph/intensity_morph.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <exception>
#include <mutex>
#include <optional>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/morph/intensity_morph_internal.h"
#include "core/morph/morph_internal.h"
#include "itkImage.h"
#include "itkSmoothingRecursiveGaussianImageFilter.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {
namespace intensity_morph_internal {

// Gaussian smoothing (ITK's recursive Gaussian, sigma in pixels) of an
// mx*my plane.
absl::StatusOr<std::vector<float>> Smooth(const std::vector<float>& in,
                                          int64_t mx, int64_t my,
                                          double sigma) {
  using Image = itk::Image<float, 2>;
  // The recursive filter needs at least 4 pixels per axis.
  if (mx < 4 || my < 4) return in;
  try {
    Image::Pointer image = Image::New();
    Image::RegionType region;
    region.SetSize({static_cast<itk::SizeValueType>(mx),
                    static_cast<itk::SizeValueType>(my)});
    image->SetRegions(region);
    image->Allocate();
    std::copy(in.begin(), in.end(), image->GetBufferPointer());
    auto filter =
        itk::SmoothingRecursiveGaussianImageFilter<Image, Image>::New();
    filter->SetInput(image);
    filter->SetSigma(sigma);
    filter->SetNumberOfWorkUnits(1);
    filter->Update();
    const float* out = filter->GetOutput()->GetBufferPointer();
    return std::vector<float>(out, out + mx * my);
  } catch (const std::exception& e) {
    return absl::InternalError(
        absl::StrCat("intensity morph: ITK smoothing: ", e.what()));
  }
}

}  // namespace intensity_morph_internal

namespace {

using intensity_morph_internal::GapCounts;
using intensity_morph_internal::GapRegistration;
using intensity_morph_internal::KeySlices;
using intensity_morph_internal::Placement;
using intensity_morph_internal::Ramp;
using intensity_morph_internal::RegistrationLattice;
using intensity_morph_internal::Smooth;
using intensity_morph_internal::WriteGapSlices;
using morph_internal::Sample;

// Closer than this to a key slice counts as on it: an exact copy (as
// ResampleSourceSlices).
constexpr double kOnSlice = 1e-4;  // mm

// The pair check's noise unit is at least this fraction of the key slices'
// robust range (their 1st to 99th percentile): 2.5 HU on a CT head.
constexpr double kNoiseFloor = 1e-3;

double Dot(const Vec3& a, const Vec3& b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

absl::Status ValidateIntensityOptions(const IntensityMorphOptions& o) {
  if (o.registration != IntensityRegistration::kGrey &&
      o.registration != IntensityRegistration::kDistanceMaps)
    return absl::InvalidArgumentError("intensity morph: unknown registration");
  if (o.values != MorphValues::kLinear &&
      o.values != MorphValues::kCatmullRom &&
      o.values != MorphValues::kSmoothstep &&
      o.values != MorphValues::kMonotone)
    return absl::InvalidArgumentError(
        "intensity morph: unknown value interpolation");
  if (!(o.grey_scale > 0) || !std::isfinite(o.grey_scale))
    return absl::InvalidArgumentError(
        "intensity morph: grey_scale must be > 0");
  if (!std::isfinite(o.gain_low) || !std::isfinite(o.gain_high) ||
      !(o.gain_high > o.gain_low))
    return absl::InvalidArgumentError(
        "intensity morph: need gain_low < gain_high");
  if (!(o.ratio_low >= 0) || !(o.ratio_high > o.ratio_low) ||
      !std::isfinite(o.ratio_high))
    return absl::InvalidArgumentError(
        "intensity morph: need 0 <= ratio_low < ratio_high");
  if (!(o.residual_sigma_px > 0) || !std::isfinite(o.residual_sigma_px))
    return absl::InvalidArgumentError(
        "intensity morph: residual_sigma_px must be > 0");
  if (!(o.min_jacobian > 0 && o.min_jacobian < 1))
    return absl::InvalidArgumentError(
        "intensity morph: min_jacobian must be in (0, 1)");
  if (!(o.pair_tolerance_noise >= 0) || !std::isfinite(o.pair_tolerance_noise))
    return absl::InvalidArgumentError(
        "intensity morph: pair_tolerance_noise must be >= 0");
  if (!(o.pair_static_noise >= 0) || !std::isfinite(o.pair_static_noise))
    return absl::InvalidArgumentError(
        "intensity morph: pair_static_noise must be >= 0");
  if (!(o.pair_sigma_px > 0) || !std::isfinite(o.pair_sigma_px))
    return absl::InvalidArgumentError(
        "intensity morph: pair_sigma_px must be > 0");
  if (!(o.max_gap_ratio >= 1) || !std::isfinite(o.max_gap_ratio))
    return absl::InvalidArgumentError(
        "intensity morph: max_gap_ratio must be >= 1");
  return absl::OkStatus();
}

// OK when `target` has the in-plane lattice of `image` (the check of
// ResampleSourceSlices, whose contract this function shares).
absl::Status CheckInPlaneGrid(const Grid& image, const Grid& target) {
  for (int a = 0; a < 2; ++a) {
    if (image.size[a] != target.size[a] ||
        std::abs(image.spacing[a] - target.spacing[a]) >
            1e-6 * std::max(1.0, image.spacing[a])) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "intensity morph: target grid %s does not share the in-plane grid "
          "of the key slices %s",
          target.DebugString(), image.DebugString()));
    }
  }
  for (int i = 0; i < 9; ++i) {
    if (std::abs(image.direction[i] - target.direction[i]) > 1e-4) {
      return absl::InvalidArgumentError(
          "intensity morph: target grid direction differs from the key "
          "slices'");
    }
  }
  const Vec3 n = image.Axis(2);
  Vec3 offset;
  for (int c = 0; c < 3; ++c) offset[c] = target.origin[c] - image.origin[c];
  const double along = Dot(offset, n);
  double in_plane = 0;
  for (int c = 0; c < 3; ++c) {
    in_plane += (offset[c] - along * n[c]) * (offset[c] - along * n[c]);
  }
  if (std::sqrt(in_plane) > 1e-3) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "intensity morph: target grid origin is %.4f mm off the key slices' "
        "in-plane grid",
        std::sqrt(in_plane)));
  }
  return absl::OkStatus();
}

// The q-quantile (q in [0, 1]) of the non-padding values of two planes,
// from every `stride`-th pixel; nullopt if there are none.
std::optional<float> PairQuantile(const float* a, const float* b, int64_t plane,
                                  std::optional<float> padding, double q,
                                  int64_t stride, std::vector<float>& scratch) {
  scratch.clear();
  for (const float* s : {a, b}) {
    for (int64_t v = 0; v < plane; v += stride) {
      if (padding.has_value() && s[v] == *padding) continue;
      scratch.push_back(s[v]);
    }
  }
  if (scratch.empty()) return std::nullopt;
  const size_t index = std::min(
      scratch.size() - 1, static_cast<size_t>(q * (scratch.size() - 1) + 0.5));
  std::nth_element(scratch.begin(), scratch.begin() + index, scratch.end());
  return scratch[index];
}

// Block mean by d (partial blocks averaged over what exists), as the demons'
// own downsampling (morph.cc ClipAndShrink).
std::vector<float> Shrink(const std::vector<float>& in, int64_t nx, int64_t ny,
                          int d, int64_t mx, int64_t my) {
  std::vector<float> out(mx * my, 0.0f);
  std::vector<int> count(mx * my, 0);
  for (int64_t j = 0; j < ny; ++j)
    for (int64_t i = 0; i < nx; ++i) {
      const int64_t c = (i / d) + mx * (j / d);
      out[c] += in[i + nx * j];
      ++count[c];
    }
  for (int64_t c = 0; c < mx * my; ++c) out[c] /= static_cast<float>(count[c]);
  return out;
}

// The noise of a pair of neighbouring key slices, from the data alone: the
// robust scale of their difference, 1.4826 median |d - median d| over the
// pixels where neither is padding (the median absolute deviation, Hampel
// 1974, J. Am. Stat. Assoc. 69(346); Rousseeuw and Croux 1993, 88(424)),
// every `stride`-th pixel. Where the tissue does not change between the two
// slices (most of a slice) d is their noise; edges and changing anatomy are
// a minority the median ignores. Not Immerkaer's Laplacian estimate
// (Computer Vision and Image Understanding 64(2), 1996): it assumes white
// noise and measured 0.7 HU on the thin CT phantom, whose reconstruction
// kernel correlates the noise (the slices' differences in homogeneous
// tissue: 6 HU). Units: the slices' own (HU, MR's arbitrary units); 0 when
// no pixel is left.
double PairNoiseScale(const float* a, const float* b, int64_t plane,
                      std::optional<float> padding, int64_t stride) {
  std::vector<float> d;
  d.reserve(static_cast<size_t>(plane / stride + 1));
  for (int64_t v = 0; v < plane; v += stride) {
    if (padding.has_value() && (a[v] == *padding || b[v] == *padding)) continue;
    d.push_back(b[v] - a[v]);
  }
  if (d.empty()) return 0;
  const size_t middle = d.size() / 2;
  std::nth_element(d.begin(), d.begin() + middle, d.end());
  const float median = d[middle];
  for (float& x : d) x = std::abs(x - median);
  std::nth_element(d.begin(), d.begin() + middle, d.end());
  return 1.4826 * d[middle];
}

// b(y) = -u(y + b(y)) by fixed-point iteration on the coarse lattice (Chen
// et al. 2008); converges where |grad u| < 1, i.e. where u does not fold
// (where it does, the fold weight falls back anyway).
CoarseDisplacement InvertField(const CoarseDisplacement& u) {
  CoarseDisplacement b = u;
  const double half = (u.downsample - 1) / 2.0;
  for (int64_t c = 0; c < u.mx * u.my; ++c) {
    b.ux[c] = -u.ux[c];
    b.uy[c] = -u.uy[c];
  }
  constexpr int kIterations = 20;
  for (int it = 0; it < kIterations; ++it) {
    for (int64_t cj = 0; cj < u.my; ++cj)
      for (int64_t ci = 0; ci < u.mx; ++ci) {
        const int64_t c = ci + u.mx * cj;
        const double y_x = ci * u.downsample + half;
        const double y_y = cj * u.downsample + half;
        // Fields are stored in coarse pixels; Sample works in fine ones.
        float vx = 0, vy = 0;
        u.Sample(y_x + b.ux[c] * u.downsample, y_y + b.uy[c] * u.downsample, vx,
                 vy);
        b.ux[c] = -vx / u.downsample;
        b.uy[c] = -vy / u.downsample;
      }
  }
  return b;
}

// Smallest det(I + t grad u) over t in [0, 1] at every coarse pixel (grad u
// by central differences, one-sided at the border; u in coarse pixels per
// coarse pixel is the same ratio as in fine ones).
std::vector<float> MinJacobian(const CoarseDisplacement& u) {
  const int64_t mx = u.mx, my = u.my;
  std::vector<float> out(mx * my, 1.0f);
  auto diff = [&](const std::vector<float>& f, int64_t i, int64_t j, int axis) {
    const int64_t n = axis == 0 ? mx : my;
    const int64_t c = axis == 0 ? i : j;
    if (n < 2) return 0.0;
    const int64_t lo = std::max<int64_t>(0, c - 1);
    const int64_t hi = std::min<int64_t>(n - 1, c + 1);
    const int64_t a = axis == 0 ? lo + mx * j : i + mx * lo;
    const int64_t b = axis == 0 ? hi + mx * j : i + mx * hi;
    return (f[b] - f[a]) / static_cast<double>(hi - lo);
  };
  for (int64_t j = 0; j < my; ++j)
    for (int64_t i = 0; i < mx; ++i) {
      const double axx = diff(u.ux, i, j, 0), axy = diff(u.ux, i, j, 1);
      const double ayx = diff(u.uy, i, j, 0), ayy = diff(u.uy, i, j, 1);
      // det(I + t A) = 1 + t tr(A) + t^2 det(A): a parabola in t.
      const double tr = axx + ayy, det = axx * ayy - axy * ayx;
      double lowest = std::min(1.0, 1.0 + tr + det);
      if (det > 0) {
        const double t = -tr / (2 * det);
        if (t > 0 && t < 1) lowest = std::min(lowest, 1 + t * tr + t * t * det);
      }
      out[i + mx * j] = static_cast<float>(lowest);
    }
  return out;
}

// Whether the gaps are registered on the caller's distance maps.
bool RegistersDistanceMaps(const IntensityMorphOptions& options) {
  return options.register_slices &&
         options.registration == IntensityRegistration::kDistanceMaps;
}

// INVALID_ARGUMENT for inputs MorphIntensity refuses (intensity_morph.h):
// the first one found, options before grids before positions.
absl::Status ValidateMorphInputs(const Volume<float>& image,
                                 const std::vector<double>& positions_mm,
                                 const Grid& target,
                                 const Volume<float>* distance_maps,
                                 const IntensityMorphOptions& options) {
  INTERSLICE_RETURN_IF_ERROR(ValidateIntensityOptions(options));
  if (options.register_slices) {
    INTERSLICE_RETURN_IF_ERROR(ValidateMorphOptions(options.demons));
  }
  if (absl::Status status = image.grid.Validate(); !status.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat("intensity morph: key slices grid: ", status.message()));
  }
  if (static_cast<int64_t>(image.data.size()) != image.grid.VoxelCount()) {
    return absl::InvalidArgumentError(
        "intensity morph: key slices' voxel count does not match their grid");
  }
  if (absl::Status status = target.Validate(); !status.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat("intensity morph: target grid: ", status.message()));
  }
  const int64_t slices = image.grid.size[2];
  if (static_cast<int64_t>(positions_mm.size()) != slices) {
    return absl::InvalidArgumentError(
        absl::StrFormat("intensity morph: %d slice positions for %d key slices",
                        positions_mm.size(), slices));
  }
  for (int64_t s = 0; s < slices; ++s) {
    if (!std::isfinite(positions_mm[s]) ||
        (s > 0 && !(positions_mm[s] > positions_mm[s - 1]))) {
      return absl::InvalidArgumentError(
          "intensity morph: key slice positions must be finite and strictly "
          "increasing");
    }
  }
  if (RegistersDistanceMaps(options) &&
      (distance_maps == nullptr ||
       distance_maps->grid.size != image.grid.size ||
       distance_maps->data.size() != image.data.size())) {
    return absl::InvalidArgumentError(
        "intensity morph: registration by distance maps needs one map per key "
        "slice on the key slices' grid");
  }
  return CheckInPlaneGrid(image.grid, target);
}

// The key slices of `image` at `positions_mm` (validated), with their gaps.
KeySlices DescribeKeySlices(const Volume<float>& image,
                            const std::vector<double>& positions_mm,
                            std::optional<float> pixel_padding) {
  KeySlices keys;
  keys.values = image.data.data();
  keys.nx = image.grid.size[0];
  keys.ny = image.grid.size[1];
  keys.plane = keys.nx * keys.ny;
  keys.gaps = image.grid.size[2] - 1;
  keys.padding = pixel_padding;
  keys.gap_mm.resize(std::max<int64_t>(0, keys.gaps));
  for (int64_t s = 0; s < keys.gaps; ++s)
    keys.gap_mm[s] = positions_mm[s + 1] - positions_mm[s];
  return keys;
}

// The median of the gaps, mm (0 without a gap).
double MedianGapMm(const std::vector<double>& gap_mm) {
  const int64_t gaps = static_cast<int64_t>(gap_mm.size());
  double median_gap = 0;
  if (gaps > 0) {
    std::vector<double> sorted = gap_mm;
    std::nth_element(sorted.begin(), sorted.begin() + gaps / 2, sorted.end());
    median_gap = sorted[gaps / 2];
  }
  return median_gap;
}

// What the gaps running in parallel share: the first failure, whether
// cancellation was seen, and the lock around progress reports.
class ParallelGaps {
 public:
  explicit ParallelGaps(const ComputeContext& context) : context_(context) {}

  // The gaps run in parallel, but ComputeContext::Report must never be
  // called concurrently (core/common/compute.h: a worker process writes each
  // report as a frame of its protocol, and two at once corrupt it): one lock.
  void Report(double fraction) {
    std::lock_guard<std::mutex> lock(report_mutex_);
    context_.Report({.stage = "intensity", .fraction = fraction});
  }
  // Keeps the first failure.
  void Fail(absl::Status status) {
    std::lock_guard<std::mutex> lock(failure_mutex_);
    if (failure_.ok()) failure_ = std::move(status);
  }
  // False once the context is cancelled (and from then on without asking it
  // again).
  bool Poll() {
    if (cancelled_.load()) return false;
    if (!context_.CheckCancelled().ok()) {
      cancelled_.store(true);
      return false;
    }
    return true;
  }
  bool Cancelled() const { return cancelled_.load(); }
  // The first failure; read once the gaps are done.
  const absl::Status& Failure() const { return failure_; }

 private:
  const ComputeContext& context_;
  std::atomic<bool> cancelled_{false};
  absl::Status failure_;
  std::mutex failure_mutex_;
  std::mutex report_mutex_;
};

// The zero field on the registration lattice.
void ZeroField(const KeySlices& keys, const RegistrationLattice& lattice,
               CoarseDisplacement& f) {
  f.nx = keys.nx;
  f.ny = keys.ny;
  f.mx = lattice.mx;
  f.my = lattice.my;
  f.downsample = lattice.d;
  f.ux.assign(lattice.mx * lattice.my, 0.0f);
  f.uy.assign(lattice.mx * lattice.my, 0.0f);
}

// What the demons register for a gap: the registration images, the unit of
// their residual and the demons' settings for them.
struct RegistrationImages {
  std::vector<float> n0, n1;
  double unit = 1;
  MorphOptions demons;
};

// IntensityRegistration::kDistanceMaps: the maps of key slices s and s+1,
// clipped to +-clip_mm as StackMorph registers them.
RegistrationImages ClippedDistanceMaps(const Volume<float>& distance_maps,
                                       int64_t s, int64_t plane,
                                       const MorphOptions& demons) {
  RegistrationImages images;
  images.n0.resize(plane);
  images.n1.resize(plane);
  images.demons = demons;
  const float* m0 = distance_maps.data.data() + s * plane;
  const float* m1 = m0 + plane;
  const float clip = static_cast<float>(images.demons.clip_mm);
  for (int64_t v = 0; v < plane; ++v) {
    images.n0[v] = std::clamp(m0[v], -clip, clip);
    images.n1[v] = std::clamp(m1[v], -clip, clip);
  }
  images.unit = 2 * images.demons.clip_mm;
  return images;
}

// IntensityRegistration::kGrey: the grey images g0, g1 with the pair's
// robust range mapped onto [0, grey_scale]; nullopt when the gap cannot be
// registered.
std::optional<RegistrationImages> NormalisedGreyImages(
    const float* g0, const float* g1, int64_t plane,
    std::optional<float> padding, const IntensityMorphOptions& options) {
  std::vector<float> scratch;
  const int64_t stride = std::max<int64_t>(1, plane / 65536);
  // A slice without contrast of its own (constant, or all padding)
  // gives the demons nothing to follow: the gap cannot be registered.
  for (const float* slice : {g0, g1}) {
    const std::optional<float> low =
        PairQuantile(slice, slice, plane, padding, 0.01, stride, scratch);
    const std::optional<float> high =
        PairQuantile(slice, slice, plane, padding, 0.99, stride, scratch);
    if (!low.has_value() || !(*high > *low)) return std::nullopt;
  }
  const std::optional<float> lo =
      PairQuantile(g0, g1, plane, padding, 0.01, stride, scratch);
  const std::optional<float> hi =
      PairQuantile(g0, g1, plane, padding, 0.99, stride, scratch);
  RegistrationImages images;
  images.n0.resize(plane);
  images.n1.resize(plane);
  images.demons = options.demons;
  const double scale = options.grey_scale / (*hi - *lo);
  const float top = static_cast<float>(options.grey_scale);
  for (int64_t v = 0; v < plane; ++v) {
    // Padding (outside the scanned field) reads as the bottom of the
    // range, like air.
    const bool pad0 = padding.has_value() && g0[v] == *padding;
    const bool pad1 = padding.has_value() && g1[v] == *padding;
    images.n0[v] =
        pad0 ? 0.0f
             : std::clamp(static_cast<float>((g0[v] - *lo) * scale), 0.0f, top);
    images.n1[v] =
        pad1 ? 0.0f
             : std::clamp(static_cast<float>((g1[v] - *lo) * scale), 0.0f, top);
  }
  images.demons.clip_mm = options.grey_scale;  // already within [0, scale]
  images.unit = options.grey_scale;
  return images;
}

// The noise of the gap's key slices and the pair check's unit.
void EstimatePairNoise(const float* g0, const float* g1, int64_t plane,
                       std::optional<float> padding, GapRegistration& g) {
  const int64_t stride = std::max<int64_t>(1, plane / 262144);
  g.noise_sigma = PairNoiseScale(g0, g1, plane, padding, stride);
  // The pair check's unit: the noise, but at least kNoiseFloor of the
  // pair's robust range (noise-free images still differ by their
  // bilinear interpolation error).
  std::vector<float> scratch;
  const std::optional<float> lo =
      PairQuantile(g0, g1, plane, padding, 0.01, stride, scratch);
  const std::optional<float> hi =
      PairQuantile(g0, g1, plane, padding, 0.99, stride, scratch);
  const double range = lo.has_value() ? *hi - *lo : 0.0;
  g.pair_unit = std::max(g.noise_sigma, kNoiseFloor * range);
}

// The fallback weight w_residual w_fold of a registered gap (g.forward set)
// on the registration lattice, and where its key slices differ.
absl::Status ComputeFallbackWeights(const RegistrationImages& images,
                                    const KeySlices& keys,
                                    const RegistrationLattice& lattice,
                                    const IntensityMorphOptions& options,
                                    GapRegistration& g) {
  const int64_t nx = keys.nx, ny = keys.ny;
  const int d = lattice.d;
  const int64_t mx = lattice.mx, my = lattice.my;
  // Residuals on the registration lattice, before and after.
  const std::vector<float> c0 = Shrink(images.n0, nx, ny, d, mx, my);
  const std::vector<float> c1 = Shrink(images.n1, nx, ny, d, mx, my);
  std::vector<float> before(mx * my), after(mx * my);
  for (int64_t cj = 0; cj < my; ++cj)
    for (int64_t ci = 0; ci < mx; ++ci) {
      const int64_t c = ci + mx * cj;
      before[c] = std::abs(c1[c] - c0[c]);
      // The field is in coarse pixels: the lattice the residual is on.
      const double x = ci + g.forward.ux[c];
      const double y = cj + g.forward.uy[c];
      after[c] = std::abs(Sample(c1.data(), mx, my, x, y) - c0[c]);
    }
  absl::StatusOr<std::vector<float>> r_lin =
      Smooth(before, mx, my, options.residual_sigma_px);
  absl::StatusOr<std::vector<float>> r_reg =
      Smooth(after, mx, my, options.residual_sigma_px);
  if (!r_lin.ok() || !r_reg.ok()) {
    return r_lin.ok() ? r_reg.status() : r_lin.status();
  }
  const std::vector<float> jacobian = MinJacobian(g.forward);
  const double unit = images.unit;
  g.changing.assign(mx * my, 0);
  for (int64_t c = 0; c < mx * my; ++c) {
    const double reg_res = (*r_reg)[c] / unit, lin_res = (*r_lin)[c] / unit;
    // The motion is used where it explains the key slices' difference:
    // not in unchanging tissue (whose noise it would only move around),
    // not where no correspondence was found (large residual left).
    const double explained =
        1.0 - Ramp((reg_res / std::max(lin_res, 1e-12) - options.ratio_low) /
                   (options.ratio_high - options.ratio_low));
    const double w_residual =
        explained * Ramp((lin_res - reg_res - options.gain_low) /
                         (options.gain_high - options.gain_low));
    const double w_fold =
        Ramp((jacobian[c] - options.min_jacobian) / options.min_jacobian);
    g.weight[c] = static_cast<float>(w_residual * w_fold);
    g.changing[c] = lin_res >= options.gain_high ? 1 : 0;
  }
  return absl::OkStatus();
}

// The mean's sum and the largest of the gap's forward displacement, mm
// (in-plane spacing sx, sy).
void AddDisplacementStatistics(const RegistrationLattice& lattice, double sx,
                               double sy, GapRegistration& g) {
  for (int64_t c = 0; c < lattice.mx * lattice.my; ++c) {
    const double len =
        lattice.d * std::hypot(g.forward.ux[c] * sx, g.forward.uy[c] * sy);
    g.displacement_sum_mm += len;
    g.displacement_max_mm = std::max(g.displacement_max_mm, len);
  }
}

// Phase 1 for gap s (between key slices s and s+1): its coarse fields and
// fallback weight into `g`. `distance_maps`: the caller's maps when the gaps
// are registered on them, else null. A gap that cannot be registered keeps
// zero fields and weight (it falls back entirely). Errors: the demons' and
// ITK's smoothing.
absl::Status RegisterGap(const KeySlices& keys, int64_t s, double median_gap,
                         const Volume<float>* distance_maps,
                         const Vec3& spacing,
                         const RegistrationLattice& lattice,
                         const IntensityMorphOptions& options,
                         GapRegistration& g) {
  ZeroField(keys, lattice, g.forward);
  ZeroField(keys, lattice, g.backward);
  g.weight.assign(lattice.mx * lattice.my, 0.0f);
  if (!options.register_slices) {
    // No registration asked for: the values are interpolated in place and
    // nothing falls back (w = 1).
    std::fill(g.weight.begin(), g.weight.end(), 1.0f);
    g.registered = true;
    return absl::OkStatus();
  }
  if (keys.gap_mm[s] > options.max_gap_ratio * median_gap)
    return absl::OkStatus();  // missing block
  const float* g0 = keys.Slice(s);
  const float* g1 = keys.Slice(s + 1);
  // The registration images and the unit of their residual.
  std::optional<RegistrationImages> images =
      distance_maps != nullptr
          ? ClippedDistanceMaps(*distance_maps, s, keys.plane, options.demons)
          : NormalisedGreyImages(g0, g1, keys.plane, keys.padding, options);
  if (!images.has_value()) return absl::OkStatus();
  EstimatePairNoise(g0, g1, keys.plane, keys.padding, g);
  INTERSLICE_ASSIGN_OR_RETURN(
      g.forward, RegisterSlicesCoarse(images->n0.data(), images->n1.data(),
                                      keys.nx, keys.ny, images->demons));
  if (options.backward_fields) g.backward = InvertField(g.forward);
  INTERSLICE_RETURN_IF_ERROR(
      ComputeFallbackWeights(*images, keys, lattice, options, g));
  AddDisplacementStatistics(lattice, spacing[0], spacing[1], g);
  g.coarse_pixels = lattice.mx * lattice.my;
  g.registered = true;
  return absl::OkStatus();
}

// Where the output slices fall: per output slice its Placement, and per gap
// the output slices strictly inside it, in order.
struct OutputSlicePlan {
  std::vector<Placement> place;
  std::vector<std::vector<int64_t>> gap_slices;
};

OutputSlicePlan PlaceOutputSlices(const Grid& target,
                                  const std::vector<double>& positions_mm,
                                  int64_t gaps) {
  const int64_t slices = static_cast<int64_t>(positions_mm.size());
  const int64_t nz = target.size[2];
  const Vec3 n = target.Axis(2);
  const double reach = 0.5 * target.spacing[2] + 1e-6;
  OutputSlicePlan plan;
  plan.place.resize(nz);
  plan.gap_slices.resize(std::max<int64_t>(0, gaps));
  for (int64_t k = 0; k < nz; ++k) {
    const double p =
        Dot(target.IndexToPhysical({0, 0, static_cast<double>(k)}), n);
    const int64_t upper =
        std::lower_bound(positions_mm.begin(), positions_mm.end(), p) -
        positions_mm.begin();
    Placement& pl = plan.place[k];
    if (upper < slices && positions_mm[upper] - p <= kOnSlice) {
      pl.a = upper;
    } else if (upper > 0 && p - positions_mm[upper - 1] <= kOnSlice) {
      pl.a = upper - 1;
    } else if (upper == 0) {
      if (positions_mm[0] - p <= reach) pl.a = 0;
    } else if (upper == slices) {
      if (p - positions_mm[slices - 1] <= reach) pl.a = slices - 1;
    } else {
      pl.a = upper - 1;
      pl.b = upper;
      pl.t =
          (p - positions_mm[pl.a]) / (positions_mm[pl.b] - positions_mm[pl.a]);
      plan.gap_slices[pl.a].push_back(k);
    }
  }
  return plan;
}

// The value of output slices beyond the reach of the key slices: the
// padding if given, else the image's minimum (as ResampleSourceSlices).
float OutsideValue(const Volume<float>& image, std::optional<float> padding) {
  return padding.has_value()
             ? *padding
             : (image.data.empty()
                    ? 0.0f
                    : *std::min_element(image.data.begin(), image.data.end()));
}

// The output slices that are not inserted: copies of a key slice, or the
// outside value.
void CopyKeyAndOutsideSlices(const std::vector<Placement>& place,
                             const KeySlices& keys, float outside,
                             Volume<float>& out) {
  const int64_t plane = keys.plane;
  for (int64_t k = 0; k < static_cast<int64_t>(place.size()); ++k) {
    const Placement& pl = place[k];
    float* dst = out.data.data() + k * plane;
    if (pl.a < 0) {
      std::fill(dst, dst + plane, outside);
    } else if (pl.b < 0) {
      std::copy(keys.Slice(pl.a), keys.Slice(pl.a + 1), dst);
    }
  }
}

// The statistics over every gap, in gap order.
void SummariseStatistics(const std::vector<GapRegistration>& reg,
                         const std::vector<int64_t>& inserted_count,
                         const std::vector<int64_t>& fallback_count,
                         IntensityMorphStatistics& stats) {
  double displacement_sum = 0, noise_sum = 0;
  int64_t displacement_pixels = 0, noise_gaps = 0;
  for (size_t s = 0; s < reg.size(); ++s) {
    if (reg[s].coarse_pixels > 0) {
      noise_sum += reg[s].noise_sigma;
      ++noise_gaps;
    }
    stats.inserted_voxels += inserted_count[s];
    stats.fallback_voxels += fallback_count[s];
    if (!reg[s].registered) ++stats.gaps_not_registered;
    displacement_sum += reg[s].displacement_sum_mm;
    displacement_pixels += reg[s].coarse_pixels;
    stats.max_displacement_mm =
        std::max(stats.max_displacement_mm, reg[s].displacement_max_mm);
  }
  stats.mean_displacement_mm =
      displacement_pixels > 0 ? displacement_sum / displacement_pixels : 0;
  stats.noise_sigma = noise_gaps > 0 ? noise_sum / noise_gaps : 0;
  stats.fallback_fraction =
      stats.inserted_voxels > 0
          ? static_cast<double>(stats.fallback_voxels) / stats.inserted_voxels
          : 0;
}

}  // namespace

absl::StatusOr<MorphedIntensity> MorphIntensity(
    const Volume<float>& image, const std::vector<double>& positions_mm,
    const Grid& target, std::optional<float> pixel_padding,
    const Volume<float>* distance_maps, const IntensityMorphOptions& options,
    const ComputeContext& context) {
  INTERSLICE_RETURN_IF_ERROR(
      ValidateMorphInputs(image, positions_mm, target, distance_maps, options));
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  const KeySlices keys = DescribeKeySlices(image, positions_mm, pixel_padding);
  const int64_t gaps = keys.gaps;
  MorphedIntensity result;
  IntensityMorphStatistics& stats = result.statistics;
  stats.gaps = static_cast<int>(std::max<int64_t>(0, gaps));
  const double median_gap = MedianGapMm(keys.gap_mm);

  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  ParallelGaps parallel(context);

  // Phase 1: register every gap (coarse fields and fallback weights).
  std::vector<GapRegistration> reg(std::max<int64_t>(0, gaps));
  RegistrationLattice lattice;
  lattice.d = options.demons.downsample;
  lattice.mx = (keys.nx + lattice.d - 1) / lattice.d;
  lattice.my = (keys.ny + lattice.d - 1) / lattice.d;
  const Volume<float>* maps_to_register =
      RegistersDistanceMaps(options) ? distance_maps : nullptr;
  if (gaps > 0) {
    arena.execute([&] {
      tbb::parallel_for(int64_t{0}, gaps, [&](int64_t s) {
        if (parallel.Poll()) {
          absl::Status status =
              RegisterGap(keys, s, median_gap, maps_to_register,
                          image.grid.spacing, lattice, options, reg[s]);
          if (!status.ok()) parallel.Fail(std::move(status));
        }
        parallel.Report(0.0);
      });
    });
  }
  if (parallel.Cancelled()) return context.CheckCancelled();
  if (!parallel.Failure().ok()) return parallel.Failure();

  // Phase 2: the output slices, grouped by the gap (or key slice) they fall
  // in.
  Volume<float>& out = result.values;
  out.grid = target;
  const int64_t nz = target.size[2];
  out.data.resize(static_cast<size_t>(keys.plane * nz));
  const float outside = OutsideValue(image, pixel_padding);
  const OutputSlicePlan plan = PlaceOutputSlices(target, positions_mm, gaps);
  CopyKeyAndOutsideSlices(plan.place, keys, outside, out);

  std::vector<int64_t> fallback_count(std::max<int64_t>(0, gaps), 0);
  std::vector<int64_t> inserted_count(std::max<int64_t>(0, gaps), 0);
  if (gaps > 0) {
    arena.execute([&] {
      tbb::parallel_for(int64_t{0}, gaps, [&](int64_t s) {
        // A gap without output slices is not polled.
        if (!plan.gap_slices[s].empty() && parallel.Poll()) {
          absl::StatusOr<GapCounts> counts =
              WriteGapSlices(keys, reg, s, plan.gap_slices[s], plan.place,
                             lattice, options, out);
          if (counts.ok()) {
            fallback_count[s] = counts->fallbacks;
            inserted_count[s] = counts->inserted;
          } else {
            parallel.Fail(counts.status());
          }
        }
        parallel.Report(0.5);
      });
    });
  }
  if (parallel.Cancelled()) return context.CheckCancelled();
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  SummariseStatistics(reg, inserted_count, fallback_count, stats);
  return result;
}

}  // namespace interslice

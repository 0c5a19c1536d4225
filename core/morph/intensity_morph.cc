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
#include "core/morph/morph_internal.h"
#include "itkImage.h"
#include "itkSmoothingRecursiveGaussianImageFilter.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {
namespace {

using morph_internal::MonotoneTangent;
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

// What phase 1 keeps of a gap: coarse forward and backward fields and the
// fallback weight on the registration lattice.
struct GapRegistration {
  bool registered = false;
  CoarseDisplacement forward, backward;
  std::vector<float> weight;  // mx*my, in [0, 1]
  // mx*my: 1 where the key slices differ (r_lin >= gain_high); empty when
  // the gap was not registered (everything counts) or not asked to be.
  std::vector<uint8_t> changing;
  double displacement_sum_mm = 0, displacement_max_mm = 0;
  int64_t coarse_pixels = 0;
  // The noise of the gap's key slices (PairNoiseScale: of their
  // difference), modality units.
  double noise_sigma = 0;
  // The pair check's tolerance per unit of pair_tolerance_noise.
  double pair_unit = 0;
};

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

inline double Ramp(double x) { return std::clamp(x, 0.0, 1.0); }

// The pair check's smoothing is cropped with this margin, in sigmas (see
// write_gap in MorphIntensity).
constexpr double kPairCropMarginSigmas = 16.0;

// A half-open box of pixels [x0, x1) x [y0, y1) of a plane; empty until a
// pixel is added.
struct PixelBox {
  int64_t x0 = 0, y0 = 0, x1 = 0, y1 = 0;
  bool Empty() const { return x1 <= x0 || y1 <= y0; }
  void Add(int64_t i, int64_t j) {
    if (Empty()) {
      x0 = i, y0 = j, x1 = i + 1, y1 = j + 1;
      return;
    }
    x0 = std::min(x0, i), y0 = std::min(y0, j);
    x1 = std::max(x1, i + 1), y1 = std::max(y1, j + 1);
  }
  // Grows the box by `margin` pixels on every side, within nx x ny.
  void Grow(int64_t margin, int64_t nx, int64_t ny) {
    x0 = std::max<int64_t>(0, x0 - margin);
    y0 = std::max<int64_t>(0, y0 - margin);
    x1 = std::min(nx, x1 + margin);
    y1 = std::min(ny, y1 + margin);
  }
  int64_t Width() const { return x1 - x0; }
  int64_t Height() const { return y1 - y0; }
  int64_t Pixels() const { return Width() * Height(); }
  bool Contains(int64_t i, int64_t j) const {
    return i >= x0 && i < x1 && j >= y0 && j < y1;
  }
  // Row-major index of plane pixel (i, j) inside the box.
  int64_t Index(int64_t i, int64_t j) const {
    return (i - x0) + Width() * (j - y0);
  }
};

// A bilinear sample that also says whether one of its (weighted) neighbours
// is the padding value.
inline float SampleUnpadded(const float* plane, int64_t nx, int64_t ny,
                            double x, double y, std::optional<float> padding,
                            bool& touched) {
  if (padding.has_value()) {
    const double cx = std::clamp(x, 0.0, static_cast<double>(nx - 1));
    const double cy = std::clamp(y, 0.0, static_cast<double>(ny - 1));
    const int64_t i0 = static_cast<int64_t>(cx), j0 = static_cast<int64_t>(cy);
    const int64_t i1 = std::min(i0 + 1, nx - 1), j1 = std::min(j0 + 1, ny - 1);
    const float pad = *padding;
    if (plane[i0 + nx * j0] == pad || plane[i1 + nx * j0] == pad ||
        plane[i0 + nx * j1] == pad || plane[i1 + nx * j1] == pad)
      touched = true;
  }
  return Sample(plane, nx, ny, x, y);
}

}  // namespace

absl::StatusOr<MorphedIntensity> MorphIntensity(
    const Volume<float>& image, const std::vector<double>& positions_mm,
    const Grid& target, std::optional<float> pixel_padding,
    const Volume<float>* distance_maps, const IntensityMorphOptions& options,
    const ComputeContext& context) {
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
  const bool by_maps =
      options.register_slices &&
      options.registration == IntensityRegistration::kDistanceMaps;
  if (by_maps && (distance_maps == nullptr ||
                  distance_maps->grid.size != image.grid.size ||
                  distance_maps->data.size() != image.data.size())) {
    return absl::InvalidArgumentError(
        "intensity morph: registration by distance maps needs one map per key "
        "slice on the key slices' grid");
  }
  INTERSLICE_RETURN_IF_ERROR(CheckInPlaneGrid(image.grid, target));
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  const int64_t nx = image.grid.size[0], ny = image.grid.size[1];
  const int64_t plane = nx * ny;
  const int64_t gaps = slices - 1;
  const float* keys = image.data.data();
  const std::optional<float> padding = pixel_padding;
  MorphedIntensity result;
  IntensityMorphStatistics& stats = result.statistics;
  stats.gaps = static_cast<int>(std::max<int64_t>(0, gaps));

  std::vector<double> gap_mm(std::max<int64_t>(0, gaps));
  for (int64_t s = 0; s < gaps; ++s)
    gap_mm[s] = positions_mm[s + 1] - positions_mm[s];
  double median_gap = 0;
  if (gaps > 0) {
    std::vector<double> sorted = gap_mm;
    std::nth_element(sorted.begin(), sorted.begin() + gaps / 2, sorted.end());
    median_gap = sorted[gaps / 2];
  }

  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  std::atomic<bool> cancelled{false};
  absl::Status failure;
  std::mutex failure_mutex;
  // The gaps run in parallel, but ComputeContext::Report must never be
  // called concurrently (core/common/compute.h: a worker process writes each
  // report as a frame of its protocol, and two at once corrupt it): one lock.
  std::mutex report_mutex;
  auto report = [&](double fraction) {
    std::lock_guard<std::mutex> lock(report_mutex);
    context.Report({.stage = "intensity", .fraction = fraction});
  };
  auto fail = [&](absl::Status status) {
    std::lock_guard<std::mutex> lock(failure_mutex);
    if (failure.ok()) failure = std::move(status);
  };
  auto poll = [&]() {
    if (cancelled.load()) return false;
    if (!context.CheckCancelled().ok()) {
      cancelled.store(true);
      return false;
    }
    return true;
  };

  // Phase 1: register every gap (coarse fields and fallback weights).
  std::vector<GapRegistration> reg(std::max<int64_t>(0, gaps));
  const int d = options.demons.downsample;
  const int64_t mx = (nx + d - 1) / d, my = (ny + d - 1) / d;
  auto register_gap = [&](int64_t s) {
    if (!poll()) return;
    GapRegistration& g = reg[s];
    auto zero = [&](CoarseDisplacement& f) {
      f.nx = nx;
      f.ny = ny;
      f.mx = mx;
      f.my = my;
      f.downsample = d;
      f.ux.assign(mx * my, 0.0f);
      f.uy.assign(mx * my, 0.0f);
    };
    zero(g.forward);
    zero(g.backward);
    g.weight.assign(mx * my, 0.0f);
    if (!options.register_slices) {
      // No registration asked for: the values are interpolated in place and
      // nothing falls back (w = 1).
      std::fill(g.weight.begin(), g.weight.end(), 1.0f);
      g.registered = true;
      return;
    }
    if (gap_mm[s] > options.max_gap_ratio * median_gap)
      return;  // missing block
    const float* g0 = keys + s * plane;
    const float* g1 = keys + (s + 1) * plane;
    // The registration images and the unit of their residual.
    std::vector<float> n0(plane), n1(plane);
    double unit = 1;
    MorphOptions demons = options.demons;
    if (by_maps) {
      const float* m0 = distance_maps->data.data() + s * plane;
      const float* m1 = m0 + plane;
      const float clip = static_cast<float>(demons.clip_mm);
      for (int64_t v = 0; v < plane; ++v) {
        n0[v] = std::clamp(m0[v], -clip, clip);
        n1[v] = std::clamp(m1[v], -clip, clip);
      }
      unit = 2 * demons.clip_mm;
    } else {
      std::vector<float> scratch;
      const int64_t stride = std::max<int64_t>(1, plane / 65536);
      // A slice without contrast of its own (constant, or all padding)
      // gives the demons nothing to follow: the gap cannot be registered.
      for (const float* slice : {g0, g1}) {
        const std::optional<float> low =
            PairQuantile(slice, slice, plane, padding, 0.01, stride, scratch);
        const std::optional<float> high =
            PairQuantile(slice, slice, plane, padding, 0.99, stride, scratch);
        if (!low.has_value() || !(*high > *low)) return;
      }
      const std::optional<float> lo =
          PairQuantile(g0, g1, plane, padding, 0.01, stride, scratch);
      const std::optional<float> hi =
          PairQuantile(g0, g1, plane, padding, 0.99, stride, scratch);
      const double scale = options.grey_scale / (*hi - *lo);
      const float top = static_cast<float>(options.grey_scale);
      for (int64_t v = 0; v < plane; ++v) {
        // Padding (outside the scanned field) reads as the bottom of the
        // range, like air.
        const bool pad0 = padding.has_value() && g0[v] == *padding;
        const bool pad1 = padding.has_value() && g1[v] == *padding;
        n0[v] = pad0 ? 0.0f
                     : std::clamp(static_cast<float>((g0[v] - *lo) * scale),
                                  0.0f, top);
        n1[v] = pad1 ? 0.0f
                     : std::clamp(static_cast<float>((g1[v] - *lo) * scale),
                                  0.0f, top);
      }
      demons.clip_mm = options.grey_scale;  // already within [0, scale]
      unit = options.grey_scale;
    }
    {
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
    absl::StatusOr<CoarseDisplacement> u =
        RegisterSlicesCoarse(n0.data(), n1.data(), nx, ny, demons);
    if (!u.ok()) {
      fail(u.status());
      return;
    }
    g.forward = *std::move(u);
    if (options.backward_fields) g.backward = InvertField(g.forward);
    // Residuals on the registration lattice, before and after.
    const std::vector<float> c0 = Shrink(n0, nx, ny, d, mx, my);
    const std::vector<float> c1 = Shrink(n1, nx, ny, d, mx, my);
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
      fail(r_lin.ok() ? r_reg.status() : r_lin.status());
      return;
    }
    const std::vector<float> jacobian = MinJacobian(g.forward);
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
    const double sx = image.grid.spacing[0], sy = image.grid.spacing[1];
    for (int64_t c = 0; c < mx * my; ++c) {
      const double len =
          d * std::hypot(g.forward.ux[c] * sx, g.forward.uy[c] * sy);
      g.displacement_sum_mm += len;
      g.displacement_max_mm = std::max(g.displacement_max_mm, len);
    }
    g.coarse_pixels = mx * my;
    g.registered = true;
  };
  if (gaps > 0) {
    arena.execute([&] {
      tbb::parallel_for(int64_t{0}, gaps, [&](int64_t s) {
        register_gap(s);
        report(0.0);
      });
    });
  }
  if (cancelled.load()) return context.CheckCancelled();
  if (!failure.ok()) return failure;

  // Phase 2: the output slices, grouped by the gap (or key slice) they fall
  // in.
  Volume<float>& out = result.values;
  out.grid = target;
  const int64_t nz = target.size[2];
  out.data.resize(static_cast<size_t>(plane * nz));
  const float outside =
      padding.has_value()
          ? *padding
          : (image.data.empty()
                 ? 0.0f
                 : *std::min_element(image.data.begin(), image.data.end()));
  const Vec3 n = target.Axis(2);
  const double reach = 0.5 * target.spacing[2] + 1e-6;
  // Per output slice: the key slice it copies (a >= 0, b < 0), the gap it
  // lies in (a = s, b = s + 1, t), or outside (a < 0).
  struct Placement {
    int64_t a = -1, b = -1;
    double t = 0;
  };
  std::vector<Placement> place(nz);
  std::vector<std::vector<int64_t>> gap_slices(std::max<int64_t>(0, gaps));
  for (int64_t k = 0; k < nz; ++k) {
    const double p =
        Dot(target.IndexToPhysical({0, 0, static_cast<double>(k)}), n);
    const int64_t upper =
        std::lower_bound(positions_mm.begin(), positions_mm.end(), p) -
        positions_mm.begin();
    Placement& pl = place[k];
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
      gap_slices[pl.a].push_back(k);
    }
  }
  for (int64_t k = 0; k < nz; ++k) {
    const Placement& pl = place[k];
    float* dst = out.data.data() + k * plane;
    if (pl.a < 0) {
      std::fill(dst, dst + plane, outside);
    } else if (pl.b < 0) {
      std::copy(keys + pl.a * plane, keys + (pl.a + 1) * plane, dst);
    }
  }

  std::vector<int64_t> fallback_count(std::max<int64_t>(0, gaps), 0);
  std::vector<int64_t> inserted_count(std::max<int64_t>(0, gaps), 0);
  auto write_gap = [&](int64_t s) {
    if (gap_slices[s].empty() || !poll()) return;
    const bool has_prev = s > 0, has_next = s + 1 < gaps;
    const double len = gap_mm[s];
    const double len_prev = has_prev ? gap_mm[s - 1] : 0;
    const double len_next = has_next ? gap_mm[s + 1] : 0;
    // Chord slopes scaled into this gap's units (morph.h).
    const double w_prev = has_prev ? len / (len_prev + len) : 0;
    const double w_next = has_next ? len / (len + len_next) : 0;
    const float* g0 = keys + s * plane;
    const float* g1 = keys + (s + 1) * plane;
    const float* gm = has_prev ? keys + (s - 1) * plane : nullptr;
    const float* gp = has_next ? keys + (s + 2) * plane : nullptr;
    // The fields this gap's slices need, at full resolution.
    const std::vector<float> u = reg[s].forward.Upsample();
    const bool backward = options.backward_fields;
    const std::vector<float> b =
        backward ? reg[s].backward.Upsample() : std::vector<float>();
    const std::vector<float> u_prev =
        has_prev ? reg[s - 1].forward.Upsample() : std::vector<float>();
    const std::vector<float> b_prev = has_prev && backward
                                          ? reg[s - 1].backward.Upsample()
                                          : std::vector<float>();
    const std::vector<float> u_next =
        has_next ? reg[s + 1].forward.Upsample() : std::vector<float>();
    const std::vector<float> b_next = has_next && backward
                                          ? reg[s + 1].backward.Upsample()
                                          : std::vector<float>();
    std::vector<float> weight(plane);
    {
      const CoarseDisplacement& f = reg[s].forward;
      const double half = (d - 1) / 2.0;
      for (int64_t j = 0; j < ny; ++j)
        for (int64_t i = 0; i < nx; ++i)
          weight[i + nx * j] = Sample(reg[s].weight.data(), f.mx, f.my,
                                      (i - half) / d, (j - half) / d);
    }
    // Where the key slices differ (the fallback statistics count there).
    std::vector<uint8_t> changing(plane, 1);
    if (!reg[s].changing.empty()) {
      for (int64_t j = 0; j < ny; ++j)
        for (int64_t i = 0; i < nx; ++i)
          changing[i + nx * j] =
              reg[s].changing[std::min<int64_t>(i / d, mx - 1) +
                              mx * std::min<int64_t>(j / d, my - 1)];
    } else if (!options.register_slices) {
      std::fill(changing.begin(), changing.end(), 0);
    }
    int64_t fallbacks = 0, inserted = 0;
    // The pair check (see the header): per pixel the squared difference of
    // the two samples the morph blends and of the two the linear blend
    // does, smoothed, and the morph's value until the check decides.
    const bool pair_check = options.pair_check && options.register_slices;
    std::vector<float> pair_morph, morph_value;
    std::vector<uint8_t> candidate;
    const double pair_tolerance =
        options.pair_tolerance_noise * reg[s].pair_unit;
    const double static_limit = options.pair_static_noise * reg[s].pair_unit;
    // The linear pair is the same two key-slice pixels for every slice of
    // the gap, so e_linear and the static weight are computed once per gap.
    // The morph's pair changes with t and is smoothed per slice, but only
    // where it can change a value: a pixel whose static weight is 0 keeps
    // w_pair = 1 whatever e_morph is, and so does one the morph does not
    // reach (weight 0). Its smoothing is therefore restricted to the box of
    // the pixels with both, grown by kPairCropMarginSigmas sigma: ITK's
    // recursive Gaussian (Deriche's 4th-order IIR) there differs from the
    // whole slice's by less than float precision (its responses decay as
    // exp(-1.5 x / sigma), e^-24 at the margin).
    std::vector<double> e_linear, static_weight;
    PixelBox pair_box;  // empty: no pixel where the check can act
    if (pair_check) {
      std::vector<float> pair_linear(plane, 0.0f);
      for (int64_t v = 0; v < plane; ++v) {
        const float lin0 = g0[v], lin1 = g1[v];
        if (padding.has_value() && (lin0 == *padding || lin1 == *padding)) {
          continue;
        }
        pair_linear[v] = (lin1 - lin0) * (lin1 - lin0);
      }
      absl::StatusOr<std::vector<float>> linear_disagreement =
          Smooth(pair_linear, nx, ny, options.pair_sigma_px);
      if (!linear_disagreement.ok()) {
        fail(linear_disagreement.status());
        return;
      }
      e_linear.resize(plane);
      static_weight.resize(plane);
      for (int64_t j = 0; j < ny; ++j)
        for (int64_t i = 0; i < nx; ++i) {
          const int64_t v = i + nx * j;
          e_linear[v] = std::sqrt(std::max(0.0f, (*linear_disagreement)[v]));
          // Static: the linear pair agrees within the noise (1 up to
          // pair_static_noise units, 0 from twice that).
          static_weight[v] = static_limit > 0
                                 ? Ramp(2.0 - e_linear[v] / static_limit)
                                 : (e_linear[v] <= 0 ? 1.0 : 0.0);
          if (static_weight[v] > 0 && weight[v] > 0) pair_box.Add(i, j);
        }
      if (!pair_box.Empty() && !options.crop_pair_check) {
        pair_box = {0, 0, nx, ny};
      } else if (!pair_box.Empty()) {
        pair_box.Grow(static_cast<int64_t>(std::ceil(kPairCropMarginSigmas *
                                                     options.pair_sigma_px)),
                      nx, ny);
      }
      if (!pair_box.Empty()) {
        pair_morph.resize(pair_box.Pixels());
        morph_value.resize(plane);
        candidate.resize(plane);
      }
    }
    const bool pair_crop = !pair_box.Empty();
    for (int64_t k : gap_slices[s]) {
      const double t = place[k].t;
      const double t2 = t * t, t3 = t2 * t;
      const double h00 = 2 * t3 - 3 * t2 + 1, h10 = t3 - 2 * t2 + t;
      const double h01 = 3 * t2 - 2 * t3, h11 = t3 - t2;
      // The backward trajectory's basis at tau = 1 - t.
      const double r = 1 - t, r2 = r * r, r3 = r2 * r;
      const double g10 = r3 - 2 * r2 + r, g01 = 3 * r2 - 2 * r3, g11 = r3 - r2;
      float* dst = out.data.data() + k * plane;
      for (int64_t j = 0; j < ny; ++j)
        for (int64_t i = 0; i < nx; ++i) {
          const int64_t v = i + nx * j;
          const float lin0 = g0[v], lin1 = g1[v];
          const bool in_pair_box = pair_crop && pair_box.Contains(i, j);
          const int64_t box_v = in_pair_box ? pair_box.Index(i, j) : 0;
          if (pair_crop) candidate[v] = 0;
          if (in_pair_box) pair_morph[box_v] = 0;
          if (padding.has_value() && (lin0 == *padding || lin1 == *padding)) {
            dst[v] = *padding;  // outside the scanned field, as linear
            continue;
          }
          if (in_pair_box) {
            const float step = lin1 - lin0;
            pair_morph[box_v] = step * step;
          }
          const double linear = (1 - t) * lin0 + t * lin1;
          const bool counted = changing[v] != 0;
          inserted += counted;
          const double w = weight[v];
          if (w <= 0) {
            dst[v] = static_cast<float>(linear);
            fallbacks += counted;
            continue;
          }
          const double u_x = u[v], u_y = u[plane + v];
          // Forward trajectory from key slice s (morph.h's cubic).
          const double vs_x = has_prev ? w_prev * (u_prev[v] + u_x) : u_x;
          const double vs_y =
              has_prev ? w_prev * (u_prev[plane + v] + u_y) : u_y;
          const double ve_x = has_next ? w_next * (u_x + u_next[v]) : u_x;
          const double ve_y =
              has_next ? w_next * (u_y + u_next[plane + v]) : u_y;
          const double x0 = i - (h10 * vs_x + h01 * u_x + h11 * ve_x);
          const double y0 = j - (h10 * vs_y + h01 * u_y + h11 * ve_y);
          double x1 = x0 + u_x, y1 = y0 + u_y;
          if (options.backward_fields) {
            // The same trajectory anchored on key slice s+1, from the
            // backward fields: b (s+1 -> s), b_next (s+2 -> s+1), b_prev
            // (s -> s-1).
            const double b_x = b[v], b_y = b[plane + v];
            const double ws_x =
                has_next ? w_next * (b_next[v] + b_x) : b_x;  // at s+1
            const double ws_y =
                has_next ? w_next * (b_next[plane + v] + b_y) : b_y;
            const double we_x = has_prev ? w_prev * (b_x + b_prev[v]) : b_x;
            const double we_y =
                has_prev ? w_prev * (b_y + b_prev[plane + v]) : b_y;
            x1 = i - (g10 * ws_x + g01 * b_x + g11 * we_x);
            y1 = j - (g10 * ws_y + g01 * b_y + g11 * we_y);
          }
          bool touched = false;
          const double a0 =
              SampleUnpadded(g0, nx, ny, x0, y0, padding, touched);
          const double a1 =
              SampleUnpadded(g1, nx, ny, x1, y1, padding, touched);
          double value = 0;
          if (options.values == MorphValues::kLinear) {
            value = (1 - t) * a0 + t * a1;
          } else if (options.values == MorphValues::kSmoothstep) {
            value = h00 * a0 + h01 * a1;
          } else {
            // Value tangents through key slices s-1 and s+2, reached by the
            // field anchored on the nearer key slice: b_prev lives on key
            // slice s (s -> s-1), u_next on key slice s+1 (s+1 -> s+2).
            double m0 = a1 - a0, m1 = a1 - a0;
            double am = 0, ap = 0;
            if (has_prev) {
              am =
                  options.backward_fields
                      ? SampleUnpadded(gm, nx, ny, x0 + b_prev[v],
                                       y0 + b_prev[plane + v], padding, touched)
                      : SampleUnpadded(gm, nx, ny, x0 - u_prev[v],
                                       y0 - u_prev[plane + v], padding,
                                       touched);
            }
            if (has_next) {
              ap = SampleUnpadded(gp, nx, ny, x1 + u_next[v],
                                  y1 + u_next[plane + v], padding, touched);
            }
            if (options.values == MorphValues::kMonotone) {
              const double slope = (a1 - a0) / len;  // per mm
              if (has_prev)
                m0 = len * MonotoneTangent((a0 - am) / len_prev, slope,
                                           len_prev, len);
              if (has_next)
                m1 = len * MonotoneTangent(slope, (ap - a1) / len_next, len,
                                           len_next);
            } else {
              if (has_prev) m0 = w_prev * (a1 - am);
              if (has_next) m1 = w_next * (ap - a0);
            }
            value = h00 * a0 + h10 * m0 + h01 * a1 + h11 * m1;
          }
          if (touched) {
            dst[v] = static_cast<float>(linear);
            fallbacks += counted;
            continue;
          }
          if (in_pair_box) {
            pair_morph[box_v] = static_cast<float>((a1 - a0) * (a1 - a0));
          }
          if (pair_crop && static_weight[v] > 0) {
            // Decided after the smoothing below.
            dst[v] = static_cast<float>(linear);
            morph_value[v] = static_cast<float>(value);
            candidate[v] = 1;
            continue;
          }
          // The pair check blends the morph's value as a float.
          if (pair_check) value = static_cast<float>(value);
          if (w < 0.5) fallbacks += counted;
          dst[v] = static_cast<float>(w * value + (1 - w) * linear);
        }
      if (!pair_crop) continue;
      absl::StatusOr<std::vector<float>> morph_disagreement =
          Smooth(pair_morph, pair_box.Width(), pair_box.Height(),
                 options.pair_sigma_px);
      if (!morph_disagreement.ok()) {
        fail(morph_disagreement.status());
        return;
      }
      for (int64_t j = pair_box.y0; j < pair_box.y1; ++j)
        for (int64_t i = pair_box.x0; i < pair_box.x1; ++i) {
          const int64_t v = i + nx * j;
          if (!candidate[v]) continue;
          const double e_morph = std::sqrt(
              std::max(0.0f, (*morph_disagreement)[pair_box.Index(i, j)]));
          // Dragged: the morph's pair disagrees by pair_tolerance_noise
          // units more than the linear pair.
          const double dragged =
              pair_tolerance > 0
                  ? Ramp((e_morph - e_linear[v]) / pair_tolerance)
                  : (e_morph > e_linear[v] ? 1.0 : 0.0);
          const double w_pair = 1.0 - static_weight[v] * dragged;
          const double w = weight[v] * w_pair;
          if (w < 0.5) fallbacks += changing[v] != 0;
          const double linear = (1 - t) * g0[v] + t * g1[v];
          dst[v] = static_cast<float>(w * morph_value[v] + (1 - w) * linear);
        }
    }
    fallback_count[s] = fallbacks;
    inserted_count[s] = inserted;
  };
  if (gaps > 0) {
    arena.execute([&] {
      tbb::parallel_for(int64_t{0}, gaps, [&](int64_t s) {
        write_gap(s);
        report(0.5);
      });
    });
  }
  if (cancelled.load()) return context.CheckCancelled();
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  double displacement_sum = 0, noise_sum = 0;
  int64_t displacement_pixels = 0, noise_gaps = 0;
  for (int64_t s = 0; s < gaps; ++s) {
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
  return result;
}

}  // namespace interslice

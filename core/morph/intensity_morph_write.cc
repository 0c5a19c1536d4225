// Phase 2 of MorphIntensity (intensity_morph.h): the inserted slices of one
// gap, each output pixel pulling its two key-slice samples along the cubic
// trajectory and blending the morph's value with the linear one by the
// fallback weight and the pair check.
#include <algorithm>
#include <cmath>
#include <optional>
#include <vector>

#include "absl/status/status.h"
#include "core/common/status_macros.h"
#include "core/morph/intensity_morph_internal.h"
#include "core/morph/morph_internal.h"

namespace interslice::intensity_morph_internal {
namespace {

using morph_internal::MonotoneTangent;
using morph_internal::Sample;

// The pair check's smoothing is cropped with this margin, in sigmas (see
// PrepareLinearPairCheck).
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

// What the inserted slices of gap s read: its key slices and those on either
// side, the gaps' lengths, and the fields of the gap and its neighbours at
// full resolution.
struct GapNeighbourhood {
  int64_t nx = 0, ny = 0, plane = 0;
  std::optional<float> padding;
  bool has_prev = false, has_next = false;
  double len = 0, len_prev = 0, len_next = 0;
  // Chord slopes scaled into this gap's units (morph.h).
  double w_prev = 0, w_next = 0;
  const float* g0 = nullptr;  // key slice s
  const float* g1 = nullptr;  // key slice s+1
  const float* gm = nullptr;  // key slice s-1, if any
  const float* gp = nullptr;  // key slice s+2, if any
  // Forward (u) and, with backward_fields, backward (b) fields of gaps s-1,
  // s and s+1 (RegisterSlices' layout: x plane, y plane).
  std::vector<float> u, b, u_prev, b_prev, u_next, b_next;
};

GapNeighbourhood GatherGapNeighbourhood(const KeySlices& keys,
                                        const std::vector<GapRegistration>& reg,
                                        int64_t s, bool backward) {
  GapNeighbourhood gap;
  gap.nx = keys.nx;
  gap.ny = keys.ny;
  gap.plane = keys.plane;
  gap.padding = keys.padding;
  gap.has_prev = s > 0;
  gap.has_next = s + 1 < keys.gaps;
  const bool has_prev = gap.has_prev, has_next = gap.has_next;
  gap.len = keys.gap_mm[s];
  gap.len_prev = has_prev ? keys.gap_mm[s - 1] : 0;
  gap.len_next = has_next ? keys.gap_mm[s + 1] : 0;
  // Chord slopes scaled into this gap's units (morph.h).
  gap.w_prev = has_prev ? gap.len / (gap.len_prev + gap.len) : 0;
  gap.w_next = has_next ? gap.len / (gap.len + gap.len_next) : 0;
  gap.g0 = keys.Slice(s);
  gap.g1 = keys.Slice(s + 1);
  gap.gm = has_prev ? keys.Slice(s - 1) : nullptr;
  gap.gp = has_next ? keys.Slice(s + 2) : nullptr;
  // The fields this gap's slices need, at full resolution.
  gap.u = reg[s].forward.Upsample();
  if (backward) gap.b = reg[s].backward.Upsample();
  if (has_prev) gap.u_prev = reg[s - 1].forward.Upsample();
  if (has_prev && backward) gap.b_prev = reg[s - 1].backward.Upsample();
  if (has_next) gap.u_next = reg[s + 1].forward.Upsample();
  if (has_next && backward) gap.b_next = reg[s + 1].backward.Upsample();
  return gap;
}

// The gap's fallback weight w = w_residual w_fold, bilinear from the
// registration lattice to every pixel.
std::vector<float> FullResolutionWeight(const GapRegistration& g,
                                        const KeySlices& keys,
                                        const RegistrationLattice& lattice) {
  const int64_t nx = keys.nx, ny = keys.ny;
  const int d = lattice.d;
  std::vector<float> weight(keys.plane);
  const CoarseDisplacement& f = g.forward;
  const double half = (d - 1) / 2.0;
  for (int64_t j = 0; j < ny; ++j)
    for (int64_t i = 0; i < nx; ++i)
      weight[i + nx * j] =
          Sample(g.weight.data(), f.mx, f.my, (i - half) / d, (j - half) / d);
  return weight;
}

// Where the key slices differ (the fallback statistics count there), per
// pixel.
std::vector<uint8_t> FullResolutionChanging(const GapRegistration& g,
                                            const KeySlices& keys,
                                            const RegistrationLattice& lattice,
                                            bool register_slices) {
  const int64_t nx = keys.nx, ny = keys.ny;
  const int d = lattice.d;
  const int64_t mx = lattice.mx, my = lattice.my;
  std::vector<uint8_t> changing(keys.plane, 1);
  if (!g.changing.empty()) {
    for (int64_t j = 0; j < ny; ++j)
      for (int64_t i = 0; i < nx; ++i)
        changing[i + nx * j] =
            g.changing[std::min<int64_t>(i / d, mx - 1) +
                       mx * std::min<int64_t>(j / d, my - 1)];
  } else if (!register_slices) {
    std::fill(changing.begin(), changing.end(), 0);
  }
  return changing;
}

// The pair check of one gap (see the header): per pixel the squared
// difference of the two samples the morph blends and of the two the linear
// blend does, smoothed, and the morph's value until the check decides.
struct PairCheck {
  // options.pair_check, and only when the slices are registered.
  bool enabled = false;
  double tolerance = 0;  // pair_tolerance_noise units
  // Per gap: sqrt of the smoothed linear pair's squared difference, and the
  // static weight (1 up to pair_static_noise units, 0 from twice that).
  std::vector<double> e_linear, static_weight;
  // The pixels whose morph pair is smoothed; empty: no pixel where the
  // check can act.
  PixelBox box;
  // Per slice: the morph pair's squared difference (box pixels), the
  // morph's value and whether the check decides the pixel (plane pixels).
  std::vector<float> pair_morph, morph_value;
  std::vector<uint8_t> candidate;

  bool Cropped() const { return !box.Empty(); }
};

// The part of the pair check that is the same for every slice of the gap:
// the linear pair, e_linear, the static weight and the box of pixels where
// the morph's pair must be smoothed.
absl::StatusOr<PairCheck> PrepareLinearPairCheck(
    const GapNeighbourhood& gap, const std::vector<float>& weight,
    double pair_unit, bool pair_check, const IntensityMorphOptions& options) {
  const int64_t nx = gap.nx, ny = gap.ny, plane = gap.plane;
  const std::optional<float>& padding = gap.padding;
  PairCheck check;
  check.enabled = pair_check;
  check.tolerance = options.pair_tolerance_noise * pair_unit;
  const double static_limit = options.pair_static_noise * pair_unit;
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
  if (!pair_check) return check;
  std::vector<float> pair_linear(plane, 0.0f);
  for (int64_t v = 0; v < plane; ++v) {
    const float lin0 = gap.g0[v], lin1 = gap.g1[v];
    if (padding.has_value() && (lin0 == *padding || lin1 == *padding)) {
      continue;
    }
    pair_linear[v] = (lin1 - lin0) * (lin1 - lin0);
  }
  INTERSLICE_ASSIGN_OR_RETURN(
      const std::vector<float> linear_disagreement,
      Smooth(pair_linear, nx, ny, options.pair_sigma_px));
  check.e_linear.resize(plane);
  check.static_weight.resize(plane);
  for (int64_t j = 0; j < ny; ++j)
    for (int64_t i = 0; i < nx; ++i) {
      const int64_t v = i + nx * j;
      check.e_linear[v] = std::sqrt(std::max(0.0f, linear_disagreement[v]));
      // Static: the linear pair agrees within the noise (1 up to
      // pair_static_noise units, 0 from twice that).
      check.static_weight[v] =
          static_limit > 0 ? Ramp(2.0 - check.e_linear[v] / static_limit)
                           : (check.e_linear[v] <= 0 ? 1.0 : 0.0);
      if (check.static_weight[v] > 0 && weight[v] > 0) check.box.Add(i, j);
    }
  if (!check.box.Empty() && !options.crop_pair_check) {
    check.box = {0, 0, nx, ny};
  } else if (!check.box.Empty()) {
    check.box.Grow(static_cast<int64_t>(std::ceil(kPairCropMarginSigmas *
                                                  options.pair_sigma_px)),
                   nx, ny);
  }
  if (!check.box.Empty()) {
    check.pair_morph.resize(check.box.Pixels());
    check.morph_value.resize(plane);
    check.candidate.resize(plane);
  }
  return check;
}

// The cubic Hermite basis at t (morph.h's trajectory and the values'
// interpolation), and the backward trajectory's at tau = 1 - t.
struct HermiteBasis {
  double t = 0;
  double h00 = 0, h10 = 0, h01 = 0, h11 = 0;
  double g10 = 0, g01 = 0, g11 = 0;
};

HermiteBasis HermiteBasisAt(double t) {
  HermiteBasis basis;
  basis.t = t;
  const double t2 = t * t, t3 = t2 * t;
  basis.h00 = 2 * t3 - 3 * t2 + 1;
  basis.h10 = t3 - 2 * t2 + t;
  basis.h01 = 3 * t2 - 2 * t3;
  basis.h11 = t3 - t2;
  // The backward trajectory's basis at tau = 1 - t.
  const double r = 1 - t, r2 = r * r, r3 = r2 * r;
  basis.g10 = r3 - 2 * r2 + r;
  basis.g01 = 3 * r2 - 2 * r3;
  basis.g11 = r3 - r2;
  return basis;
}

// Where output pixel (i, j) of a slice at t finds its two samples: x_s on
// key slice s, x_s+1 on key slice s+1.
struct TrajectoryPoints {
  double x0 = 0, y0 = 0, x1 = 0, y1 = 0;
};

TrajectoryPoints TrajectoryAt(const GapNeighbourhood& gap,
                              const HermiteBasis& basis, int64_t i, int64_t j,
                              bool backward_fields) {
  const int64_t v = i + gap.nx * j, plane = gap.plane;
  const bool has_prev = gap.has_prev, has_next = gap.has_next;
  const double w_prev = gap.w_prev, w_next = gap.w_next;
  const std::vector<float>& u = gap.u;
  const double u_x = u[v], u_y = u[plane + v];
  // Forward trajectory from key slice s (morph.h's cubic).
  const double vs_x = has_prev ? w_prev * (gap.u_prev[v] + u_x) : u_x;
  const double vs_y = has_prev ? w_prev * (gap.u_prev[plane + v] + u_y) : u_y;
  const double ve_x = has_next ? w_next * (u_x + gap.u_next[v]) : u_x;
  const double ve_y = has_next ? w_next * (u_y + gap.u_next[plane + v]) : u_y;
  TrajectoryPoints p;
  p.x0 = i - (basis.h10 * vs_x + basis.h01 * u_x + basis.h11 * ve_x);
  p.y0 = j - (basis.h10 * vs_y + basis.h01 * u_y + basis.h11 * ve_y);
  p.x1 = p.x0 + u_x, p.y1 = p.y0 + u_y;
  if (backward_fields) {
    // The same trajectory anchored on key slice s+1, from the
    // backward fields: b (s+1 -> s), b_next (s+2 -> s+1), b_prev
    // (s -> s-1).
    const std::vector<float>& b = gap.b;
    const double b_x = b[v], b_y = b[plane + v];
    const double ws_x =
        has_next ? w_next * (gap.b_next[v] + b_x) : b_x;  // at s+1
    const double ws_y = has_next ? w_next * (gap.b_next[plane + v] + b_y) : b_y;
    const double we_x = has_prev ? w_prev * (b_x + gap.b_prev[v]) : b_x;
    const double we_y = has_prev ? w_prev * (b_y + gap.b_prev[plane + v]) : b_y;
    p.x1 = i - (basis.g10 * ws_x + basis.g01 * b_x + basis.g11 * we_x);
    p.y1 = j - (basis.g10 * ws_y + basis.g01 * b_y + basis.g11 * we_y);
  }
  return p;
}

// The morph at one output pixel: the two samples the registration matched
// (a_s, a_s+1) and their value interpolated in t; `touched` when a sample
// reaches a pixel of padding.
struct MorphedPixel {
  double a0 = 0, a1 = 0;
  double value = 0;
  bool touched = false;
};

MorphedPixel MorphPixel(const GapNeighbourhood& gap, const HermiteBasis& basis,
                        int64_t i, int64_t j,
                        const IntensityMorphOptions& options) {
  const int64_t nx = gap.nx, ny = gap.ny, plane = gap.plane;
  const int64_t v = i + nx * j;
  const std::optional<float>& padding = gap.padding;
  const double t = basis.t;
  const TrajectoryPoints p =
      TrajectoryAt(gap, basis, i, j, options.backward_fields);
  MorphedPixel px;
  bool& touched = px.touched;
  const double a0 =
      SampleUnpadded(gap.g0, nx, ny, p.x0, p.y0, padding, touched);
  const double a1 =
      SampleUnpadded(gap.g1, nx, ny, p.x1, p.y1, padding, touched);
  px.a0 = a0;
  px.a1 = a1;
  double value = 0;
  if (options.values == MorphValues::kLinear) {
    value = (1 - t) * a0 + t * a1;
  } else if (options.values == MorphValues::kSmoothstep) {
    value = basis.h00 * a0 + basis.h01 * a1;
  } else {
    // Value tangents through key slices s-1 and s+2, reached by the
    // field anchored on the nearer key slice: b_prev lives on key
    // slice s (s -> s-1), u_next on key slice s+1 (s+1 -> s+2).
    double m0 = a1 - a0, m1 = a1 - a0;
    double am = 0, ap = 0;
    if (gap.has_prev) {
      am = options.backward_fields
               ? SampleUnpadded(gap.gm, nx, ny, p.x0 + gap.b_prev[v],
                                p.y0 + gap.b_prev[plane + v], padding, touched)
               : SampleUnpadded(gap.gm, nx, ny, p.x0 - gap.u_prev[v],
                                p.y0 - gap.u_prev[plane + v], padding, touched);
    }
    if (gap.has_next) {
      ap = SampleUnpadded(gap.gp, nx, ny, p.x1 + gap.u_next[v],
                          p.y1 + gap.u_next[plane + v], padding, touched);
    }
    const double len = gap.len, len_prev = gap.len_prev,
                 len_next = gap.len_next;
    if (options.values == MorphValues::kMonotone) {
      const double slope = (a1 - a0) / len;  // per mm
      if (gap.has_prev)
        m0 = len * MonotoneTangent((a0 - am) / len_prev, slope, len_prev, len);
      if (gap.has_next)
        m1 = len * MonotoneTangent(slope, (ap - a1) / len_next, len, len_next);
    } else {
      if (gap.has_prev) m0 = gap.w_prev * (a1 - am);
      if (gap.has_next) m1 = gap.w_next * (ap - a0);
    }
    value = basis.h00 * a0 + basis.h10 * m0 + basis.h01 * a1 + basis.h11 * m1;
  }
  px.value = value;
  return px;
}

// The first pass over output slice `dst` at t: every pixel's value, except
// those the pair check decides (candidates, left at the linear blend with
// the morph's value kept in `check`), whose morph pair is recorded for the
// smoothing.
void WriteMorphedSlice(const GapNeighbourhood& gap,
                       const std::vector<float>& weight,
                       const std::vector<uint8_t>& changing,
                       const HermiteBasis& basis,
                       const IntensityMorphOptions& options, PairCheck& check,
                       float* dst, GapCounts& counts) {
  const int64_t nx = gap.nx, ny = gap.ny;
  const std::optional<float>& padding = gap.padding;
  const double t = basis.t;
  const bool pair_crop = check.Cropped();
  const PixelBox& pair_box = check.box;
  for (int64_t j = 0; j < ny; ++j)
    for (int64_t i = 0; i < nx; ++i) {
      const int64_t v = i + nx * j;
      const float lin0 = gap.g0[v], lin1 = gap.g1[v];
      const bool in_pair_box = pair_crop && pair_box.Contains(i, j);
      const int64_t box_v = in_pair_box ? pair_box.Index(i, j) : 0;
      if (pair_crop) check.candidate[v] = 0;
      if (in_pair_box) check.pair_morph[box_v] = 0;
      if (padding.has_value() && (lin0 == *padding || lin1 == *padding)) {
        dst[v] = *padding;  // outside the scanned field, as linear
        continue;
      }
      if (in_pair_box) {
        const float step = lin1 - lin0;
        check.pair_morph[box_v] = step * step;
      }
      const double linear = (1 - t) * lin0 + t * lin1;
      const bool counted = changing[v] != 0;
      counts.inserted += counted;
      const double w = weight[v];
      if (w <= 0) {
        dst[v] = static_cast<float>(linear);
        counts.fallbacks += counted;
        continue;
      }
      const MorphedPixel px = MorphPixel(gap, basis, i, j, options);
      double value = px.value;
      if (px.touched) {
        dst[v] = static_cast<float>(linear);
        counts.fallbacks += counted;
        continue;
      }
      if (in_pair_box) {
        check.pair_morph[box_v] =
            static_cast<float>((px.a1 - px.a0) * (px.a1 - px.a0));
      }
      if (pair_crop && check.static_weight[v] > 0) {
        // Decided after the smoothing below.
        dst[v] = static_cast<float>(linear);
        check.morph_value[v] = static_cast<float>(value);
        check.candidate[v] = 1;
        continue;
      }
      // The pair check blends the morph's value as a float.
      if (check.enabled) value = static_cast<float>(value);
      if (w < 0.5) counts.fallbacks += counted;
      dst[v] = static_cast<float>(w * value + (1 - w) * linear);
    }
}

// The second pass over output slice `dst` at t: the morph pair smoothed, and
// the candidates' values with w = w_residual w_fold w_pair.
absl::Status ApplyPairCheck(const GapNeighbourhood& gap,
                            const std::vector<float>& weight,
                            const std::vector<uint8_t>& changing, double t,
                            const IntensityMorphOptions& options,
                            const PairCheck& check, float* dst,
                            GapCounts& counts) {
  const int64_t nx = gap.nx;
  const PixelBox& pair_box = check.box;
  INTERSLICE_ASSIGN_OR_RETURN(const std::vector<float> morph_disagreement,
                              Smooth(check.pair_morph, pair_box.Width(),
                                     pair_box.Height(), options.pair_sigma_px));
  for (int64_t j = pair_box.y0; j < pair_box.y1; ++j)
    for (int64_t i = pair_box.x0; i < pair_box.x1; ++i) {
      const int64_t v = i + nx * j;
      if (!check.candidate[v]) continue;
      const double e_morph =
          std::sqrt(std::max(0.0f, morph_disagreement[pair_box.Index(i, j)]));
      // Dragged: the morph's pair disagrees by pair_tolerance_noise
      // units more than the linear pair.
      const double dragged =
          check.tolerance > 0
              ? Ramp((e_morph - check.e_linear[v]) / check.tolerance)
              : (e_morph > check.e_linear[v] ? 1.0 : 0.0);
      const double w_pair = 1.0 - check.static_weight[v] * dragged;
      const double w = weight[v] * w_pair;
      if (w < 0.5) counts.fallbacks += changing[v] != 0;
      const double linear = (1 - t) * gap.g0[v] + t * gap.g1[v];
      dst[v] = static_cast<float>(w * check.morph_value[v] + (1 - w) * linear);
    }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<GapCounts> WriteGapSlices(
    const KeySlices& keys, const std::vector<GapRegistration>& reg, int64_t s,
    const std::vector<int64_t>& slices_in_gap,
    const std::vector<Placement>& place, const RegistrationLattice& lattice,
    const IntensityMorphOptions& options, Volume<float>& out) {
  const GapNeighbourhood gap =
      GatherGapNeighbourhood(keys, reg, s, options.backward_fields);
  const std::vector<float> weight = FullResolutionWeight(reg[s], keys, lattice);
  const std::vector<uint8_t> changing =
      FullResolutionChanging(reg[s], keys, lattice, options.register_slices);
  GapCounts counts;
  const bool pair_check = options.pair_check && options.register_slices;
  INTERSLICE_ASSIGN_OR_RETURN(
      PairCheck check, PrepareLinearPairCheck(gap, weight, reg[s].pair_unit,
                                              pair_check, options));
  for (int64_t k : slices_in_gap) {
    const HermiteBasis basis = HermiteBasisAt(place[k].t);
    float* dst = out.data.data() + k * keys.plane;
    WriteMorphedSlice(gap, weight, changing, basis, options, check, dst,
                      counts);
    if (!check.Cropped()) continue;
    INTERSLICE_RETURN_IF_ERROR(ApplyPairCheck(gap, weight, changing, basis.t,
                                              options, check, dst, counts));
  }
  return counts;
}

}  // namespace interslice::intensity_morph_internal

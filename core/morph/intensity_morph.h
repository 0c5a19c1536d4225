// Grey values carried along the morph (issue 23): the source's modality
// values (HU for CT, the stored units times slope plus intercept for MR) on
// an output grid, each inserted slice interpolated along the motion between
// its two bracketing key slices instead of blended in place. Registration-
// based interpolation after Penney et al. 2004 ("Registration-based
// interpolation", IEEE TMI 23(7)) and Frakes et al. 2008 (IEEE TMI 27(3)),
// with the trajectory and value interpolation of core/morph (morph.h: a C1
// cubic Hermite trajectory through the key slices, monotone (PCHIP) values
// along it, Fritsch & Carlson 1980).
//
// For every gap between neighbouring key slices s, s+1 (grey images G_s,
// G_s+1 at true positions z_s < z_s+1 along the slice normal):
// - Registration: the forward field u_s (pixels) with
//   G_s+1(x + u_s(x)) ~ G_s(x), by core/morph's demons (RegisterSlicesCoarse,
//   MorphOptions' settings) on the registration images (IntensityRegistration:
//   by default the grey images themselves, each pair's robust range mapped
//   onto [0, grey_scale]).
// - An output slice at z in (z_s, z_s+1), t = (z - z_s) / (z_s+1 - z_s),
//   takes at pixel p the grey value of key slice s at x_s = p - h(t) and of
//   key slice s+1 at x_s+1 = x_s + u_s, where h is morph.h's cubic Hermite
//   trajectory (tangent at a key slice: the chord of the two gaps' fields,
//   per mm for uneven gaps; one-sided at the ends), the fields evaluated at
//   p (first order, as StackMorph). Every output pixel pulls its values
//   (bilinear sampling), so the result has no holes; the two samples are
//   the pair the registration matched, so the blend never mixes tissue that
//   does not correspond. (backward_fields: key slice s+1 sampled instead
//   through the inverse field b_s, b_s(y) = -u_s(y + b_s(y)) by fixed-point
//   iteration, Chen et al. 2008, Med. Phys. 35(1), anchored on its own
//   lattice; measured worse, docs/eval/intensity.md.)
// - The value is the monotone cubic Hermite (PCHIP) of a_s = G_s(x_s) and
//   a_s+1 = G_s+1(x_s+1) in t, with tangents from a_s-1 and a_s+2 reached
//   through the neighbouring gaps' fields (morph.h, MorphValues::kMonotone):
//   C1 in z and never outside [min(a_s, a_s+1), max(a_s, a_s+1)] (no
//   overshoot at bone edges, no new extremes of noise).
// - Local fallback to the linear blend (1 - t) G_s(p) + t G_s+1(p), the
//   value ResampleSourceSlices gives (core/dicom_out), with a weight w(p) in
//   [0, 1] per gap: value = w morph + (1 - w) linear, w = w_residual w_fold
//   w_pair:
//     w_residual: the motion is used where it explains the key slices'
//       difference. On the registration lattice, r_lin = Gauss(|N_s+1 -
//       N_s|) and r_reg = Gauss(|N_s+1(x + u_s(x)) - N_s(x)|) (N: the
//       registration images, in units of their range; Gauss: sigma
//       residual_sigma_px); w_residual rises from 0 at r_lin - r_reg =
//       gain_low to 1 at gain_high. So a large residual that the
//       registration leaves (no correspondence: anatomy that appears, a
//       wrong match) falls back, and so does unchanging tissue, where a
//       field driven by noise would only move the noise around.
//     w_fold: 0 where the intermediate map x -> x + t u_s(x) folds or nearly
//       does (min over t in [0, 1] of det(I + t grad u_s) <= min_jacobian),
//       1 from twice that, linear between.
//     w_pair, the pair check, per output pixel (issue 23: a smooth field
//       carries a large motion, e.g. an insert's oblique face, onto static
//       tissue next to it, which then moves although nothing there
//       changes; measured in homogeneous soft tissue of the CT phantoms at
//       every 2nd slice): e_linear and e_morph, the root of the squared
//       difference of the two samples each estimator blends (G_s(p),
//       G_s+1(p) for linear; a_s, a_s+1 for the morph), Gaussian-smoothed.
//       Where the linear pair agrees within the noise (static tissue) and
//       the morph's pair disagrees by more than the noise, the motion is
//       wrong there: w_pair = 1 - static * dragged, static = clamp(2 -
//       e_linear / (pair_static_noise sigma), 0, 1), dragged = clamp((e_morph
//       - e_linear) / (pair_tolerance_noise sigma), 0, 1). sigma is the
//       noise estimated from the data of each gap (the robust scale, 1.4826
//       x the median absolute deviation, of the key slices' difference;
//       modality independent, so MR in arbitrary units takes the same
//       settings; at least 1e-3 of the pair's robust range, for noise-free
//       images). Where the tissue changes between the key slices (a skull
//       that thins towards the vertex) both pairs disagree and the check
//       leaves the morph alone: there it is still the better estimate.
//   A gap falls back entirely (w = 0) when it cannot be registered: one of
//   its key slices has no contrast (its 1st and 99th percentiles equal:
//   constant, or all padding), or it is longer than max_gap_ratio times the
//   series' median gap (a missing block: the slices on either side need not
//   show the same anatomy, and a plausible wrong match need not leave a
//   large residual). A bilinear sample that touches a pixel of
//   pixel_padding (outside the scanned field) also falls back at that output
//   pixel, so padding appears exactly where the linear blend puts it, never
//   inside the body.
// - Output slices on a key slice (within 1e-4 mm) are copies of it, bit for
//   bit; slices beyond the first or last key slice by at most half the output
//   z spacing copy it; further out, the outside value (pixel_padding if given,
//   else the image's minimum), as ResampleSourceSlices.
//
// Memory: the coarse fields of every gap (forward and backward, the weight
// and a flag: about 5 floats per coarse pixel, e.g. 330 KB per gap of
// 512x512 at downsample 4), plus per running gap its neighbourhood's fields
// at full resolution (up to 13 floats per pixel, 13.6 MB for 512x512), plus
// the output volume (as ResampleSourceSlices). Threads: gaps are registered
// and written concurrently on context.threads; the result does not depend on
// the thread count. Cancellation is polled once per gap and phase.
#ifndef INTERSLICE_CORE_MORPH_INTENSITY_MORPH_H_
#define INTERSLICE_CORE_MORPH_INTENSITY_MORPH_H_

#include <cstdint>
#include <optional>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"
#include "core/morph/morph.h"

namespace interslice {

// What the registration between neighbouring key slices sees.
enum class IntensityRegistration {
  // The grey images themselves, each pair mapped linearly so that its
  // robust range (the 1st to 99th percentile of both slices' values) spans
  // [0, grey_scale]: every structure with contrast drives it.
  kGrey,
  // The caller's 2D signed distance maps of the thresholded object (the
  // mask job's, core/sdf), clipped to +-clip_mm as StackMorph registers
  // them: only the object's contours drive it.
  kDistanceMaps,
};

struct IntensityMorphOptions {
  IntensityRegistration registration = IntensityRegistration::kGrey;
  // Demons settings (levels, iterations, field_sigma_px, downsample;
  // clip_mm for kDistanceMaps). The trajectory is always the cubic, the
  // values are `values` below. The defaults are the mask morph's; 1/2
  // resolution with 2 levels was no better (worse at every 8th slice) at
  // 3-4x the cost (docs/eval/intensity-notes.md).
  MorphOptions demons;
  // kGrey: the robust range of a pair is mapped onto [0, grey_scale].
  double grey_scale = 8.0;
  // The value interpolation along the trajectory: kMonotone (default) or
  // kLinear / kSmoothstep / kCatmullRom (morph.h).
  MorphValues values = MorphValues::kMonotone;
  // Whether key slice s+1 is sampled through the backward field (see above);
  // false samples both through the forward field as StackMorph does.
  bool backward_fields = false;
  // Whether to register at all: false gives u = 0, i.e. each pixel's values
  // interpolated in z in place by `values` (kCatmullRom: the Catmull-Rom
  // baseline; kLinear: exactly the linear blend).
  bool register_slices = true;
  // Fallback (see above): the morph's weight rises from 0 where the
  // registration lowers the local residual by gain_low (r_lin - r_reg, in
  // units of the pair's robust range (kGrey) or of 2 clip_mm
  // (kDistanceMaps)) to 1 where it lowers it by gain_high; gain_low <
  // gain_high. Where the key slices differ by at least gain_high (r_lin >=
  // gain_high: tissue that changes between them) a weight below 1/2 counts
  // as a fallback in the statistics. 0.01 / 0.04 and 0.005 / 0.02 and
  // 0.002 / 0.01 gave the same PSNR within 0.03 dB on the thin phantom; the
  // largest kept homogeneous soft tissue closest to linear.
  double gain_low = 0.01;
  double gain_high = 0.04;
  // ... and only where it explains most of it: the weight falls from 1 at
  // r_reg / r_lin = ratio_low to 0 at ratio_high (demons also lower the
  // residual of unrelated textures a little, by matching their noise);
  // 0 <= ratio_low < ratio_high.
  double ratio_low = 0.5;
  double ratio_high = 0.75;
  // Smoothing of the residual maps, registration-lattice pixels; > 0.
  double residual_sigma_px = 2.0;
  // Smallest Jacobian determinant of the intermediate maps kept; in (0, 1).
  double min_jacobian = 0.2;
  // A gap longer than this many median gaps falls back entirely; >= 1.
  double max_gap_ratio = 3.0;
  // The pair check (see above): static tissue up to pair_static_noise noise
  // units of e_linear (ramping out at twice that), dragged from
  // pair_tolerance_noise units of e_morph - e_linear; smoothing
  // pair_sigma_px output pixels. All >= 0, pair_sigma_px > 0 (a 0 unit makes
  // its ramp a step). pair_static_noise 2 and 4 left the tilted phantom's
  // homogeneous tissue at k = 2 worse than linear (11.9 and 10.4 HU against
  // 8.9); 8 is the smallest of the three that does not (8.2), at a cost of
  // 0.06 dB (thin) and 0.36 dB (tilted) at k = 8 against no pair check
  // (docs/eval/intensity-notes.md).
  bool pair_check = true;
  // Smooth the morph's pair only around the pixels where the check can act
  // (static weight and morph weight both > 0, plus 16 sigma): the same
  // values as whole slices to float precision, ~15% less CPU on the CT
  // phantoms. false smooths whole slices (the reference the crop is tested
  // against).
  bool crop_pair_check = true;
  double pair_tolerance_noise = 2.0;
  double pair_static_noise = 8.0;
  double pair_sigma_px = 1.5;
};

struct IntensityMorphStatistics {
  int gaps = 0;                 // between key slices
  int gaps_not_registered = 0;  // fell back entirely (constant, too long)
  // Output voxels strictly between two key slices where the key slices
  // differ (r_lin >= gain_high; every voxel of a gap that was not
  // registered), and those of them whose value is mostly the linear blend
  // (fallback weight 1 - w > 1/2): unchanging tissue needs no motion and is
  // not counted.
  int64_t inserted_voxels = 0;
  int64_t fallback_voxels = 0;
  // fallback_voxels / inserted_voxels (0 if none).
  double fallback_fraction = 0;
  // The key slices' noise standard deviation estimated from the data
  // (the median absolute deviation of neighbouring key slices' difference,
  // intensity_morph.cc PairNoiseScale), mean over the registered gaps,
  // modality units (0 if none).
  double noise_sigma = 0;
  // Mean and largest forward displacement over all registered gaps, mm.
  double mean_displacement_mm = 0;
  double max_displacement_mm = 0;
};

struct MorphedIntensity {
  Volume<float> values;
  IntensityMorphStatistics statistics;
};

// The grey values of `image` (key slices in order, after any gantry tilt
// resampling and region-of-interest crop; positions_mm[k] = true position of
// slice k along the normal, strictly increasing) on `target` (the in-plane
// lattice of `image`, slices along its normal), interpolated along the
// motion between key slices as described above. `distance_maps` (same grid
// as `image`) is required for IntensityRegistration::kDistanceMaps and
// ignored otherwise. `pixel_padding`: as ResampleSourceSlices. Errors:
// INVALID_ARGUMENT for mismatched grids, positions or bad options (naming
// them); RESOURCE_EXHAUSTED never (the output is the target's size, which the
// caller bounds); CANCELLED / DEADLINE_EXCEEDED from context.
absl::StatusOr<MorphedIntensity> MorphIntensity(
    const Volume<float>& image, const std::vector<double>& positions_mm,
    const Grid& target, std::optional<float> pixel_padding,
    const Volume<float>* distance_maps, const IntensityMorphOptions& options,
    const ComputeContext& context);

}  // namespace interslice

#endif  // INTERSLICE_CORE_MORPH_INTENSITY_MORPH_H_

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
//   G_s+1(x + u_s(x)) ~ G_s(x), by core/morph's demons (RegisterSlicesCoarse)
//   on the registration images (see IntensityRegistration), and the backward
//   field b_s, its inverse (b_s(y) = -u_s(y + b_s(y)), solved by fixed-point
//   iteration: Chen et al. 2008, "A simple fixed-point approach to invert a
//   deformation field", Med. Phys. 35(1)).
// - An output slice at z in (z_s, z_s+1), t = (z - z_s) / (z_s+1 - z_s),
//   takes at pixel p the grey value of key slice s at x_s = p - h(t) and of
//   key slice s+1 at x_s+1 = p - h'(1 - t), where h is the cubic Hermite
//   trajectory of morph.h built from the forward fields (tangent at s:
//   the chord of u_s-1 and u_s, per mm for uneven gaps; one-sided at the
//   ends) and h' the same built from the backward fields anchored on key
//   slice s+1. Each key slice is sampled through the field that lives on its
//   own lattice, so the first-order error of evaluating the fields at p
//   (rather than at the tissue's pre-image) is O(t^2) on the side of s and
//   O((1-t)^2) on the side of s+1: small where that side's weight is large.
//   Every output pixel pulls its values (bilinear sampling), so the result
//   has no holes.
// - The value is the monotone cubic Hermite (PCHIP) of a_s = G_s(x_s) and
//   a_s+1 = G_s+1(x_s+1) in t, with tangents from a_s-1 and a_s+2 reached
//   through the neighbouring gaps' forward fields (morph.h, MorphValues::
//   kMonotone): C1 in z and never outside [min(a_s, a_s+1), max(a_s, a_s+1)]
//   (no overshoot at bone edges, no new extremes of noise).
// - Local fallback to the linear blend (1 - t) G_s(p) + t G_s+1(p), the
//   value ResampleSourceSlices gives (core/dicom_out), with a weight
//   w(p) in [0, 1] per gap: value = w morph + (1 - w) linear, where
//   w = w_residual * w_fold:
//     w_residual: the registration's local residual r_reg =
//       Gauss(|N_s+1(x + u_s(x)) - N_s(x)|) on the registration lattice (N:
//       the registration images, in units of the pair's robust intensity
//       range), against that of no registration r_lin (u = 0): 1 where
//       r_reg <= r_lin and r_reg <= residual_low, 0 where r_reg >=
//       residual_high or r_reg >= 2 r_lin + residual_low, linear between;
//     w_fold: 0 where the intermediate map x -> x + t u_s(x) folds or nearly
//       does (min over t in [0, 1] of det(I + t grad u_s) < min_jacobian),
//       else 1.
//   A gap also falls back entirely (w = 0) when it cannot be registered: its
//   key slices are constant (no robust range), or it is longer than
//   max_gap_ratio times the series' median gap (a missing block: the slices
//   on either side need not show the same anatomy, and a plausible wrong
//   match would not show as a large residual). A bilinear sample that
//   touches a pixel of pixel_padding (outside the scanned field) also falls
//   back at that output pixel, so padding appears exactly where the linear
//   blend puts it, never inside the body.
// - Output slices on a key slice (within 1e-4 mm) are copies of it, bit for
//   bit; slices beyond the first or last key slice by at most half the output
//   z spacing copy it; further out, the outside value (pixel_padding if given,
//   else the image's minimum), as ResampleSourceSlices.
//
// Memory: the registration's coarse fields of every gap (forward, backward
// and the fallback weight: 5 floats per coarse pixel, 1/d^2 of a slice each,
// e.g. 320 KB per gap of 512x512 at d = 4), plus per running gap its three
// fields and weight upsampled to full resolution (7 floats per pixel), plus
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
  // values are `values` below.
  MorphOptions demons;
  // kGrey: the robust range of a pair is mapped onto [0, grey_scale].
  double grey_scale = 8.0;
  // The value interpolation along the trajectory: kMonotone (default) or
  // kLinear / kSmoothstep / kCatmullRom (morph.h).
  MorphValues values = MorphValues::kMonotone;
  // Whether key slice s+1 is sampled through the backward field (see above);
  // false samples both through the forward field as StackMorph does.
  bool backward_fields = true;
  // Whether to register at all: false gives u = 0, i.e. each pixel's values
  // interpolated in z in place by `values` (kCatmullRom: the Catmull-Rom
  // baseline; kLinear: exactly the linear blend).
  bool register_slices = true;
  // Fallback thresholds (see above), in units of the robust range (kGrey) or
  // of clip_mm (kDistanceMaps); >= 0, residual_low < residual_high.
  double residual_low = 0.04;
  double residual_high = 0.12;
  // ... and only where the registration did not reduce the residual much:
  // the fallback is weighted in from r_reg / r_lin = ratio_low to
  // ratio_high (a large residual that the registration explains, e.g. at a
  // moving bone edge, keeps the morph); 0 <= ratio_low < ratio_high.
  double ratio_low = 0.75;
  double ratio_high = 0.95;
  // Smoothing of the residual maps, registration-lattice pixels; > 0.
  double residual_sigma_px = 2.0;
  // Smallest Jacobian determinant of the intermediate maps kept; in (0, 1).
  double min_jacobian = 0.2;
  // A gap longer than this many median gaps falls back entirely; >= 1.
  double max_gap_ratio = 3.0;
};

struct IntensityMorphStatistics {
  int gaps = 0;                // between key slices
  int gaps_not_registered = 0; // fell back entirely (constant, too long)
  // Output voxels strictly between two key slices, and those of them whose
  // value is mostly the linear blend (fallback weight 1 - w > 1/2).
  int64_t inserted_voxels = 0;
  int64_t fallback_voxels = 0;
  double fallback_fraction = 0;  // fallback_voxels / inserted_voxels (0 if none)
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

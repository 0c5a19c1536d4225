// Registration-based stacking of per-slice distance maps ("morph"): shape-
// based interpolation that follows the structure between key slices instead
// of blending the maps in place (issue 14). Literature: registration-based
// interpolation (Penney et al. 2004, "Registration-based interpolation",
// IEEE TMI 23(7); Frakes et al. 2008, "A new method for registration-based
// medical image interpolation", IEEE TMI 27(3)).
//
// For every pair of neighbouring original slices s, s+1 (distance maps D0,
// D1, in mm, positive inside), a dense 2D displacement u (pixels) is found by
// ITK's multi-resolution symmetric-forces demons (Thirion 1998; Vercauteren
// et al. 2007), fixed = D0 and moving = D1, both clipped to +-clip_mm so the
// registration is driven by the band around the contours:
//   D1(x + u(x)) ~ D0(x).
// An output slice at fraction t in (0, 1) of the gap is
//   f_t(p) = (1 - t) D0(p - t u(p)) + t D1(p + (1 - t) u(p))
// (bilinear sampling, clamped at the slice border): both maps are carried
// along the correspondence to the intermediate position and blended. u is
// smooth (Gaussian-regularised demons), so evaluating it at p rather than at
// its pre-image is a first-order approximation. For u = 0 this is exactly
// linear stacking (core/stack StackLinear); at t = 0 and t = 1 it returns D0
// and D1, so the original slices are reproduced bit-identically.
//
// With the piecewise trajectory the field is meant to be refined by
// core/solver with a fidelity term (SolverOptions::fidelity,
// MorphOptions::refine): the curvature energy removes the creases that
// piecewise morphing leaves at the original slices while staying close to
// the morph.
//
// MorphTrajectory::kCubic (issue 14, "smooth in z by construction") removes
// the crease without a refinement: the gap registrations are composed into
// one trajectory per pixel through all key slices, interpolated in z by a
// cubic Hermite spline with Catmull-Rom tangents (Catmull & Rom 1974; chord
// slopes over the two gaps for uneven gaps), and the values carried
// along it by a cubic Hermite too (below), so the field is C1 across the key
// slices (up to the first-order evaluation of the fields at p, as above).
// Inside the gap between key slices s, s+1 (registration u_s, output slice
// at fraction t, everything per gap, i.e. in units of the gap):
//   x_s(p)   = p - h(t),  h(t) = H10(t) v_s + H01(t) u_s + H11(t) v_{s+1}
//   x_{s+1}  = x_s + u_s, x_{s-1} = x_s - u_{s-1}, x_{s+2} = x_{s+1} + u_{s+1}
//   f_t(p)   = H00(t) a_s + H10(t) m_s + H01(t) a_{s+1} + H11(t) m_{s+1}
// with a_r = D_r(x_r), the Hermite basis H00 = 2t^3 - 3t^2 + 1, H10 = t^3 -
// 2t^2 + t, H01 = 3t^2 - 2t^3, H11 = t^3 - t^2, the trajectory tangent v_s =
// (u_{s-1} + u_s) / 2 and, with Catmull-Rom values, the value tangent m_s =
// (a_{s+1} - a_{s-1}) / 2 (uniform gaps; for uneven gaps of L_{s-1}, L_s output
// slices the chord slopes (u_{s-1} + u_s) / (L_{s-1} + L_s) and (a_{s+1} -
// a_{s-1}) / (L_{s-1} + L_s) per output slice, scaled by the gap's L;
// one-sided, v = u and m = a_{s+1} - a_s within the gap, at the first and last
// key slice). A constant velocity (u_{s-1} = u_s) gives h(t) = t u_s, i.e.
// exactly the piecewise-linear trajectory. Catmull-Rom value tangents can
// overshoot the key-slice values (an object where neither key slice has one
// along the trajectory); the default value tangents are therefore the monotone
// (PCHIP) ones of Fritsch & Carlson 1980 (MorphValues::kMonotone): m_s is the
// weighted harmonic mean of the value slopes a_s - a_{s-1} and a_{s+1} - a_s
// (per output slice, weights 2 L_s + L_{s-1} and L_s + 2 L_{s-1}), 0 where
// they differ in sign, so every piece stays between a_s and a_{s+1} and the
// value is still C1 at the key slices. At t = 0 and 1 the key slices are
// reproduced bit-identically (they are never rewritten).
//
// Parallelism: gaps are registered concurrently (one ITK filter per gap,
// single-threaded); the cubic needs the neighbouring gaps' fields, so all
// gaps are registered before any slice is written. Results do not depend
// on the thread count. Cancellation is polled once per gap and phase.
// Memory: kCubic holds every gap's displacement (2 floats per pixel per gap,
// e.g. 73 MB for 35 gaps of 512x512) until the slices are written; the
// piecewise trajectory holds one per running gap.
#ifndef INTERSLICE_CORE_MORPH_MORPH_H_
#define INTERSLICE_CORE_MORPH_MORPH_H_

#include <cstdint>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"
#include "core/stack/stacking.h"

namespace interslice {

// How the output slices inside a gap follow the registrations.
enum class MorphTrajectory {
  // One registration per gap, linear in t (Penney et al. 2004): C0 in z,
  // creased at every key slice.
  kPiecewiseLinear,
  // The gap registrations composed into one C1 cubic Hermite trajectory per
  // pixel (Catmull-Rom tangents), the values C1 along it (see above).
  kCubic,
};

// kCubic only: the interpolation of the values a_s, a_{s+1} carried along
// the trajectory (see above).
enum class MorphValues {
  // (1 - t) a_s + t a_{s+1}, as kPiecewiseLinear: C1 trajectory, but the
  // value still creases at the key slices.
  kLinear,
  // Cubic Hermite with Catmull-Rom tangents through a_{s-1} .. a_{s+2}: C1;
  // may overshoot the key values.
  kCatmullRom,
  // a_s + (a_{s+1} - a_s) (3t^2 - 2t^3) (the Hermite cubic with zero
  // tangents, "smoothstep"): C1, and a convex blend of the two key values
  // like the linear one, so it never overshoots them (no object where
  // neither key slice has one along the trajectory).
  kSmoothstep,
  // Cubic Hermite with monotone (PCHIP) tangents: the weighted harmonic mean
  // of the value slopes on either side of a key slice, zero at a local
  // extremum (Fritsch & Carlson 1980). C1 like Catmull-Rom (the tangent at a
  // key slice is the same from both gaps), and like smoothstep every piece
  // stays between its two key values, so it never overshoots them; linear
  // values along the trajectory are reproduced exactly.
  kMonotone,
};

struct MorphOptions {
  // The trajectory through the key slices. The default is what
  // --method morph runs: the cubic, which on the phantom (bone and soft
  // tissue, every 2nd / 4th / 8th slice and thick -> thin) is more accurate
  // than the refined piecewise morph everywhere and has crease index <= 2.7
  // without any refinement (docs/eval/candidates.md, "Smooth-in-z morph" and
  // "Monotone values").
  MorphTrajectory trajectory = MorphTrajectory::kCubic;
  // kCubic only: how the values carried along the trajectory are
  // interpolated between the key slices. The default, monotone (PCHIP), is
  // the most accurate of the four on both objects of the phantom at every 2nd,
  // 4th and 8th slice (docs/eval/candidates.md, "Monotone values"); it has no
  // parameter.
  MorphValues values = MorphValues::kMonotone;
  // Pyramid levels of the demons registration (each halves the resolution).
  // >= 1.
  int levels = 4;
  // Demons iterations per level, the same at every level. >= 0 (0 gives
  // u = 0: linear stacking for kPiecewiseLinear; for kCubic the values of
  // each pixel interpolated in z in place). 25: the registration has
  // converged by then on the phantom (mean displacement within 3% of 50
  // iterations at every 2nd, 4th and 8th slice on both objects, a property
  // of the key slices alone) at half the cost; docs/eval/candidates.md,
  // "Demons iterations".
  int iterations = 25;
  // Standard deviation of the Gaussian applied to the displacement field
  // after every demons iteration (the regulariser), in pixels of the level.
  // > 0.
  double field_sigma_px = 2.0;
  // The maps are clipped to [-clip_mm, clip_mm] before registration. > 0.
  double clip_mm = 4.0;
  // Registration runs on maps downsampled by this integer factor in-plane
  // (block mean); the displacement is upsampled bilinearly. >= 1.
  int downsample = 4;
  // Whether the pipeline refines the morph by the direct solver with the
  // fidelity below. The piecewise trajectory needs it to remove its crease
  // at the key slices (crease index 4-14 -> <= 3, at a cost in accuracy);
  // the cubic one has no crease to remove, and the refinement only costs it
  // accuracy (docs/eval/candidates.md), so the default does not refine.
  bool refine = false;
  // The refinement (only with refine; SolverOptions::fidelity,
  // fidelity_taper), chosen for the piecewise trajectory: the largest
  // tapered fidelity of {0.3, 1, 3} whose result keeps the crease index
  // (docs/eval; a property of the result alone, no ground truth) <= 3 on the
  // phantom (bone, every 8th slice); Dice was not used to choose it.
  // docs/eval/candidates.md has the sweep.
  double fidelity = 0.3;
  bool fidelity_taper = true;
  // RemoveUnsupportedComponents' margin, mm.
  float component_margin_mm = 1e-3f;
};

struct MorphStatistics {
  // Mean and largest displacement length over all gaps, mm (in-plane).
  double mean_displacement_mm = 0;
  double max_displacement_mm = 0;
  int gaps = 0;
};

struct MorphedField {
  StackedField stacked;
  MorphStatistics statistics;
};

// Stacks `slice_maps` (one 2D map per original slice, as StackLinear) onto
// the grid of `plan` by registration-based morphing. The output grid, fixed
// slices and factor are those StackLinear gives for the same plan.
// Distances stay in mm, displacements in pixels; uneven plans (gaps of
// different numbers of output slices) are handled with t measured in output
// slices. INVALID_ARGUMENT for bad options (including an unknown trajectory
// or value interpolation) or a plan that does not match the maps;
// RESOURCE_EXHAUSTED if the output would exceed max_voxels; CANCELLED /
// DEADLINE_EXCEEDED from context.cancel.
absl::StatusOr<MorphedField> StackMorph(const Volume<float>& slice_maps,
                                        const StackPlan& plan,
                                        const MorphOptions& options,
                                        int64_t max_voxels,
                                        const ComputeContext& context);

// The component filter of the morph method ("a component only where the key
// slices allow one", issue 14): every connected component (face
// connectivity, ITK ConnectedComponentImageFilter) of the object field >= 0
// that has no voxel on an original (fixed) slice is supported by no data:
// linear stacking can never create one (a blend is positive only where one
// of its two original slices is), so it is an artefact of the refinement
// (overshoot) or of the morph. Its voxels are set to min(f, -margin_mm) so
// that the object and the zero level set lose it; nothing else changes.
// Returns the number of components removed. INVALID_ARGUMENT for a size
// mismatch or margin_mm <= 0.
absl::StatusOr<int64_t> RemoveUnsupportedComponents(
    Volume<float>& field, const std::vector<uint8_t>& fixed_slices,
    float margin_mm, const ComputeContext& context);

// Used by StackMorph and exposed for tests: the displacement u (pixels, two
// planes: ux then uy, each nx*ny, i fastest) registering `moving` onto
// `fixed` (both nx*ny, i fastest): moving(x + u(x)) ~ fixed(x).
absl::StatusOr<std::vector<float>> RegisterSlices(const float* fixed,
                                                  const float* moving,
                                                  int64_t nx, int64_t ny,
                                                  const MorphOptions& options);

// The displacement RegisterSlices computes, before it is upsampled: on the
// registration's own lattice of mx x my = ceil(nx / d) x ceil(ny / d)
// pixels (d = options.downsample; coarse pixel c covers fine pixels
// [c d, c d + d) in each axis), in pixels of the coarse lattice (times d
// for fine pixels, which Sample and Upsample apply). Holding this instead of
// the full-resolution field takes 1/d^2 of the memory (e.g. 128 KB per gap of a
// 512x512 series at d = 4); Sample() gives exactly the value RegisterSlices
// writes at a fine pixel.
struct CoarseDisplacement {
  int64_t nx = 0, ny = 0;  // the fine lattice
  int64_t mx = 0, my = 0;  // the coarse lattice
  int downsample = 1;
  std::vector<float> ux, uy;  // mx*my each, i fastest; coarse pixels

  // u in fine pixels at fine pixel (x, y) (continuous): bilinear on the
  // coarse lattice, clamped at its border, times d, as RegisterSlices
  // upsamples.
  void Sample(double x, double y, float& out_x, float& out_y) const;
  // The full-resolution field (RegisterSlices' layout: ux plane, uy plane).
  std::vector<float> Upsample() const;
};

// INVALID_ARGUMENT naming the first option out of range (see MorphOptions).
absl::Status ValidateMorphOptions(const MorphOptions& options);

// RegisterSlices without the upsampling: the same registration, the same
// errors. With options.iterations == 0 the field is zero.
absl::StatusOr<CoarseDisplacement> RegisterSlicesCoarse(
    const float* fixed, const float* moving, int64_t nx, int64_t ny,
    const MorphOptions& options);

}  // namespace interslice

#endif  // INTERSLICE_CORE_MORPH_MORPH_H_

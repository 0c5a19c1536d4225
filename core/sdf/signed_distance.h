// Per-slice contours and 2D signed distance maps (paper section 3, steps 1-2).
//
// For each original slice the iso-contour of the grey image at the threshold
// is extracted with ITK's ContourExtractor2DImageFilter (marching squares,
// sub-pixel by linear interpolation along cell edges). The signed distance of
// a pixel is, in millimetres (PixelSpacing-aware):
//   - exact to the nearest contour segment within `band_radius_mm` of the
//     contour (the paper's band), and
//   - outside the band, max(band_radius_mm, ITK SignedMaurerDistanceMap
//     distance of the thresholded mask): within about one pixel of exact, and
//     never below the band radius, so it stays monotone across the band edge.
// The sign is positive inside the object, negative outside. "Inside" means
// lower <= value (and value <= upper when an upper threshold is given); the
// sign of a pixel is that of its own grey value, which is the side of the
// linearly interpolated contour it lies on.
//
// End caps: SliceSignedDistance gives a slice with no contour (object
// absent, or the slice entirely inside) the constant -cap (+cap), cap = band
// radius. ComputeSliceDistanceMaps, which sees the whole stack, instead gives
// such a slice the 3D distance to the nearest slice holding the other state,
// taking that slice's cross-section as the object: at pixel p,
// -(+) sqrt((m * slice_spacing)^2 + d(p)^2), where m is the number of slices
// to it and d(p) the in-plane distance of p to the cross-section there (0
// inside it). Between a slice showing the object at depth rho and the empty
// slice next to it, the interpolated shape closes off a fraction
// rho / (rho + spacing) of the gap: within one slice gap, neither cut flat
// at the last slice nor extended along z, and without a jump against the
// far field that the refinement would overshoot. (Only if no slice at all
// holds the other state does the constant cap remain.)
#ifndef INTERSLICE_CORE_SDF_SIGNED_DISTANCE_H_
#define INTERSLICE_CORE_SDF_SIGNED_DISTANCE_H_

#include <optional>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"

namespace interslice {

struct ContourOptions {
  float lower = 0;             // threshold, in image units (HU)
  std::optional<float> upper;  // optional upper threshold (HU)
  // Radius of the exact band, mm; <= 0 picks 16 pixels of the larger
  // in-plane spacing.
  double band_radius_mm = 0;
};

// A contour segment in continuous in-plane index coordinates (i, j).
struct ContourSegment {
  double i0, j0, i1, j1;
};

// The iso-contour segments of one slice (nx * ny floats, i fastest).
absl::StatusOr<std::vector<ContourSegment>> ExtractContourSegments(
    const float* slice, int64_t nx, int64_t ny, const ContourOptions& options);

// Signed distance map of one slice, mm. `out` holds nx * ny floats.
absl::Status SliceSignedDistance(const float* slice, int64_t nx, int64_t ny,
                                 double spacing_x, double spacing_y,
                                 const ContourOptions& options, float* out);

// The band radius actually used for `options` and in-plane spacings.
double EffectiveBandRadius(const ContourOptions& options, double spacing_x,
                           double spacing_y);

// Signed distance maps of every slice of `image` (same grid as `image`).
// Slices run in parallel (context.threads); cancellation is polled per slice.
absl::StatusOr<Volume<float>> ComputeSliceDistanceMaps(
    const Volume<float>& image, const ContourOptions& options,
    const ComputeContext& context);

}  // namespace interslice

#endif  // INTERSLICE_CORE_SDF_SIGNED_DISTANCE_H_

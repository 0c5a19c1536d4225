// Exact 2D signed distance of planar polygons (RTSTRUCT contours) on a slice
// of a grid, so that a structure drawn as contours keeps its drawn boundary
// on the key slices instead of the staircase of its rasterised pixels.
//
// Coordinates: polygons are in continuous in-plane index coordinates (i, j)
// of the reference grid: pixel (i, j)'s centre is at (i, j); patient mm are
// (i * spacing_x, j * spacing_y) along the grid's row and column axes.
// Inside: the even-odd rule over all polygons of the slice (a polygon inside
// another is a hole; disjoint polygons are separate parts). This is the rule
// ReadRtStruct rasterises with, so the sign at a pixel centre equals whether
// that pixel is drawn.
//
// Distance: Euclidean, in mm, to the nearest polygon edge (exact point-to-
// segment distance); positive inside, negative outside, 0 on an edge. This
// matches core/sdf (signed_distance.h) inside its band; see
// OverlayPolygonDistances for how the band and the far field are combined.
#ifndef INTERSLICE_CORE_LABELS_POLYGON_DISTANCE_H_
#define INTERSLICE_CORE_LABELS_POLYGON_DISTANCE_H_

#include <array>
#include <cstdint>
#include <map>
#include <vector>

#include "absl/status/status.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"

namespace interslice {

// One closed polygon: its vertices (i, j) in order, the closing edge from the
// last vertex back to the first implied.
using Polygon2D = std::vector<std::array<double, 2>>;

// Contours of a segmentation: per label, per input slice k, its polygons.
struct LabelContours {
  std::map<int, std::map<int64_t, std::vector<Polygon2D>>> polygons;

  // The polygons of `label` on slice `k`, or nullptr if there are none.
  const std::vector<Polygon2D>* Find(int label, int64_t k) const;
};

// Signed distance (mm) of the pixels of the box [i0, i0 + width) x
// [j0, j0 + height) to `polygons`, written row by row (i fastest) to `out`
// (width * height floats). Pixels whose nearest edge is farther than
// `band_radius_mm` are left untouched (`out` keeps what it held) unless
// band_radius_mm is +infinity. Cost: each edge visits only the pixels of its
// bounding box grown by the band, about edges x (edge length + 2 band)^2
// pixels, not pixels x edges (+infinity: pixels x edges). INVALID_ARGUMENT for
// a polygon with fewer than 3 vertices, non-finite coordinates, spacing <= 0
// or band_radius_mm <= 0.
absl::Status PolygonSignedDistance(const std::vector<Polygon2D>& polygons,
                                   int64_t i0, int64_t j0, int64_t width,
                                   int64_t height, double spacing_x,
                                   double spacing_y, double band_radius_mm,
                                   float* out);

// The hook of FillBetweenSlices (label_fill.h): `maps` holds the 2D signed
// distances of `label` on its key slices `keys` (slice s of `maps` is input
// slice keys[s]) over the in-plane box whose first pixel is (i0, j0) of the
// reference grid, as core/sdf computed them from the rasterised label (its
// grid spacing is the reference's in-plane spacing). On every key slice where
// `contours` has polygons of `label`, each pixel within `band_radius_mm` of a
// polygon edge gets the exact polygon distance; a pixel farther away keeps
// core/sdf's magnitude (which is >= the band radius there) with the sign of
// the polygons. So the field's zero set on a key slice is the drawn contour
// itself, and the far field is core/sdf's, monotone across the band edge.
// Slices without polygons (drawn-and-empty ends) are left as they are.
// INVALID_ARGUMENT as for PolygonSignedDistance; CANCELLED /
// DEADLINE_EXCEEDED from context (polled per slice).
absl::Status OverlayPolygonDistances(const LabelContours& contours, int label,
                                     const std::vector<int64_t>& keys,
                                     int64_t i0, int64_t j0,
                                     double band_radius_mm, Volume<float>& maps,
                                     const ComputeContext& context);

}  // namespace interslice

#endif  // INTERSLICE_CORE_LABELS_POLYGON_DISTANCE_H_

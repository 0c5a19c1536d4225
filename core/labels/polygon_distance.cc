#include "core/labels/polygon_distance.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"

namespace interslice {
namespace {

struct Edge {
  double ax, ay, bx, by;  // mm
};

// Squared distance from (px, py) to the segment a-b: the projection onto the
// segment's line clamped to the segment (Schneider & Eberly, "Geometric
// Tools for Computer Graphics", 2003, sec. 6.1.2).
double SegmentDistanceSquared(const Edge& e, double px, double py) {
  const double dx = e.bx - e.ax, dy = e.by - e.ay;
  const double length2 = dx * dx + dy * dy;
  double t = 0;
  if (length2 > 0) {
    t = std::clamp(((px - e.ax) * dx + (py - e.ay) * dy) / length2, 0.0, 1.0);
  }
  const double qx = e.ax + t * dx - px, qy = e.ay + t * dy - py;
  return qx * qx + qy * qy;
}

absl::Status Validate(const std::vector<Polygon2D>& polygons, double sx,
                      double sy, double band) {
  if (!(sx > 0) || !(sy > 0) || !std::isfinite(sx) || !std::isfinite(sy)) {
    return absl::InvalidArgumentError(
        "polygon distance: pixel spacing must be positive");
  }
  if (!(band > 0)) {
    return absl::InvalidArgumentError(
        "polygon distance: band radius must be positive");
  }
  for (size_t p = 0; p < polygons.size(); ++p) {
    if (polygons[p].size() < 3) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "polygon distance: polygon %d has %d vertices (needs 3)", p + 1,
          polygons[p].size()));
    }
    for (const auto& v : polygons[p]) {
      if (!std::isfinite(v[0]) || !std::isfinite(v[1])) {
        return absl::InvalidArgumentError(absl::StrFormat(
            "polygon distance: polygon %d has a non-finite vertex", p + 1));
      }
    }
  }
  return absl::OkStatus();
}

// For the box: `inside[p]` by the even-odd rule at the pixel centre, and
// `distance[p]` the unsigned distance (mm) to the nearest edge, or +infinity
// if that is farther than `band` (all exact when band is +infinity).
void Compute(const std::vector<Polygon2D>& polygons, int64_t i0, int64_t j0,
             int64_t width, int64_t height, double sx, double sy, double band,
             std::vector<uint8_t>& inside, std::vector<double>& distance) {
  const size_t count = static_cast<size_t>(width * height);
  inside.assign(count, 0);
  distance.assign(count, std::numeric_limits<double>::infinity());

  // Even-odd per row, in index coordinates exactly as ReadRtStruct fills:
  // an edge crosses row y when y is in [min(ay, by), max(ay, by)); a pixel
  // is inside when an odd number of crossings lie at or left of it.
  std::vector<double> crossings;
  for (int64_t r = 0; r < height; ++r) {
    const double y = static_cast<double>(j0 + r);
    crossings.clear();
    for (const Polygon2D& polygon : polygons) {
      for (size_t e = 0; e < polygon.size(); ++e) {
        const auto& a = polygon[e];
        const auto& b = polygon[(e + 1) % polygon.size()];
        if ((a[1] <= y) != (b[1] <= y)) {
          crossings.push_back(a[0] +
                              (y - a[1]) / (b[1] - a[1]) * (b[0] - a[0]));
        }
      }
    }
    std::sort(crossings.begin(), crossings.end());
    size_t c = 0;
    for (int64_t i = 0; i < width; ++i) {
      const double x = static_cast<double>(i0 + i);
      while (c < crossings.size() && crossings[c] <= x) ++c;
      inside[r * width + i] = c % 2;
    }
  }

  std::vector<Edge> edges;
  for (const Polygon2D& polygon : polygons) {
    for (size_t e = 0; e < polygon.size(); ++e) {
      const auto& a = polygon[e];
      const auto& b = polygon[(e + 1) % polygon.size()];
      edges.push_back({a[0] * sx, a[1] * sy, b[0] * sx, b[1] * sy});
    }
  }

  // Pixel centres of the box in mm.
  const double x0 = static_cast<double>(i0) * sx;
  const double y0 = static_cast<double>(j0) * sy;
  const double x1 = static_cast<double>(i0 + width - 1) * sx;
  const double y1 = static_cast<double>(j0 + height - 1) * sy;

  if (!std::isfinite(band)) {
    for (int64_t r = 0; r < height; ++r) {
      for (int64_t i = 0; i < width; ++i) {
        const double px = x0 + i * sx, py = y0 + r * sy;
        double best = std::numeric_limits<double>::infinity();
        for (const Edge& e : edges) {
          best = std::min(best, SegmentDistanceSquared(e, px, py));
        }
        distance[r * width + i] = std::sqrt(best);
      }
    }
    return;
  }

  // Each edge updates only the pixels of its bounding box grown by the
  // band: every pixel within the band of the edge lies there, so the
  // minimum over those updates is exact wherever it is <= band. Cost:
  // sum over edges of (edge extent + 2 band)^2 / pixel area, instead of
  // pixels x edges.
  const double band2 = band * band;
  std::vector<double> d2(count, std::numeric_limits<double>::infinity());
  for (const Edge& e : edges) {
    const double ex0 = std::min(e.ax, e.bx) - band;
    const double ex1 = std::max(e.ax, e.bx) + band;
    const double ey0 = std::min(e.ay, e.by) - band;
    const double ey1 = std::max(e.ay, e.by) + band;
    if (ex1 < x0 || ey1 < y0 || ex0 > x1 || ey0 > y1) continue;
    // Clamped as doubles first: far-off vertices must not overflow int64.
    const auto first = [](double v, int64_t n) {
      return static_cast<int64_t>(
          std::clamp(std::ceil(v), 0.0, static_cast<double>(n - 1)));
    };
    const auto last = [](double v, int64_t n) {
      return static_cast<int64_t>(
          std::clamp(std::floor(v), 0.0, static_cast<double>(n - 1)));
    };
    const int64_t c0 = first((ex0 - x0) / sx, width);
    const int64_t c1 = last((ex1 - x0) / sx, width);
    const int64_t r0 = first((ey0 - y0) / sy, height);
    const int64_t r1 = last((ey1 - y0) / sy, height);
    for (int64_t r = r0; r <= r1; ++r) {
      const double py = y0 + r * sy;
      double* row = d2.data() + r * width;
      for (int64_t c = c0; c <= c1; ++c) {
        row[c] = std::min(row[c], SegmentDistanceSquared(e, x0 + c * sx, py));
      }
    }
  }
  for (size_t p = 0; p < count; ++p) {
    if (d2[p] <= band2) distance[p] = std::sqrt(d2[p]);
  }
}

}  // namespace

const std::vector<Polygon2D>* LabelContours::Find(int label, int64_t k) const {
  const auto l = polygons.find(label);
  if (l == polygons.end()) return nullptr;
  const auto s = l->second.find(k);
  if (s == l->second.end() || s->second.empty()) return nullptr;
  return &s->second;
}

absl::Status PolygonSignedDistance(const std::vector<Polygon2D>& polygons,
                                   int64_t i0, int64_t j0, int64_t width,
                                   int64_t height, double spacing_x,
                                   double spacing_y, double band_radius_mm,
                                   float* out) {
  INTERSLICE_RETURN_IF_ERROR(
      Validate(polygons, spacing_x, spacing_y, band_radius_mm));
  if (width <= 0 || height <= 0) return absl::OkStatus();
  std::vector<uint8_t> inside;
  std::vector<double> distance;
  Compute(polygons, i0, j0, width, height, spacing_x, spacing_y, band_radius_mm,
          inside, distance);
  for (size_t p = 0; p < distance.size(); ++p) {
    if (!std::isfinite(distance[p])) continue;
    out[p] = static_cast<float>(inside[p] ? distance[p] : -distance[p]);
  }
  return absl::OkStatus();
}

absl::Status OverlayPolygonDistances(const LabelContours& contours, int label,
                                     const std::vector<int64_t>& keys,
                                     int64_t i0, int64_t j0,
                                     double band_radius_mm, Volume<float>& maps,
                                     const ComputeContext& context) {
  const Grid& g = maps.grid;
  if (static_cast<int64_t>(keys.size()) != g.size[2]) {
    return absl::InvalidArgumentError(
        absl::StrFormat("polygon distance: %d key slices for %d distance maps",
                        keys.size(), g.size[2]));
  }
  const int64_t plane = g.size[0] * g.size[1];
  std::vector<uint8_t> inside;
  std::vector<double> distance;
  for (size_t s = 0; s < keys.size(); ++s) {
    const std::vector<Polygon2D>* polygons = contours.Find(label, keys[s]);
    if (polygons == nullptr) continue;
    INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
    if (absl::Status st =
            Validate(*polygons, g.spacing[0], g.spacing[1], band_radius_mm);
        !st.ok()) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "label %d, slice %d: %s", label, keys[s], st.message()));
    }
    Compute(*polygons, i0, j0, g.size[0], g.size[1], g.spacing[0], g.spacing[1],
            band_radius_mm, inside, distance);
    float* slice = maps.data.data() + s * plane;
    for (int64_t p = 0; p < plane; ++p) {
      const double magnitude =
          std::isfinite(distance[p])
              ? distance[p]
              : std::max<double>(std::abs(slice[p]), band_radius_mm);
      slice[p] = static_cast<float>(inside[p] ? magnitude : -magnitude);
    }
  }
  return absl::OkStatus();
}

}  // namespace interslice

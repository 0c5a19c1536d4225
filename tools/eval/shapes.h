// The paper's artificial data (section 5): analytic signed distances (> 0
// inside) on 64 x 64 voxels of 1 mm in-plane. Header-only, shared by the
// evaluation harness and tests/core/pipeline/paper_artificial_test.cc.
#ifndef INTERSLICE_TOOLS_EVAL_SHAPES_H_
#define INTERSLICE_TOOLS_EVAL_SHAPES_H_

#include <algorithm>
#include <array>
#include <cmath>

namespace interslice::eval {

constexpr int kShapeSize = 64;

// Exact signed distance of the sphere of radius 20 mm at the centre (>0 in).
inline double Sphere(double x, double y, double z) {
  const double c = (kShapeSize - 1) / 2.0;
  return 20.0 -
         std::sqrt((x - c) * (x - c) + (y - c) * (y - c) + (z - c) * (z - c));
}

inline double SegmentDistance(const std::array<double, 3>& p,
                              const std::array<double, 3>& a,
                              const std::array<double, 3>& b) {
  double ab2 = 0, t = 0;
  for (int n = 0; n < 3; ++n) {
    ab2 += (b[n] - a[n]) * (b[n] - a[n]);
    t += (p[n] - a[n]) * (b[n] - a[n]);
  }
  t = std::clamp(t / ab2, 0.0, 1.0);
  double d2 = 0;
  for (int n = 0; n < 3; ++n) {
    const double q = a[n] + t * (b[n] - a[n]) - p[n];
    d2 += q * q;
  }
  return std::sqrt(d2);
}

// A cross of two round-ended tubes of radius 6 mm (an X in the xz plane).
inline double TubeCross(double x, double y, double z) {
  const double c = (kShapeSize - 1) / 2.0;
  const std::array<double, 3> p = {x, y, z};
  const double a =
      6.0 - SegmentDistance(p, {c - 18, c, c - 18}, {c + 18, c, c + 18});
  const double b =
      6.0 - SegmentDistance(p, {c - 18, c, c + 18}, {c + 18, c, c - 18});
  return std::max(a, b);
}

}  // namespace interslice::eval

#endif  // INTERSLICE_TOOLS_EVAL_SHAPES_H_

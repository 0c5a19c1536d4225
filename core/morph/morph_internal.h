// Private to core/morph: the sampling and value-tangent helpers that the
// distance-map morph (morph.cc) and the grey-value morph
// (intensity_morph.cc, intensity_morph_write.cc) share, so both carry values
// along a trajectory the same way.
#ifndef INTERSLICE_CORE_MORPH_MORPH_INTERNAL_H_
#define INTERSLICE_CORE_MORPH_MORPH_INTERNAL_H_

#include <algorithm>
#include <cstdint>

namespace interslice::morph_internal {

// Bilinear sample of an nx*ny plane at continuous pixel (x, y), clamped to
// the border.
inline float Sample(const float* plane, int64_t nx, int64_t ny, double x,
                    double y) {
  x = std::clamp(x, 0.0, static_cast<double>(nx - 1));
  y = std::clamp(y, 0.0, static_cast<double>(ny - 1));
  const int64_t i0 =
      std::min<int64_t>(static_cast<int64_t>(x), nx - 2 < 0 ? 0 : nx - 2);
  const int64_t j0 =
      std::min<int64_t>(static_cast<int64_t>(y), ny - 2 < 0 ? 0 : ny - 2);
  const int64_t i1 = std::min(i0 + 1, nx - 1), j1 = std::min(j0 + 1, ny - 1);
  const double fx = x - i0, fy = y - j0;
  const double a = plane[i0 + nx * j0] * (1 - fx) + plane[i1 + nx * j0] * fx;
  const double b = plane[i0 + nx * j1] * (1 - fx) + plane[i1 + nx * j1] * fx;
  return static_cast<float>(a * (1 - fy) + b * fy);
}

// The tangent at a key slice of the monotone (PCHIP) value interpolation,
// per unit of length: the weighted harmonic mean of the slopes of the gaps on
// either side (Fritsch & Carlson 1980, "Monotone piecewise cubic
// interpolation", SIAM J. Numer. Anal. 17(2); the weights of Fritsch &
// Butland 1984 for uneven gaps, as in MATLAB's pchip), zero where the slopes
// differ in sign or one is zero (a local extremum or plateau at the key
// slice). |tangent| <= 3 min(|slope_before|, |slope_after|), so every Hermite
// piece stays between its two key values. `before`/`after`: slopes (value per
// unit length) of the gaps of `len_before`/`len_after` units.
inline double MonotoneTangent(double before, double after, double len_before,
                              double len_after) {
  if (!(before * after > 0)) return 0.0;
  const double w1 = 2 * len_after + len_before;
  const double w2 = len_after + 2 * len_before;
  return (w1 + w2) / (w1 / before + w2 / after);
}

}  // namespace interslice::morph_internal

#endif  // INTERSLICE_CORE_MORPH_MORPH_INTERNAL_H_

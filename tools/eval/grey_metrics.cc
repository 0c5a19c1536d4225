#include "tools/eval/grey_metrics.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <optional>
#include <vector>

namespace interslice::eval {

ErrorScores ErrorOnMask(const Volume<float>& result, const Volume<float>& truth,
                        const std::vector<uint8_t>& mask, double peak) {
  ErrorScores s;
  double sum = 0;
  for (size_t v = 0; v < mask.size(); ++v) {
    if (!mask[v]) continue;
    const double e = static_cast<double>(result.data[v]) - truth.data[v];
    sum += e * e;
    ++s.voxels;
  }
  if (s.voxels == 0) return s;
  s.rmse = std::sqrt(sum / s.voxels);
  s.psnr = s.rmse > 0 ? 20 * std::log10(peak / s.rmse)
                      : std::numeric_limits<double>::infinity();
  return s;
}

namespace {

// Wang et al. 2004, section III-C: 11x11 Gaussian window, sigma 1.5,
// normalised to unit sum (separable: the 1D taps' outer product).
constexpr int kRadius = 5;
std::vector<double> GaussianTaps() {
  std::vector<double> taps(2 * kRadius + 1);
  double total = 0;
  for (int i = -kRadius; i <= kRadius; ++i) {
    taps[i + kRadius] = std::exp(-(i * i) / (2 * 1.5 * 1.5));
    total += taps[i + kRadius];
  }
  for (double& t : taps) t /= total;
  return taps;
}

// Valid-mode separable filtering of an nx*ny plane: output (nx-10)*(ny-10).
std::vector<double> FilterValid(const std::vector<double>& in, int64_t nx,
                                int64_t ny, const std::vector<double>& taps) {
  const int64_t ox = nx - 2 * kRadius, oy = ny - 2 * kRadius;
  std::vector<double> rows(ox * ny), out(ox * oy);
  for (int64_t j = 0; j < ny; ++j)
    for (int64_t i = 0; i < ox; ++i) {
      double acc = 0;
      for (int t = 0; t <= 2 * kRadius; ++t)
        acc += taps[t] * in[i + t + nx * j];
      rows[i + ox * j] = acc;
    }
  for (int64_t j = 0; j < oy; ++j)
    for (int64_t i = 0; i < ox; ++i) {
      double acc = 0;
      for (int t = 0; t <= 2 * kRadius; ++t)
        acc += taps[t] * rows[i + ox * (j + t)];
      out[i + ox * j] = acc;
    }
  return out;
}

}  // namespace

void AccumulateSsim(const float* a, const float* b, int64_t nx, int64_t ny,
                    const uint8_t* mask, double dynamic_range, double* sum,
                    int64_t* count) {
  if (nx <= 2 * kRadius || ny <= 2 * kRadius) return;
  static const std::vector<double> taps = GaussianTaps();
  const int64_t plane = nx * ny;
  std::vector<double> x(plane), y(plane), xx(plane), yy(plane), xy(plane);
  for (int64_t v = 0; v < plane; ++v) {
    x[v] = a[v];
    y[v] = b[v];
    xx[v] = x[v] * x[v];
    yy[v] = y[v] * y[v];
    xy[v] = x[v] * y[v];
  }
  const std::vector<double> mx = FilterValid(x, nx, ny, taps);
  const std::vector<double> my = FilterValid(y, nx, ny, taps);
  const std::vector<double> mxx = FilterValid(xx, nx, ny, taps);
  const std::vector<double> myy = FilterValid(yy, nx, ny, taps);
  const std::vector<double> mxy = FilterValid(xy, nx, ny, taps);
  const double c1 = std::pow(0.01 * dynamic_range, 2);
  const double c2 = std::pow(0.03 * dynamic_range, 2);
  const int64_t ox = nx - 2 * kRadius, oy = ny - 2 * kRadius;
  for (int64_t j = 0; j < oy; ++j)
    for (int64_t i = 0; i < ox; ++i) {
      if (!mask[(i + kRadius) + nx * (j + kRadius)]) continue;
      const int64_t o = i + ox * j;
      const double mux = mx[o], muy = my[o];
      const double vx = mxx[o] - mux * mux, vy = myy[o] - muy * muy;
      const double cxy = mxy[o] - mux * muy;
      // Wang et al. 2004, eq. (13).
      const double ssim = ((2 * mux * muy + c1) * (2 * cxy + c2)) /
                          ((mux * mux + muy * muy + c1) * (vx + vy + c2));
      *sum += ssim;
      ++*count;
    }
}

double SampleTrilinear(const Volume<float>& v, const Vec3& p) {
  const Vec3 idx = v.grid.PhysicalToIndex(p);
  const Index3 n = v.grid.size;
  int64_t i0[3];
  double f[3];
  for (int a = 0; a < 3; ++a) {
    const double c = std::clamp(
        idx[a], 0.0, static_cast<double>(std::max<int64_t>(0, n[a] - 1)));
    i0[a] = std::min<int64_t>(static_cast<int64_t>(c),
                              std::max<int64_t>(0, n[a] - 2));
    f[a] = n[a] > 1 ? c - i0[a] : 0;
  }
  double acc = 0;
  for (int dk = 0; dk < 2; ++dk)
    for (int dj = 0; dj < 2; ++dj)
      for (int di = 0; di < 2; ++di) {
        const int64_t i = std::min(i0[0] + di, n[0] - 1);
        const int64_t j = std::min(i0[1] + dj, n[1] - 1);
        const int64_t k = std::min(i0[2] + dk, n[2] - 1);
        const double w = (di ? f[0] : 1 - f[0]) * (dj ? f[1] : 1 - f[1]) *
                         (dk ? f[2] : 1 - f[2]);
        acc += w * v.at(i, j, k);
      }
  return acc;
}

std::optional<double> RiseDistance(const Volume<float>& v, const Vec3& p,
                                   const Vec3& n, double half_length,
                                   double step_mm) {
  const int steps = static_cast<int>(std::lround(half_length / step_mm));
  const int count = 2 * steps + 1;
  std::vector<double> profile(count);
  for (int s = 0; s < count; ++s) {
    const double d = (s - steps) * step_mm;
    profile[s] =
        SampleTrilinear(v, {p[0] + d * n[0], p[1] + d * n[1], p[2] + d * n[2]});
  }
  const double low =
      *std::min_element(profile.begin(), profile.begin() + steps + 1);
  const double high = *std::max_element(profile.begin() + steps, profile.end());
  if (!(high > low)) return std::nullopt;
  const double l10 = low + 0.1 * (high - low), l50 = low + 0.5 * (high - low),
               l90 = low + 0.9 * (high - low);
  // The 50% crossing nearest to the centre.
  int best = -1;
  for (int s = 0; s + 1 < count; ++s) {
    if ((profile[s] - l50) * (profile[s + 1] - l50) <= 0 &&
        profile[s + 1] > profile[s]) {
      if (best < 0 || std::abs(s - steps) < std::abs(best - steps)) best = s;
    }
  }
  if (best < 0) return std::nullopt;
  // Walk down to the 10% level and up to the 90% level, interpolating the
  // crossing between samples.
  int lo = best;
  while (lo >= 0 && profile[lo] > l10) --lo;
  int hi = best + 1;
  while (hi < count && profile[hi] < l90) ++hi;
  if (lo < 0 || hi >= count) return std::nullopt;
  const double s10 = lo + (l10 - profile[lo]) / (profile[lo + 1] - profile[lo]);
  const double s90 =
      hi - 1 + (l90 - profile[hi - 1]) / (profile[hi] - profile[hi - 1]);
  return (s90 - s10) * step_mm;
}

}  // namespace interslice::eval

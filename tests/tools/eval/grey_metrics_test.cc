#include "tools/eval/grey_metrics.h"

#include <cmath>
#include <random>
#include <vector>

#include "gtest/gtest.h"

namespace interslice::eval {
namespace {

// SSIM of Wang et al. 2004, eq. (13), computed window by window with the
// 11x11 Gaussian (sigma 1.5) written out in full: the reference the
// separable implementation must agree with.
double BruteForceSsim(const std::vector<float>& a, const std::vector<float>& b,
                      int64_t nx, int64_t ny, double range) {
  double weights[11][11], total = 0;
  for (int j = -5; j <= 5; ++j)
    for (int i = -5; i <= 5; ++i) {
      weights[j + 5][i + 5] = std::exp(-(i * i + j * j) / (2 * 1.5 * 1.5));
      total += weights[j + 5][i + 5];
    }
  const double c1 = std::pow(0.01 * range, 2), c2 = std::pow(0.03 * range, 2);
  double sum = 0;
  int64_t count = 0;
  for (int64_t y = 5; y + 5 < ny; ++y)
    for (int64_t x = 5; x + 5 < nx; ++x) {
      double mx = 0, my = 0, xx = 0, yy = 0, xy = 0;
      for (int j = -5; j <= 5; ++j)
        for (int i = -5; i <= 5; ++i) {
          const double w = weights[j + 5][i + 5] / total;
          const double p = a[(x + i) + nx * (y + j)];
          const double q = b[(x + i) + nx * (y + j)];
          mx += w * p;
          my += w * q;
          xx += w * p * p;
          yy += w * q * q;
          xy += w * p * q;
        }
      const double vx = xx - mx * mx, vy = yy - my * my, cxy = xy - mx * my;
      sum += ((2 * mx * my + c1) * (2 * cxy + c2)) /
             ((mx * mx + my * my + c1) * (vx + vy + c2));
      ++count;
    }
  return sum / count;
}

double Ssim(const std::vector<float>& a, const std::vector<float>& b,
            int64_t nx, int64_t ny, double range) {
  std::vector<uint8_t> mask(nx * ny, 1);
  double sum = 0;
  int64_t count = 0;
  AccumulateSsim(a.data(), b.data(), nx, ny, mask.data(), range, &sum, &count);
  EXPECT_EQ(count, (nx - 10) * (ny - 10));
  return sum / count;
}

TEST(SsimTest, IdenticalImagesScoreOne) {
  std::mt19937 random(3);
  std::uniform_real_distribution<float> value(-1000, 1000);
  std::vector<float> a(40 * 30);
  for (float& v : a) v = value(random);
  EXPECT_NEAR(Ssim(a, a, 40, 30, 2000), 1.0, 1e-12);
}

TEST(SsimTest, ConstantImagesScoreTheLuminanceTerm) {
  // Constant x = 100, y = 50: variances and covariance vanish, so SSIM is
  // (2 mu_x mu_y + C1) / (mu_x^2 + mu_y^2 + C1) exactly.
  const double range = 255, c1 = std::pow(0.01 * range, 2);
  const std::vector<float> a(32 * 32, 100.0f), b(32 * 32, 50.0f);
  EXPECT_NEAR(Ssim(a, b, 32, 32, range),
              (2 * 100.0 * 50 + c1) / (100.0 * 100 + 50 * 50 + c1), 1e-12);
}

TEST(SsimTest, AgreesWithTheWindowByWindowDefinition) {
  std::mt19937 random(5);
  std::normal_distribution<float> noise(0, 40);
  std::vector<float> a(48 * 36), b(48 * 36);
  for (int64_t j = 0; j < 36; ++j)
    for (int64_t i = 0; i < 48; ++i) {
      a[i + 48 * j] = static_cast<float>(200 * std::sin(i / 5.0) + 30 * j);
      b[i + 48 * j] = a[i + 48 * j] + noise(random);
    }
  const double reference = BruteForceSsim(a, b, 48, 36, 1000);
  EXPECT_NEAR(Ssim(a, b, 48, 36, 1000), reference, 1e-9);
  // Noise lowers it; inverting the contrast makes it negative.
  EXPECT_LT(reference, 0.99);
  std::vector<float> inverted(a.size());
  for (size_t v = 0; v < a.size(); ++v) inverted[v] = 2000 - a[v];
  EXPECT_LT(Ssim(a, inverted, 48, 36, 1000), 0.0);
}

TEST(RiseDistanceTest, ErfEdgeRisesOver2563Sigma) {
  // A blurred step along x, value 1000 (1 + erf(x / (sqrt(2) sigma))) / 2:
  // its 10-90% rise distance is 2 * 1.2816 sigma.
  Volume<float> v;
  v.grid.size = {200, 4, 4};
  v.grid.spacing = {0.1, 1, 1};
  v.data.resize(200 * 16);
  const double sigma = 0.8;  // mm
  for (int64_t k = 0; k < 4; ++k)
    for (int64_t j = 0; j < 4; ++j)
      for (int64_t i = 0; i < 200; ++i) {
        const double x = 0.1 * i - 10.0;
        v.at(i, j, k) = static_cast<float>(
            500 * (1 + std::erf(x / (std::sqrt(2.0) * sigma))));
      }
  const auto rise = RiseDistance(v, {10.0, 1.5, 1.5}, {1, 0, 0}, 4.0, 0.05);
  ASSERT_TRUE(rise.has_value());
  EXPECT_NEAR(*rise, 2 * 1.2816 * sigma, 0.02);
  // Along the edge there is no rise.
  EXPECT_FALSE(
      RiseDistance(v, {10.0, 1.5, 1.5}, {0, 1, 0}, 1.0, 0.05).has_value());
}

TEST(ErrorOnMaskTest, RmseAndPsnrOverTheMaskOnly) {
  Volume<float> truth, result;
  truth.grid.size = result.grid.size = {4, 1, 1};
  truth.data = {0, 0, 0, 0};
  result.data = {3, -4, 100, 0};
  const ErrorScores s = ErrorOnMask(result, truth, {1, 1, 0, 1}, 50);
  EXPECT_EQ(s.voxels, 3);
  EXPECT_NEAR(s.rmse, std::sqrt(25.0 / 3), 1e-12);
  EXPECT_NEAR(s.psnr, 20 * std::log10(50 / std::sqrt(25.0 / 3)), 1e-12);
}

}  // namespace
}  // namespace interslice::eval

// Exact polygon distances (core/labels/polygon_distance.h) against analytic
// signed distances of boxes, and the fill of contour input using them.
#include "core/labels/polygon_distance.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <limits>
#include <numbers>
#include <vector>

#include "core/labels/label_fill.h"
#include "core/sdf/signed_distance.h"
#include "gtest/gtest.h"

namespace interslice {
namespace {

Polygon2D Box(double x0, double y0, double x1, double y1) {
  return {{x0, y0}, {x1, y0}, {x1, y1}, {x0, y1}};
}

// Signed distance (mm, positive inside) of an axis-aligned box given in
// index coordinates, at pixel (i, j), spacing (sx, sy).
double BoxDistance(double x0, double y0, double x1, double y1, double i,
                   double j, double sx, double sy) {
  const double dx = std::max({(x0 - i) * sx, 0.0, (i - x1) * sx});
  const double dy = std::max({(y0 - j) * sy, 0.0, (j - y1) * sy});
  if (dx > 0 || dy > 0) return -std::hypot(dx, dy);
  return std::min({(i - x0) * sx, (x1 - i) * sx, (j - y0) * sy, (y1 - j) * sy});
}

constexpr double kInf = std::numeric_limits<double>::infinity();

TEST(PolygonDistanceTest, SquareMatchesTheAnalyticDistance) {
  // Anisotropic pixels: the distance is in mm, not pixels.
  const double sx = 0.7, sy = 1.3;
  const int64_t w = 30, h = 24;
  std::vector<float> out(w * h, 0);
  ASSERT_TRUE(PolygonSignedDistance({Box(5.5, 4.25, 19.5, 15.75)}, 0, 0, w, h,
                                    sx, sy, kInf, out.data())
                  .ok());
  for (int64_t j = 0; j < h; ++j) {
    for (int64_t i = 0; i < w; ++i) {
      ASSERT_NEAR(out[j * w + i],
                  BoxDistance(5.5, 4.25, 19.5, 15.75, i, j, sx, sy), 1e-5)
          << i << ", " << j;
    }
  }
  EXPECT_GT(out[10 * w + 10], 0);  // inside is positive
}

TEST(PolygonDistanceTest, HoleAndTwoPolygonsByTheEvenOddRule) {
  // A square with a square hole, and a second square beside it; the box of
  // pixels starts at (3, 2) of the grid.
  const std::vector<Polygon2D> polygons = {Box(4.5, 4.5, 24.5, 24.5),
                                           Box(10.2, 9.8, 17.6, 18.3),
                                           Box(30.5, 6.5, 36.5, 12.5)};
  const int64_t i0 = 3, j0 = 2, w = 38, h = 26;
  std::vector<float> out(w * h, 0);
  ASSERT_TRUE(
      PolygonSignedDistance(polygons, i0, j0, w, h, 1, 1, kInf, out.data())
          .ok());
  for (int64_t r = 0; r < h; ++r) {
    for (int64_t c = 0; c < w; ++c) {
      const double i = i0 + c, j = j0 + r;
      const double outer = BoxDistance(4.5, 4.5, 24.5, 24.5, i, j, 1, 1);
      const double hole = BoxDistance(10.2, 9.8, 17.6, 18.3, i, j, 1, 1);
      const double other = BoxDistance(30.5, 6.5, 36.5, 12.5, i, j, 1, 1);
      // Ring = outer minus hole; the parts are disjoint: union = max.
      const double expected = std::max(std::min(outer, -hole), other);
      ASSERT_NEAR(out[r * w + c], expected, 1e-5) << i << ", " << j;
    }
  }
  EXPECT_LT(out[(14 - j0) * w + (14 - i0)], 0);  // in the hole
  EXPECT_GT(out[(9 - j0) * w + (33 - i0)], 0);   // in the second square
}

TEST(PolygonDistanceTest, BandLeavesFartherPixelsAlone) {
  const int64_t w = 40, h = 40;
  const float kUntouched = 1234.0f;
  std::vector<float> out(w * h, kUntouched);
  ASSERT_TRUE(PolygonSignedDistance({Box(10.5, 10.5, 29.5, 29.5)}, 0, 0, w, h,
                                    0.5, 0.5, 2.0, out.data())
                  .ok());
  int64_t touched = 0;
  for (int64_t j = 0; j < h; ++j) {
    for (int64_t i = 0; i < w; ++i) {
      const double d = BoxDistance(10.5, 10.5, 29.5, 29.5, i, j, 0.5, 0.5);
      if (std::abs(d) <= 2.0) {
        ASSERT_NEAR(out[j * w + i], d, 1e-5) << i << ", " << j;
        ++touched;
      } else {
        ASSERT_EQ(out[j * w + i], kUntouched) << i << ", " << j;
      }
    }
  }
  EXPECT_GT(touched, 100);
}

TEST(PolygonDistanceTest, RejectsDegeneratePolygons) {
  std::vector<float> out(4);
  EXPECT_EQ(PolygonSignedDistance({{{0, 0}, {1, 1}}}, 0, 0, 2, 2, 1, 1, kInf,
                                  out.data())
                .code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(PolygonSignedDistance({Box(0, 0, 1, 1)}, 0, 0, 2, 2, 0, 1, kInf,
                                  out.data())
                .code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(PolygonSignedDistance({{{0, 0}, {1, NAN}, {1, 1}}}, 0, 0, 2, 2, 1,
                                  1, kInf, out.data())
                .code(),
            absl::StatusCode::kInvalidArgument);
}

// Regression: a vertex far outside the box (a contour point 1e12 pixels
// away) must not overflow the pixel ranges of its edges.
TEST(PolygonDistanceTest, FarVerticesAreClampedToTheBox) {
  const int64_t w = 16, h = 16;
  std::vector<float> out(w * h, 99);
  ASSERT_TRUE(PolygonSignedDistance({{{5, 5}, {1e12, 5}, {5, 1e12}}}, 0, 0, w,
                                    h, 1, 1, 8, out.data())
                  .ok());
  EXPECT_NEAR(out[10 * w + 10], 5, 1e-5);
  EXPECT_NEAR(out[10 * w + 3], -2, 1e-5);
  EXPECT_EQ(out[15 * w + 15], 99);  // 10 px from both edges: beyond the band
}

// A circle drawn as a 720-vertex polygon on key slices 0, 4, 8.
constexpr double kCx = 31.7, kCy = 32.2, kR = 17.3;
Polygon2D Circle() {
  Polygon2D p;
  for (int n = 0; n < 720; ++n) {
    const double t = 2 * std::numbers::pi * n / 720;
    p.push_back({kCx + kR * std::cos(t), kCy + kR * std::sin(t)});
  }
  return p;
}

// The largest distance, in pixels, between the zero crossings of slice z of
// `field` along its rows and the true circle.
double ZeroSetError(const Volume<float>& field, int64_t z) {
  const int64_t bi = std::lround(field.grid.origin[0]);
  const int64_t bj = std::lround(field.grid.origin[1]);
  const int64_t w = field.grid.size[0], h = field.grid.size[1];
  double worst = 0;
  int crossings = 0;
  for (int64_t r = 0; r < h; ++r) {
    const double y = bj + r;
    if (std::abs(y - kCy) > kR - 1) continue;  // rows cutting the circle
    const double half = std::sqrt(kR * kR - (y - kCy) * (y - kCy));
    for (int64_t c = 0; c + 1 < w; ++c) {
      const float a = field.at(c, r, z), b = field.at(c + 1, r, z);
      if ((a > 0) == (b > 0)) continue;
      const double x = bi + c + a / (a - b);
      worst = std::max(worst, std::min(std::abs(x - (kCx - half)),
                                       std::abs(x - (kCx + half))));
      ++crossings;
    }
  }
  EXPECT_GT(crossings, 40);
  return worst;
}

TEST(PolygonDistanceTest, FillOfContoursKeepsTheDrawnContourOnKeySlices) {
  LabelVolume labels;
  labels.grid.size = {64, 64, 9};
  labels.grid.spacing = {1, 1, 2};
  labels.data.assign(labels.grid.VoxelCount(), 0);
  LabelContours contours;
  // The raster: pixel centres inside the polygon (its own sign, as
  // ReadRtStruct rasterises).
  std::vector<float> inside(64 * 64, -1);
  ASSERT_TRUE(
      PolygonSignedDistance({Circle()}, 0, 0, 64, 64, 1, 1, kInf, inside.data())
          .ok());
  for (int64_t k : {0, 4, 8}) {
    contours.polygons[3][k] = {Circle()};
    for (int64_t p = 0; p < 64 * 64; ++p) {
      if (inside[p] > 0) labels.data[k * 64 * 64 + p] = 3;
    }
  }
  FillOptions options;
  options.solver.method = SolverMethod::kLinear;
  options.keep_fields = true;
  ComputeContext context;
  context.threads = 1;

  absl::StatusOr<FillResult> raster =
      FillBetweenSlices(labels, options, context);
  ASSERT_TRUE(raster.ok()) << raster.status();
  options.contours = &contours;
  absl::StatusOr<FillResult> exact =
      FillBetweenSlices(labels, options, context);
  ASSERT_TRUE(exact.ok()) << exact.status();
  ASSERT_EQ(exact->per_label.size(), 1u);
  const double exact_error = ZeroSetError(exact->per_label[0].field, 4);
  const double raster_error = ZeroSetError(raster->per_label[0].field, 4);
  std::printf(
      "key-slice zero set vs circle: polygons %.4f px, raster %.4f px\n",
      exact_error, raster_error);
  EXPECT_LT(exact_error, 0.05);
  EXPECT_GT(raster_error, 0.2);
  // The key slices are still restored exactly from the raster.
  for (int64_t k : {0, 4, 8}) {
    for (int64_t p = 0; p < 64 * 64; ++p) {
      ASSERT_EQ(exact->labels.data[k * 64 * 64 + p],
                labels.data[k * 64 * 64 + p]);
    }
  }
}

// Not a limit, a measurement: a 500-vertex contour on a 512 x 512 slice.
TEST(PolygonDistanceTest, MeasureA500VertexContourOn512x512) {
  Polygon2D p;
  for (int n = 0; n < 500; ++n) {
    const double t = 2 * std::numbers::pi * n / 500;
    const double r = 180 + 25 * std::sin(5 * t);  // a wavy, non-convex shape
    p.push_back({256 + r * std::cos(t), 256 + r * std::sin(t)});
  }
  // Exact everywhere (every pixel against every edge), then banded.
  std::vector<float> exact(512 * 512, 0), out(512 * 512, 0);
  auto start = std::chrono::steady_clock::now();
  ASSERT_TRUE(
      PolygonSignedDistance({p}, 0, 0, 512, 512, 0.8, 0.8, kInf, exact.data())
          .ok());
  const double brute =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count();
  start = std::chrono::steady_clock::now();
  ASSERT_TRUE(
      PolygonSignedDistance({p}, 0, 0, 512, 512, 0.8, 0.8, 16 * 0.8, out.data())
          .ok());
  const double banded =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count();
  EXPECT_GT(exact[256 * 512 + 256], 0);
  EXPECT_LT(exact[0], 0);
  int64_t in_band = 0;
  for (size_t n = 0; n < out.size(); ++n) {
    if (std::abs(std::abs(exact[n]) - 16 * 0.8) < 1e-4) continue;
    if (std::abs(exact[n]) > 16 * 0.8) {
      ASSERT_EQ(out[n], 0.0f) << n;
    } else {
      ASSERT_EQ(out[n], exact[n]) << n;  // the culling loses nothing
      ++in_band;
    }
  }
  EXPECT_GT(in_band, 10000);
  // For scale: core/sdf's distance of the same shape's raster.
  std::vector<float> mask(512 * 512), raster(512 * 512);
  for (size_t n = 0; n < mask.size(); ++n) {
    mask[n] = exact[n] > 0 ? 1.0f : 0.0f;
  }
  ContourOptions contour;
  contour.lower = 0.5f;
  const auto sdf_start = std::chrono::steady_clock::now();
  ASSERT_TRUE(SliceSignedDistance(mask.data(), 512, 512, 0.8, 0.8, contour,
                                  raster.data())
                  .ok());
  const double sdf = std::chrono::duration<double>(
                         std::chrono::steady_clock::now() - sdf_start)
                         .count();
  std::printf(
      "500-vertex polygon, 512 x 512, band 16 px: polygon distance %.1f ms "
      "(every pixel to every edge: %.1f ms), core/sdf on its raster %.1f "
      "ms\n",
      1e3 * banded, 1e3 * brute, 1e3 * sdf);
}

}  // namespace
}  // namespace interslice

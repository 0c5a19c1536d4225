#include "core/sdf/signed_distance.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstring>
#include <functional>
#include <limits>
#include <optional>
#include <vector>

#include "gtest/gtest.h"

namespace interslice {
namespace {

ContourOptions Threshold(float lower, std::optional<float> upper = std::nullopt,
                         double band_radius_mm = 0) {
  ContourOptions options;
  options.lower = lower;
  options.upper = upper;
  options.band_radius_mm = band_radius_mm;
  return options;
}

ComputeContext Context(int threads, const CancellationToken* cancel) {
  ComputeContext context;
  context.threads = threads;
  context.cancel = cancel;
  return context;
}

// One slice sampled at pixel centres x = i * sx, y = j * sy (mm).
struct Slice {
  int64_t nx = 0, ny = 0;
  double sx = 1, sy = 1;
  std::vector<float> v;

  float at(int64_t i, int64_t j) const { return v[i + nx * j]; }
};

Slice MakeSlice(int64_t nx, int64_t ny, double sx, double sy,
                const std::function<double(double, double)>& f) {
  Slice s{nx, ny, sx, sy, std::vector<float>(nx * ny)};
  for (int64_t j = 0; j < ny; ++j) {
    for (int64_t i = 0; i < nx; ++i) {
      s.v[i + nx * j] = static_cast<float>(f(i * sx, j * sy));
    }
  }
  return s;
}

std::vector<float> Map(const Slice& s, const ContourOptions& options) {
  std::vector<float> out(s.nx * s.ny, std::nanf(""));
  const absl::Status status = SliceSignedDistance(s.v.data(), s.nx, s.ny, s.sx,
                                                  s.sy, options, out.data());
  EXPECT_TRUE(status.ok()) << status;
  return out;
}

double SegmentDistance(double px, double py, double ax, double ay, double bx,
                       double by) {
  const double ex = bx - ax, ey = by - ay;
  const double ee = ex * ex + ey * ey;
  const double t =
      ee > 0 ? std::clamp(((px - ax) * ex + (py - ay) * ey) / ee, 0.0, 1.0)
             : 0.0;
  return std::hypot(px - ax - t * ex, py - ay - t * ey);
}

// Hausdorff bound between the marching-squares polygon of a convex or concave
// radial profile and the true circle of radius `r`: vertex error of linear
// interpolation along an edge of length h (r'' <= 1/r along a line) plus the
// sagitta of a chord no longer than the cell diagonal.
double CircleTolerance(double r, double sx, double sy) {
  const double h = std::max(sx, sy);
  const double diag = std::hypot(sx, sy);
  return h * h / (8 * (r - h)) + diag * diag / (8 * (r - diag));
}

TEST(ExtractContourSegmentsTest, VerticesAreContinuousIndicesOfCrossings) {
  // v = i: the crossing of 1.25 lies a quarter of the way from i = 1 to 2 on
  // every horizontal cell edge.
  const Slice s = MakeSlice(5, 4, 1, 1, [](double x, double) { return x; });
  auto segments = ExtractContourSegments(s.v.data(), 5, 4, Threshold(1.25f));
  ASSERT_TRUE(segments.ok()) << segments.status();
  ASSERT_EQ(segments->size(), 3u);  // one per row of cells
  double covered = 0;
  for (const ContourSegment& seg : *segments) {
    EXPECT_NEAR(seg.i0, 1.25, 1e-12);
    EXPECT_NEAR(seg.i1, 1.25, 1e-12);
    EXPECT_EQ(seg.j0, std::round(seg.j0));
    EXPECT_GE(std::min(seg.j0, seg.j1), 0.0);
    EXPECT_LE(std::max(seg.j0, seg.j1), 3.0);
    covered += std::abs(seg.j1 - seg.j0);
  }
  EXPECT_DOUBLE_EQ(covered, 3.0);

  // Along j, with a slope of 2: 3 lies at j = 1.5.
  const Slice t = MakeSlice(4, 5, 1, 1, [](double, double y) { return 2 * y; });
  segments = ExtractContourSegments(t.v.data(), 4, 5, Threshold(3.0f));
  ASSERT_TRUE(segments.ok());
  ASSERT_EQ(segments->size(), 3u);
  for (const ContourSegment& seg : *segments) {
    EXPECT_NEAR(seg.j0, 1.5, 1e-12);
    EXPECT_NEAR(seg.j1, 1.5, 1e-12);
  }
}

TEST(SliceSignedDistanceTest, HalfPlaneIsExactInMillimetres) {
  // v = i, threshold 1.25: the contour is the line i = 1.25, so the signed
  // distance is (i - 1.25) * sx, in every row.
  const double sx = 0.5, sy = 0.8;
  const Slice s =
      MakeSlice(40, 6, sx, sy, [&](double x, double) { return x / sx; });
  const ContourOptions options = Threshold(1.25f);
  const std::vector<float> map = Map(s, options);
  const double band = EffectiveBandRadius(options, sx, sy);
  for (int64_t j = 0; j < s.ny; ++j) {
    for (int64_t i = 0; i < s.nx; ++i) {
      const double expected = (i - 1.25) * sx;
      if (std::abs(expected) <= band) {
        EXPECT_NEAR(map[i + s.nx * j], expected, 1e-6) << i << "," << j;
      } else {
        EXPECT_GE(map[i + s.nx * j], static_cast<float>(band));
      }
    }
  }
}

struct CircleCase {
  double sx, sy;
  bool smooth_disk;  // tanh grey disk instead of the cone R - r
};

class CircleTest : public testing::TestWithParam<CircleCase> {};

TEST_P(CircleTest, MatchesAnalyticSignedDistance) {
  const CircleCase c = GetParam();
  const double cx = 31.3, cy = 29.7, radius = 18.0;  // mm
  const int64_t nx = static_cast<int64_t>(std::ceil(64 / c.sx));
  const int64_t ny = static_cast<int64_t>(std::ceil(62 / c.sy));
  ContourOptions options;
  std::function<double(double, double)> f;
  if (c.smooth_disk) {
    // A blurred grey disk: 100 outside, 1100 inside, contour at 600.
    options.lower = 600;
    f = [&](double x, double y) {
      return 600 + 500 * std::tanh((radius - std::hypot(x - cx, y - cy)) / 3);
    };
  } else {
    options.lower = 0;
    f = [&](double x, double y) { return radius - std::hypot(x - cx, y - cy); };
  }
  const Slice s = MakeSlice(nx, ny, c.sx, c.sy, f);
  const std::vector<float> map = Map(s, options);

  const double band = EffectiveBandRadius(options, c.sx, c.sy);
  EXPECT_DOUBLE_EQ(band, 16 * std::max(c.sx, c.sy));
  const double min_spacing = std::min(c.sx, c.sy);
  const double max_spacing = std::max(c.sx, c.sy);
  // The cone is exactly linear in r, so only the chord and the interpolation
  // of r along cell edges contribute; the tanh profile also bends along r,
  // which adds an interpolation error of the same order.
  const double tolerance =
      (c.smooth_disk ? 2 : 1) * CircleTolerance(radius, c.sx, c.sy);
  ASSERT_LE(tolerance, 0.1 * min_spacing);

  double max_band_error = 0, max_far_error = 0;
  int64_t band_pixels = 0, far_pixels = 0;
  for (int64_t j = 0; j < ny; ++j) {
    for (int64_t i = 0; i < nx; ++i) {
      const double expected = radius - std::hypot(i * c.sx - cx, j * c.sy - cy);
      const float got = map[i + nx * j];
      ASSERT_EQ(std::signbit(got), !(s.at(i, j) >= options.lower))
          << i << "," << j;
      if (std::abs(expected) < 1e-3) continue;  // sign of a float tie
      ASSERT_EQ(got > 0, expected > 0) << i << "," << j;
      if (std::abs(expected) <= band - tolerance) {
        max_band_error = std::max(max_band_error, std::abs(got - expected));
        ++band_pixels;
      } else if (std::abs(expected) > band + tolerance) {
        // The output is float: the band radius rounded to nearest.
        EXPECT_GE(std::abs(got), static_cast<float>(band));
        max_far_error = std::max(max_far_error, std::abs(got - expected));
        ++far_pixels;
      }
    }
  }
  EXPECT_GT(band_pixels, 1000);
  EXPECT_GT(far_pixels, 100);
  EXPECT_LE(max_band_error, tolerance);
  EXPECT_LE(max_far_error, 1.5 * max_spacing);
  RecordProperty("max_band_error_mm", std::to_string(max_band_error));
  std::printf(
      "spacing %.2f x %.2f %s: band error %.5f mm (tol %.5f), far "
      "error %.3f mm\n",
      c.sx, c.sy, c.smooth_disk ? "tanh" : "cone", max_band_error, tolerance,
      max_far_error);
}

INSTANTIATE_TEST_SUITE_P(Spacings, CircleTest,
                         testing::Values(CircleCase{1.0, 1.0, false},
                                         CircleCase{0.5, 0.8, false},
                                         CircleCase{0.5, 0.8, true},
                                         CircleCase{0.9, 0.6, true}));

TEST(SliceSignedDistanceTest, RectangleIsExactIncludingCorners) {
  // Edges through pixel centres (i in [20, 40], j in [15, 32]): the linear
  // ramps are exact on every cell, so the contour is the rectangle itself and
  // the map is its exact signed distance, Euclidean to the corners outside.
  const double sx = 0.6, sy = 0.9;
  const int64_t nx = 60, ny = 50;
  Slice s{nx, ny, sx, sy, std::vector<float>(nx * ny)};
  for (int64_t j = 0; j < ny; ++j) {
    for (int64_t i = 0; i < nx; ++i) {
      s.v[i + nx * j] = static_cast<float>(std::min(
          {(i - 20) * sx, (40 - i) * sx, (j - 15) * sy, (32 - j) * sy}));
    }
  }
  const ContourOptions options = Threshold(0);
  const std::vector<float> map = Map(s, options);
  const double band = EffectiveBandRadius(options, sx, sy);
  int64_t corner_pixels = 0;
  for (int64_t j = 0; j < ny; ++j) {
    for (int64_t i = 0; i < nx; ++i) {
      const double dx = std::max<int64_t>({0, 20 - i, i - 40}) * sx;
      const double dy = std::max<int64_t>({0, 15 - j, j - 32}) * sy;
      const bool inside = dx == 0 && dy == 0;
      const double expected = inside ? std::min({(i - 20) * sx, (40 - i) * sx,
                                                 (j - 15) * sy, (32 - j) * sy})
                                     : -std::hypot(dx, dy);
      if (std::abs(expected) > band) continue;
      EXPECT_NEAR(map[i + nx * j], expected, 1e-5) << i << "," << j;
      if (dx > 0 && dy > 0) ++corner_pixels;
    }
  }
  EXPECT_GT(corner_pixels, 200);
  // Spot check: a pixel diagonally off the corner (40, 32).
  EXPECT_NEAR(map[45 + nx * 36], -std::hypot(5 * sx, 4 * sy), 1e-5);
}

TEST(SliceSignedDistanceTest, TriangleIsExactAwayFromCorners) {
  // A generic triangle as the min of three linear ramps (signed distances to
  // its edge lines). Marching squares is exact where one ramp is active on a
  // whole cell; near a corner it cuts the corner slightly, always inwards
  // (linear interpolation under-estimates the concave min), so outside pixels
  // never get less than the true distance, and pixels far enough from the
  // corners get exactly it.
  const double sx = 0.7, sy = 0.5;
  const int64_t nx = 70, ny = 90;
  const std::array<std::array<double, 2>, 3> p = {
      {{10.2, 8.7}, {40.9, 12.3}, {22.4, 37.1}}};  // mm
  // Signed distance to the line of edge e, positive on its left.
  auto edge_value = [&](int e, double x, double y) {
    const auto& a = p[e];
    const auto& b = p[(e + 1) % 3];
    const double ex = b[0] - a[0], ey = b[1] - a[1];
    return ((y - a[1]) * ex - (x - a[0]) * ey) / std::hypot(ex, ey);
  };
  // Make the inside positive whatever the vertex order.
  const double sign = edge_value(0, 24.5, 19.4) > 0 ? 1 : -1;
  const Slice s = MakeSlice(nx, ny, sx, sy, [&](double x, double y) {
    return std::min({sign * edge_value(0, x, y), sign * edge_value(1, x, y),
                     sign * edge_value(2, x, y)});
  });
  const ContourOptions options = Threshold(0);
  const std::vector<float> map = Map(s, options);
  const double band = EffectiveBandRadius(options, sx, sy);
  const double diag = std::hypot(sx, sy);
  int64_t exact_checked = 0;
  for (int64_t j = 0; j < ny; ++j) {
    for (int64_t i = 0; i < nx; ++i) {
      const double x = i * sx, y = j * sy;
      const bool inside = s.at(i, j) >= 0;
      double d = std::numeric_limits<double>::infinity();
      for (int e = 0; e < 3; ++e) {
        d = std::min(d, SegmentDistance(x, y, p[e][0], p[e][1],
                                        p[(e + 1) % 3][0], p[(e + 1) % 3][1]));
      }
      if (d > band - 0.01) continue;
      double to_vertex = std::numeric_limits<double>::infinity();
      for (const auto& v : p) {
        to_vertex = std::min(to_vertex, std::hypot(x - v[0], y - v[1]));
      }
      const float got = map[i + nx * j];
      ASSERT_EQ(got >= 0 && !std::signbit(got), inside) << i << "," << j;
      const double magnitude = std::abs(got);
      if (!inside) {
        EXPECT_GE(magnitude, d - 1e-5) << i << "," << j;
      }
      EXPECT_LE(std::abs(magnitude - d), 3 * diag) << i << "," << j;
      if (to_vertex > d + 3 * diag) {
        EXPECT_NEAR(magnitude, d, 1e-5) << i << "," << j;
        ++exact_checked;
      }
    }
  }
  EXPECT_GT(exact_checked, 2000);
}

TEST(SliceSignedDistanceTest, UpperThresholdAnnulus) {
  // v = r: lower 10, upper 20 gives a ring with two contours.
  const double sx = 0.5, sy = 0.5, cx = 25.1, cy = 24.8;
  const Slice s = MakeSlice(100, 100, sx, sy, [&](double x, double y) {
    return std::hypot(x - cx, y - cy);
  });
  const ContourOptions options = Threshold(10, 20);
  auto segments = ExtractContourSegments(s.v.data(), s.nx, s.ny, options);
  ASSERT_TRUE(segments.ok());
  const double tolerance = CircleTolerance(10, sx, sy);
  double inner_length = 0, outer_length = 0;
  for (const ContourSegment& seg : *segments) {
    const double r0 = std::hypot(seg.i0 * sx - cx, seg.j0 * sy - cy);
    const double r1 = std::hypot(seg.i1 * sx - cx, seg.j1 * sy - cy);
    const double length =
        std::hypot((seg.i1 - seg.i0) * sx, (seg.j1 - seg.j0) * sy);
    if (std::abs(r0 - 10) < tolerance) {
      EXPECT_NEAR(r1, 10, tolerance);
      inner_length += length;
    } else {
      EXPECT_NEAR(r0, 20, tolerance);
      EXPECT_NEAR(r1, 20, tolerance);
      outer_length += length;
    }
  }
  EXPECT_NEAR(inner_length, 2 * M_PI * 10, 0.01 * 2 * M_PI * 10);
  EXPECT_NEAR(outer_length, 2 * M_PI * 20, 0.01 * 2 * M_PI * 20);

  const std::vector<float> map = Map(s, options);
  const double band = EffectiveBandRadius(options, sx, sy);
  int64_t ring_pixels = 0;
  for (int64_t j = 0; j < s.ny; ++j) {
    for (int64_t i = 0; i < s.nx; ++i) {
      const double r = std::hypot(i * sx - cx, j * sy - cy);
      const double expected = std::min(r - 10, 20 - r);
      const float got = map[i + s.nx * j];
      if (std::abs(expected) < 1e-3) continue;
      ASSERT_EQ(got > 0, expected > 0) << i << "," << j;
      if (expected > 0) ++ring_pixels;
      if (std::abs(expected) <= band - tolerance) {
        EXPECT_NEAR(got, expected, tolerance) << i << "," << j;
      }
    }
  }
  EXPECT_GT(ring_pixels, 3000);
  // The middle of the ring is 5 mm from both contours.
  EXPECT_NEAR(map[static_cast<int64_t>(std::round((cx + 15) / sx)) +
                  s.nx * static_cast<int64_t>(std::round(cy / sy))],
              5.0, 0.2);
}

TEST(SliceSignedDistanceTest, EmptyAndFullSlicesHoldTheCap) {
  const double sx = 0.7, sy = 0.5;
  const Slice empty =
      MakeSlice(20, 15, sx, sy, [](double, double) { return -5.0; });
  const Slice full = MakeSlice(20, 15, sx, sy, [](double, double) {
    return 0.0;  // exactly at the threshold: inside
  });
  const ContourOptions options = Threshold(0);
  const float cap = static_cast<float>(16 * 0.7);
  EXPECT_DOUBLE_EQ(EffectiveBandRadius(options, sx, sy), 16 * 0.7);
  for (float x : Map(empty, options)) ASSERT_EQ(x, -cap);
  for (float x : Map(full, options)) ASSERT_EQ(x, cap);
  const ContourOptions banded = Threshold(0, std::nullopt, 3.0);
  for (float x : Map(empty, banded)) ASSERT_EQ(x, -3.0f);
  for (float x : Map(full, banded)) ASSERT_EQ(x, 3.0f);
  auto segments = ExtractContourSegments(full.v.data(), 20, 15, options);
  ASSERT_TRUE(segments.ok());
  EXPECT_TRUE(segments->empty());
}

TEST(SliceSignedDistanceTest, PixelAtThresholdCountsAsInside) {
  const double sx = 0.7, sy = 0.5;
  // An isolated pixel exactly at the threshold among lower values: it is
  // inside, on the contour (0), and its neighbours are one pixel from it.
  // ITK's marching squares drops this zero-length contour; a block of high
  // values far away makes sure the map still has other segments.
  for (const bool with_block : {false, true}) {
    SCOPED_TRACE(with_block);
    Slice s = MakeSlice(30, 30, sx, sy, [&](double x, double y) {
      return with_block && x / sx >= 24 && y / sy >= 24 ? 1.0 : -1.0;
    });
    s.v[4 + 30 * 4] = 0;
    const std::vector<float> map = Map(s, Threshold(0));
    EXPECT_EQ(map[4 + 30 * 4], 0.0f);
    EXPECT_FALSE(std::signbit(map[4 + 30 * 4]));
    EXPECT_NEAR(map[5 + 30 * 4], -sx, 1e-6);
    EXPECT_NEAR(map[4 + 30 * 3], -sy, 1e-6);
    EXPECT_NEAR(map[5 + 30 * 5], -std::hypot(sx, sy), 1e-6);
    EXPECT_NEAR(map[0], -std::hypot(4 * sx, 4 * sy), 1e-6);
  }

  // A column at the threshold on a ramp: 0 and inside there.
  Slice s =
      MakeSlice(12, 6, sx, sy, [&](double x, double) { return x / sx - 5; });
  std::vector<float> map = Map(s, Threshold(0));
  for (int64_t j = 0; j < 6; ++j) {
    for (int64_t i = 0; i < 12; ++i) {
      const float got = map[i + 12 * j];
      EXPECT_NEAR(got, (i - 5) * sx, 1e-6);
      if (i == 5) {
        EXPECT_FALSE(std::signbit(got));
      }
    }
  }

  // Both thresholds are inclusive.
  s = MakeSlice(10, 4, sx, sy, [&](double x, double) { return x / sx; });
  map = Map(s, Threshold(2, 5));
  const std::array<double, 10> expected = {-2, -1, 0, 1, 1, 0, -1, -2, -3, -4};
  for (int64_t i = 0; i < 10; ++i) {
    EXPECT_NEAR(map[i + 10 * 2], expected[i] * sx, 1e-6) << i;
    EXPECT_EQ(std::signbit(map[i + 10 * 2]), expected[i] < 0) << i;
  }
}

TEST(SliceSignedDistanceTest, FarFieldIsMonotoneAcrossTheBandEdge) {
  // A small band: outside it the magnitude never drops below the radius.
  const double sx = 1, sy = 1;
  const Slice s = MakeSlice(80, 80, sx, sy, [](double x, double y) {
    return 12 - std::hypot(x - 40.2, y - 39.6);
  });
  const ContourOptions options = Threshold(0, std::nullopt, 4);
  const std::vector<float> map = Map(s, options);
  for (int64_t j = 0; j < 80; ++j) {
    for (int64_t i = 0; i < 80; ++i) {
      const double expected = 12 - std::hypot(i - 40.2, j - 39.6);
      const float got = map[i + 80 * j];
      if (std::abs(expected) <= 3.9) {
        EXPECT_NEAR(got, expected, 0.05);
      } else if (std::abs(expected) > 4.1) {
        EXPECT_GE(std::abs(got), 4.0f);
        EXPECT_NEAR(got, expected, 1.5);
      }
    }
  }
}

Volume<float> TestVolume() {
  Volume<float> image;
  image.grid.size = {48, 40, 6};
  image.grid.spacing = {0.6, 0.9, 2.5};
  image.grid.origin = {-12.5, 30, 101};
  const double c = std::cos(0.3), s = std::sin(0.3);
  image.grid.direction = {c, -s, 0, s, c, 0, 0, 0, 1};
  image.data.resize(image.grid.VoxelCount());
  for (int64_t k = 0; k < 6; ++k) {
    for (int64_t j = 0; j < 40; ++j) {
      for (int64_t i = 0; i < 48; ++i) {
        const double r = std::hypot(i * 0.6 - 14.1, j * 0.9 - 17.3);
        float v = static_cast<float>(100 * (2.0 * k + 1 - r));
        if (k == 0) v = -100;  // empty
        if (k == 5) v = 50;    // full
        image.at(i, j, k) = v;
      }
    }
  }
  return image;
}

TEST(ComputeSliceDistanceMapsTest, SameResultForAnyThreadCount) {
  const Volume<float> image = TestVolume();
  const ContourOptions options = Threshold(0);
  std::vector<double> fractions;
  ComputeContext one;
  one.threads = 1;
  one.progress = [&](const ProgressEvent& e) {
    EXPECT_EQ(e.stage, "contour");
    fractions.push_back(e.fraction);
  };
  auto a = ComputeSliceDistanceMaps(image, options, one);
  ASSERT_TRUE(a.ok()) << a.status();
  ASSERT_EQ(fractions.size(), 6u);
  EXPECT_TRUE(std::is_sorted(fractions.begin(), fractions.end()));
  EXPECT_DOUBLE_EQ(fractions.back(), 1.0);

  int calls = 0;
  ComputeContext two;
  two.threads = 2;
  two.progress = [&](const ProgressEvent&) { ++calls; };
  auto b = ComputeSliceDistanceMaps(image, options, two);
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_EQ(calls, 6);
  auto automatic = ComputeSliceDistanceMaps(image, options, ComputeContext{});
  ASSERT_TRUE(automatic.ok());

  ASSERT_EQ(a->data.size(), image.data.size());
  EXPECT_EQ(std::memcmp(a->data.data(), b->data.data(),
                        a->data.size() * sizeof(float)),
            0);
  EXPECT_EQ(std::memcmp(a->data.data(), automatic->data.data(),
                        a->data.size() * sizeof(float)),
            0);
  EXPECT_EQ(b->grid.size, image.grid.size);
  EXPECT_EQ(b->grid.spacing, image.grid.spacing);
  EXPECT_EQ(b->grid.origin, image.grid.origin);
  EXPECT_EQ(b->grid.direction, image.grid.direction);

  // Each slice with a contour is the single-slice map with the in-plane
  // spacing.
  const int64_t n = image.grid.SliceVoxelCount();
  std::vector<float> slice(n);
  for (int64_t k = 1; k < 5; ++k) {
    ASSERT_TRUE(SliceSignedDistance(image.data.data() + k * n, 48, 40, 0.6, 0.9,
                                    options, slice.data())
                    .ok());
    EXPECT_EQ(
        std::memcmp(slice.data(), a->data.data() + k * n, n * sizeof(float)), 0)
        << k;
  }
  // End caps: the empty slice 0 and the full slice 5 are one slice (2.5 mm)
  // from a slice with the other state; the in-plane part is the distance to
  // that slice's cross-section (0 inside it).
  for (int64_t p = 0; p < n; ++p) {
    const double out1 = std::max(0.0f, -a->data[1 * n + p]);
    ASSERT_FLOAT_EQ(a->data[p], -std::sqrt(2.5 * 2.5 + out1 * out1)) << p;
    const double in4 = std::max(0.0f, a->data[4 * n + p]);
    ASSERT_FLOAT_EQ(a->data[5 * n + p], std::sqrt(2.5 * 2.5 + in4 * in4)) << p;
  }
}

TEST(ComputeSliceDistanceMapsTest, EndCapsGrowWithDistanceToTheObject) {
  // Object (a disk) only in slice 2 of 6; slices further away are more
  // negative, in steps of the slice spacing.
  Volume<float> image;
  image.grid.size = {20, 20, 6};
  image.grid.spacing = {1, 1, 3};
  image.data.assign(image.grid.VoxelCount(), -100.0f);
  for (int64_t j = 0; j < 20; ++j)
    for (int64_t i = 0; i < 20; ++i)
      image.at(i, j, 2) = static_cast<float>(5 - std::hypot(i - 9.5, j - 9.5));
  const auto maps = ComputeSliceDistanceMaps(image, Threshold(0), {});
  ASSERT_TRUE(maps.ok()) << maps.status();
  // Above the disk (in-plane distance 0): -3 mm per slice of separation.
  const float expected[6] = {-6, -3, 0, -3, -6, -9};
  for (int64_t k : {0, 1, 3, 4, 5}) {
    EXPECT_FLOAT_EQ(maps->at(10, 10, k), expected[k]) << k;
  }
  // Beside it: the 3D distance to the disk's rim, continuous with slice 2's
  // own far field and never crossing zero.
  const double rim = -maps->at(0, 0, 2);
  ASSERT_GT(rim, 5.0);
  for (int64_t k : {0, 1, 3, 4, 5}) {
    const double dz = 3.0 * std::abs(k - 2);
    EXPECT_FLOAT_EQ(maps->at(0, 0, k), -std::sqrt(dz * dz + rim * rim)) << k;
  }
  EXPECT_GT(maps->at(10, 10, 2), 4.0f);  // inside the disk

  // With no slice holding the object at all, the 2D cap remains.
  std::fill(image.data.begin(), image.data.end(), -100.0f);
  const auto empty = ComputeSliceDistanceMaps(image, Threshold(0), {});
  ASSERT_TRUE(empty.ok());
  EXPECT_EQ(empty->at(3, 3, 3), -16.0f);
}

TEST(ComputeSliceDistanceMapsTest, Cancellation) {
  const Volume<float> image = TestVolume();
  CancellationToken token;
  token.Cancel();
  auto result =
      ComputeSliceDistanceMaps(image, Threshold(0), Context(2, &token));
  EXPECT_EQ(result.status().code(), absl::StatusCode::kCancelled);

  CancellationToken expired;
  expired.SetDeadline(std::chrono::steady_clock::now() -
                      std::chrono::seconds(1));
  result = ComputeSliceDistanceMaps(image, Threshold(0), Context(1, &expired));
  EXPECT_EQ(result.status().code(), absl::StatusCode::kDeadlineExceeded);

  // Cancelled while running: polled before the next slice.
  CancellationToken later;
  int reports = 0;
  ComputeContext context = Context(1, &later);
  context.progress = [&](const ProgressEvent&) {
    ++reports;
    later.Cancel();
  };
  result = ComputeSliceDistanceMaps(image, Threshold(0), context);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kCancelled);
  EXPECT_EQ(reports, 1);
}

TEST(ComputeSliceDistanceMapsTest, RejectsBadInputs) {
  const Volume<float> image = TestVolume();
  const ComputeContext context;
  auto code = [&](const Volume<float>& v, const ContourOptions& o) {
    return ComputeSliceDistanceMaps(v, o, context).status().code();
  };
  constexpr auto kInvalid = absl::StatusCode::kInvalidArgument;
  EXPECT_EQ(code(image, Threshold(10, 5)), kInvalid);
  EXPECT_EQ(code(image, Threshold(std::nanf(""))), kInvalid);
  EXPECT_EQ(code(image, Threshold(0, std::nanf(""))), kInvalid);
  EXPECT_EQ(code(image, Threshold(-std::numeric_limits<float>::infinity())),
            kInvalid);
  EXPECT_EQ(code(image, Threshold(0, std::nullopt, std::nan(""))), kInvalid);
  Volume<float> bad = image;
  bad.data.pop_back();
  EXPECT_EQ(code(bad, Threshold(0)), kInvalid);
  bad = image;
  bad.grid.size[2] = 0;
  EXPECT_EQ(code(bad, Threshold(0)), kInvalid);
  bad = image;
  bad.grid.spacing[1] = -1;
  EXPECT_EQ(code(bad, Threshold(0)), kInvalid);
  EXPECT_EQ(code(image, Threshold(5, 5)), absl::StatusCode::kOk);

  std::vector<float> out(4);
  const float v[4] = {0, 1, 2, 3};
  EXPECT_EQ(SliceSignedDistance(v, 2, 2, 1, 0, {}, out.data()).code(),
            kInvalid);
  EXPECT_EQ(SliceSignedDistance(v, 0, 2, 1, 1, {}, out.data()).code(),
            kInvalid);
  EXPECT_EQ(
      SliceSignedDistance(v, 2, 2, 1, 1, Threshold(3, 1), out.data()).code(),
      kInvalid);
  EXPECT_EQ(
      ExtractContourSegments(v, 2, 2, Threshold(std::nanf(""))).status().code(),
      kInvalid);
  EXPECT_EQ(ExtractContourSegments(nullptr, 2, 2, {}).status().code(),
            kInvalid);
}

TEST(SliceSignedDistanceTest, EffectiveBandRadius) {
  EXPECT_DOUBLE_EQ(EffectiveBandRadius({}, 0.5, 0.8), 12.8);
  EXPECT_DOUBLE_EQ(EffectiveBandRadius(Threshold(0, std::nullopt, -1), 2, 1),
                   32);
  EXPECT_DOUBLE_EQ(EffectiveBandRadius(Threshold(0, std::nullopt, 5), 0.5, 0.8),
                   5);
}

TEST(SliceSignedDistanceTest, NonFiniteAndThinSlices) {
  // NaN pixels are outside, infinities are clamped: the map stays finite.
  Slice s = MakeSlice(16, 16, 1, 1, [](double x, double y) {
    return 5 - std::hypot(x - 8, y - 8);
  });
  s.v[8 + 16 * 8] = std::numeric_limits<float>::infinity();
  s.v[0] = std::nanf("");
  s.v[1] = -std::numeric_limits<float>::infinity();
  const std::vector<float> map = Map(s, Threshold(0));
  for (float x : map) ASSERT_TRUE(std::isfinite(x));
  EXPECT_LT(map[0], 0);
  EXPECT_GT(map[8 + 16 * 8], 0);

  // A single row has no marching-squares cell; the mask EDT still signs it.
  const Slice row =
      MakeSlice(6, 1, 1, 1, [](double x, double) { return x - 2.5; });
  const std::vector<float> row_map = Map(row, Threshold(0));
  for (int i = 0; i < 6; ++i) EXPECT_EQ(std::signbit(row_map[i]), i < 3) << i;
}

TEST(SliceSignedDistanceTest, TimingOf512Slice) {
  // Not an assertion on speed: logs the cost of a CT-sized slice with a
  // realistic number of contour segments.
  const double sx = 0.7, sy = 0.7;
  const Slice s = MakeSlice(512, 512, sx, sy, [](double x, double y) {
    const double body = 150 - std::hypot(x - 180, (y - 175) * 1.3);
    const double texture =
        std::cos(x / 4.1) * std::cos(y / 3.7) + 0.4 * std::sin(x / 9 + y / 13);
    return std::min(body, 20 * texture + 5);
  });
  const ContourOptions options = Threshold(0);
  auto segments = ExtractContourSegments(s.v.data(), 512, 512, options);
  ASSERT_TRUE(segments.ok());
  std::vector<float> out(512 * 512);
  ASSERT_TRUE(SliceSignedDistance(s.v.data(), 512, 512, sx, sy, options,
                                  out.data())
                  .ok());  // warm-up
  const auto start = std::chrono::steady_clock::now();
  constexpr int kRuns = 3;
  for (int r = 0; r < kRuns; ++r) {
    ASSERT_TRUE(
        SliceSignedDistance(s.v.data(), 512, 512, sx, sy, options, out.data())
            .ok());
  }
  const double ms = std::chrono::duration<double, std::milli>(
                        std::chrono::steady_clock::now() - start)
                        .count() /
                    kRuns;
  std::printf("512x512 slice, %zu segments, band %.1f mm: %.1f ms\n",
              segments->size(), EffectiveBandRadius(options, sx, sy), ms);
  RecordProperty("segments", static_cast<int>(segments->size()));
  RecordProperty("ms_per_slice", std::to_string(ms));
  EXPECT_GT(segments->size(), 1000u);
}

}  // namespace
}  // namespace interslice

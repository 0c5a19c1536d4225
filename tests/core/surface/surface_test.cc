#include "core/surface/surface.h"

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <map>
#include <numbers>
#include <set>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace interslice {
namespace {

using ::testing::HasSubstr;

constexpr double kPi = std::numbers::pi;
// Largest distance of a vertex from the analytic sphere, mm: 0.05 of the
// largest spacing (0.8 mm) of the test grids.
constexpr double kVertexTolerance = 0.04;

// Rotation by `angle` about the unit axis `u`, row-major.
Mat3 Rotation(Vec3 u, double angle) {
  const double n = std::sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
  for (double& v : u) v /= n;
  const double c = std::cos(angle), s = std::sin(angle), t = 1 - c;
  return {t * u[0] * u[0] + c,        t * u[0] * u[1] - s * u[2],
          t * u[0] * u[2] + s * u[1], t * u[0] * u[1] + s * u[2],
          t * u[1] * u[1] + c,        t * u[1] * u[2] - s * u[0],
          t * u[0] * u[2] - s * u[1], t * u[1] * u[2] + s * u[0],
          t * u[2] * u[2] + c};
}

Grid ObliqueGrid() {
  Grid grid;
  grid.size = {40, 36, 30};
  grid.spacing = {0.5, 0.6, 0.8};
  grid.origin = {-12.5, 30.25, 101.0};
  grid.direction = Rotation({0.3, -0.5, 0.8}, 0.7);
  return grid;
}

// Signed distance to a sphere, positive inside, in mm.
Volume<float> SphereField(const Grid& grid, const Vec3& centre, double radius) {
  Volume<float> field;
  field.grid = grid;
  field.data.resize(grid.VoxelCount());
  for (int64_t k = 0; k < grid.size[2]; ++k) {
    for (int64_t j = 0; j < grid.size[1]; ++j) {
      for (int64_t i = 0; i < grid.size[0]; ++i) {
        const Vec3 p = grid.IndexToPhysical({double(i), double(j), double(k)});
        const double d =
            std::hypot(p[0] - centre[0], p[1] - centre[1], p[2] - centre[2]);
        field.at(i, j, k) = static_cast<float>(radius - d);
      }
    }
  }
  return field;
}

Vec3 GridCentre(const Grid& grid) {
  return grid.IndexToPhysical({(grid.size[0] - 1) / 2.0,
                               (grid.size[1] - 1) / 2.0,
                               (grid.size[2] - 1) / 2.0});
}

// Every undirected edge is shared by exactly two triangles, traversed once in
// each direction (a closed, consistently oriented 2-manifold), and no
// triangle repeats a vertex.
::testing::AssertionResult IsWatertight(const Mesh& mesh) {
  std::map<std::pair<uint32_t, uint32_t>, int> directed;
  for (const auto& t : mesh.triangles) {
    for (int e = 0; e < 3; ++e) {
      const uint32_t a = t[e], b = t[(e + 1) % 3];
      if (a >= mesh.vertices.size()) {
        return ::testing::AssertionFailure() << "vertex index out of range";
      }
      if (a == b) {
        return ::testing::AssertionFailure() << "degenerate triangle";
      }
      ++directed[{a, b}];
    }
  }
  int bad = 0;
  std::string first;
  for (const auto& [edge, count] : directed) {
    const auto reverse = directed.find({edge.second, edge.first});
    const int back = reverse == directed.end() ? 0 : reverse->second;
    if (count != 1 || back != 1) {
      if (bad++ == 0) {
        first = "edge " + std::to_string(edge.first) + "->" +
                std::to_string(edge.second) + " appears " +
                std::to_string(count) + " times, reversed " +
                std::to_string(back) + " times";
      }
    }
  }
  if (bad > 0) {
    return ::testing::AssertionFailure()
           << bad << " bad directed edges of " << directed.size()
           << "; first: " << first;
  }
  return ::testing::AssertionSuccess();
}

// Divergence theorem: positive for outward (counter-clockwise) triangles.
double SignedVolume(const Mesh& mesh) {
  if (mesh.vertices.empty()) return 0;
  const auto& r = mesh.vertices[0];  // reference point, for precision
  double sum = 0;
  for (const auto& t : mesh.triangles) {
    double p[3][3];
    for (int v = 0; v < 3; ++v) {
      for (int c = 0; c < 3; ++c) {
        p[v][c] = double(mesh.vertices[t[v]][c]) - r[c];
      }
    }
    sum += p[0][0] * (p[1][1] * p[2][2] - p[1][2] * p[2][1]) -
           p[0][1] * (p[1][0] * p[2][2] - p[1][2] * p[2][0]) +
           p[0][2] * (p[1][0] * p[2][1] - p[1][1] * p[2][0]);
  }
  return sum / 6;
}

double MaxRadialError(const Mesh& mesh, const Vec3& centre, double radius) {
  double worst = 0;
  for (const auto& v : mesh.vertices) {
    const double d =
        std::hypot(v[0] - centre[0], v[1] - centre[1], v[2] - centre[2]);
    worst = std::max(worst, std::abs(d - radius));
  }
  return worst;
}

TEST(ExtractSurfaceTest, ObliqueAnisotropicSphereIsWatertightOutwardAccurate) {
  const Grid grid = ObliqueGrid();
  // Off-centre, so that a wrong index-to-physical map moves the sphere.
  const Vec3 centre = grid.IndexToPhysical({19.3, 17.1, 15.4});
  const double radius = 7.0;
  const Volume<float> field = SphereField(grid, centre, radius);
  absl::StatusOr<Mesh> mesh = ExtractSurface(field, {}, {});
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  ASSERT_GT(mesh->triangles.size(), 1000u);
  EXPECT_TRUE(IsWatertight(*mesh));
  const double exact = 4.0 / 3.0 * kPi * radius * radius * radius;
  const double volume = SignedVolume(*mesh);
  EXPECT_GT(volume, 0);
  // Vertices are averages of the linearly interpolated edge crossings of
  // their cell, so they sit slightly inside a convex surface: measured
  // 0.022 mm at most (R = 7 mm, 0.5-0.8 mm spacing) and 1% of the volume.
  EXPECT_NEAR(volume / exact, 0.99, 0.01);
  EXPECT_LT(MaxRadialError(*mesh, centre, radius), kVertexTolerance);
}

// A thick spherical shell: away from the surface the narrow band holds no
// leaves, the solid part as inside tiles and the cavity and the outside as
// background; a tile with the wrong sign would add surfaces along leaf
// borders (more area, less volume, or open edges).
TEST(ExtractSurfaceTest, ThickShellFromTheNarrowBandIsExact) {
  Grid grid;
  grid.size = {72, 70, 68};
  grid.spacing = {1.0, 1.0, 1.0};
  const Vec3 centre = {35.3, 34.6, 33.9};
  const double outer = 30.0, inner = 12.0;
  Volume<float> field;
  field.grid = grid;
  field.data.resize(grid.VoxelCount());
  for (int64_t k = 0; k < grid.size[2]; ++k) {
    for (int64_t j = 0; j < grid.size[1]; ++j) {
      for (int64_t i = 0; i < grid.size[0]; ++i) {
        const double d =
            std::hypot(i - centre[0], j - centre[1], k - centre[2]);
        field.at(i, j, k) = static_cast<float>(std::min(outer - d, d - inner));
      }
    }
  }
  absl::StatusOr<Mesh> mesh = ExtractSurface(field, {}, {});
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  EXPECT_TRUE(IsWatertight(*mesh));
  const double exact =
      4.0 / 3.0 * kPi * (outer * outer * outer - inner * inner * inner);
  EXPECT_NEAR(SignedVolume(*mesh) / exact, 1.0, 0.01);
  double area = 0;
  for (const auto& t : mesh->triangles) {
    const auto& a = mesh->vertices[t[0]];
    const auto& b = mesh->vertices[t[1]];
    const auto& c = mesh->vertices[t[2]];
    const double u[3] = {b[0] - a[0], b[1] - a[1], b[2] - a[2]};
    const double v[3] = {c[0] - a[0], c[1] - a[1], c[2] - a[2]};
    area +=
        0.5 * std::hypot(u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2],
                         u[0] * v[1] - u[1] * v[0]);
  }
  // Marching-cubes facets overestimate a smooth area by a few percent.
  const double exact_area = 4 * kPi * (outer * outer + inner * inner);
  EXPECT_GT(area / exact_area, 0.99);
  EXPECT_LT(area / exact_area, 1.10);
}

TEST(ExtractSurfaceTest, IsovalueSelectsTheLevel) {
  const Grid grid = ObliqueGrid();
  const Vec3 centre = GridCentre(grid);
  const Volume<float> field = SphereField(grid, centre, 8.0);
  SurfaceOptions options;
  options.isovalue = 2.0;  // the sphere of radius 6
  absl::StatusOr<Mesh> mesh = ExtractSurface(field, options, {});
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  EXPECT_TRUE(IsWatertight(*mesh));
  EXPECT_LT(MaxRadialError(*mesh, centre, 6.0), kVertexTolerance);
  EXPECT_NEAR(SignedVolume(*mesh) / (4.0 / 3.0 * kPi * 216), 0.99, 0.01);
}

TEST(ExtractSurfaceTest, MirroredDirectionStaysOutward) {
  Grid grid = ObliqueGrid();
  for (int r = 0; r < 3; ++r) grid.direction[3 * r + 1] *= -1;  // det < 0
  const Vec3 centre = GridCentre(grid);
  const double radius = 7.0;
  absl::StatusOr<Mesh> mesh =
      ExtractSurface(SphereField(grid, centre, radius), {}, {});
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  EXPECT_TRUE(IsWatertight(*mesh));
  EXPECT_NEAR(
      SignedVolume(*mesh) / (4.0 / 3.0 * kPi * radius * radius * radius), 0.99,
      0.01);
  EXPECT_LT(MaxRadialError(*mesh, centre, radius), kVertexTolerance);
}

TEST(ExtractSurfaceTest, ShapeCutByTheGridBoundaryIsClosed) {
  const Grid grid = ObliqueGrid();
  // Centre on the i = 0 face: half of the ball lies outside the grid.
  const Vec3 centre = grid.IndexToPhysical({0.0, 17.5, 14.5});
  const double radius = 7.0;
  absl::StatusOr<Mesh> mesh =
      ExtractSurface(SphereField(grid, centre, radius), {}, {});
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  EXPECT_TRUE(IsWatertight(*mesh));
  // Half a ball, closed by a cap at most one voxel (0.5 mm along i) outside
  // the i = 0 face.
  const double half = 2.0 / 3.0 * kPi * radius * radius * radius;
  const double volume = SignedVolume(*mesh);
  EXPECT_GT(volume, 0.99 * half);
  EXPECT_LT(volume, half + kPi * radius * radius * grid.spacing[0]);
}

TEST(ExtractSurfaceTest, PositiveEverywhereGivesTheClosedGridBox) {
  for (bool mirrored : {false, true}) {
    Grid grid = ObliqueGrid();
    if (mirrored) {
      for (int r = 0; r < 3; ++r) grid.direction[3 * r + 2] *= -1;
    }
    Volume<float> field;
    field.grid = grid;
    field.data.assign(grid.VoxelCount(), 5.0f);
    absl::StatusOr<Mesh> mesh = ExtractSurface(field, {}, {});
    ASSERT_TRUE(mesh.ok()) << mesh.status();
    EXPECT_TRUE(IsWatertight(*mesh)) << "mirrored " << mirrored;
    // Between the box of voxel centres and that box grown by one voxel.
    double inner = 1, outer = 1;
    for (int a = 0; a < 3; ++a) {
      inner *= (grid.size[a] - 1) * grid.spacing[a];
      outer *= (grid.size[a] + 1) * grid.spacing[a];
    }
    const double volume = SignedVolume(*mesh);
    EXPECT_GT(volume, inner) << "mirrored " << mirrored;
    EXPECT_LT(volume, outer) << "mirrored " << mirrored;
  }
}

TEST(ExtractSurfaceTest, AdaptivityMergesTrianglesAndStaysClosed) {
  const Grid grid = ObliqueGrid();
  const Vec3 centre = GridCentre(grid);
  const double radius = 8.0;
  const Volume<float> field = SphereField(grid, centre, radius);
  absl::StatusOr<Mesh> fine = ExtractSurface(field, {}, {});
  SurfaceOptions options;
  options.adaptivity = 0.5;
  absl::StatusOr<Mesh> coarse = ExtractSurface(field, options, {});
  ASSERT_TRUE(fine.ok()) << fine.status();
  ASSERT_TRUE(coarse.ok()) << coarse.status();
  // OpenVDB merges aggressively on a smooth sphere: measured 6388 -> 182
  // triangles, still closed and consistently oriented, 17% of the volume
  // lost to large chords, vertices up to 0.34 mm (0.43 voxel) inside.
  EXPECT_LT(coarse->triangles.size(), fine->triangles.size() / 4);
  EXPECT_TRUE(IsWatertight(*coarse));
  const double exact = 4.0 / 3.0 * kPi * radius * radius * radius;
  const double ratio = SignedVolume(*coarse) / exact;
  EXPECT_GT(ratio, 0.78);
  EXPECT_LT(ratio, 1.0);
  EXPECT_LT(MaxRadialError(*coarse, centre, radius), 0.6 * 0.8);
}

// The deviation of a simplified sphere from the full one agrees with the
// analytic distance of the same sample points to the sphere; a mesh against
// itself deviates by (almost) nothing, one shifted by 1 mm by 1 mm.
TEST(MeasureMeshDeviationTest, AgreesWithTheAnalyticDistanceToASphere) {
  const Grid grid = ObliqueGrid();
  const Vec3 centre = GridCentre(grid);
  const double radius = 8.0;
  const Volume<float> field = SphereField(grid, centre, radius);
  absl::StatusOr<Mesh> fine = ExtractSurface(field, {}, {});
  SurfaceOptions options;
  options.adaptivity = 0.5;
  absl::StatusOr<Mesh> coarse = ExtractSurface(field, options, {});
  ASSERT_TRUE(fine.ok() && coarse.ok());
  const double resolution = 0.2;
  absl::StatusOr<MeshDeviation> deviation =
      MeasureMeshDeviation(*coarse, *fine, resolution, {});
  ASSERT_TRUE(deviation.ok()) << deviation.status();
  // The same samples (vertices, edge midpoints, centroids), measured to the
  // exact sphere.
  double analytic = 0;
  auto distance = [&](double x, double y, double z) {
    return std::abs(std::hypot(x - centre[0], y - centre[1], z - centre[2]) -
                    radius);
  };
  for (const auto& t : coarse->triangles) {
    const auto& a = coarse->vertices[t[0]];
    const auto& b = coarse->vertices[t[1]];
    const auto& c = coarse->vertices[t[2]];
    analytic = std::max(
        {analytic, distance(a[0], a[1], a[2]),
         distance((a[0] + b[0]) / 2, (a[1] + b[1]) / 2, (a[2] + b[2]) / 2),
         distance((a[0] + b[0] + c[0]) / 3, (a[1] + b[1] + c[1]) / 3,
                  (a[2] + b[2] + c[2]) / 3)});
  }
  // The full mesh is itself within ~0.05 mm of the sphere (chords of 0.5 mm
  // voxels), and the grid within half a voxel.
  EXPECT_GT(analytic, 0.3);
  EXPECT_NEAR(deviation->max_mm, analytic, resolution / 2 + 0.06);
  EXPECT_GT(deviation->mean_mm, 0);
  EXPECT_LT(deviation->mean_mm, deviation->max_mm);
  EXPECT_EQ(deviation->samples,
            static_cast<int64_t>(7 * coarse->triangles.size()));

  absl::StatusOr<MeshDeviation> same =
      MeasureMeshDeviation(*fine, *fine, resolution, {});
  ASSERT_TRUE(same.ok());
  EXPECT_LT(same->max_mm, resolution / 2);

  Mesh shifted = *fine;
  for (auto& v : shifted.vertices) v[0] += 1.0f;
  absl::StatusOr<MeshDeviation> moved =
      MeasureMeshDeviation(shifted, *fine, resolution, {});
  ASSERT_TRUE(moved.ok());
  EXPECT_NEAR(moved->max_mm, 1.0, resolution / 2 + 0.06);
  EXPECT_EQ(moved->beyond_band, 0);
  // Farther than the band (2 mm): counted, and max_mm is the band.
  for (auto& v : shifted.vertices) v[0] += 9.0f;
  moved = MeasureMeshDeviation(shifted, *fine, resolution, {});
  ASSERT_TRUE(moved.ok());
  EXPECT_GT(moved->beyond_band, 0);
  EXPECT_DOUBLE_EQ(moved->max_mm, moved->band_mm);
  EXPECT_NEAR(moved->band_mm, 2.0, 1e-9);  // 10 voxels

  EXPECT_EQ(MeasureMeshDeviation(*coarse, *fine, 0, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(MeasureMeshDeviation(*coarse, Mesh(), 0.1, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
}

// Regression: 2D distance maps are exactly 0 on pixels lying on the contour
// (CT values equal to the threshold). Such samples used to put the vertices
// of all their edges at one point: distinct vertices at identical positions,
// degenerate triangles, and non-manifold edges once welded (seen on the CT
// phantom skull).
TEST(ExtractSurfaceTest, SamplesExactlyAtTheIsovalueGiveNoCoincidentVertices) {
  Grid grid;
  grid.size = {12, 12, 12};
  grid.spacing = {0.45, 0.45, 0.45};
  grid.origin = {-115.5, -1.85, 696.21};  // patient-scale coordinates
  Volume<float> field;
  field.grid = grid;
  field.data.resize(grid.VoxelCount());
  // A box with faces through voxel centres: exactly 0 on whole planes.
  for (int64_t k = 0; k < 12; ++k)
    for (int64_t j = 0; j < 12; ++j)
      for (int64_t i = 0; i < 12; ++i)
        field.at(i, j, k) = static_cast<float>(
            3 - std::max({std::abs(i - 5), std::abs(j - 6), std::abs(k - 5)}));
  const auto mesh = ExtractSurface(field, {}, {});
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  ASSERT_FALSE(mesh->triangles.empty());
  std::set<std::array<float, 3>> positions(mesh->vertices.begin(),
                                           mesh->vertices.end());
  EXPECT_EQ(positions.size(), mesh->vertices.size())
      << "distinct vertices share a position";
  EXPECT_TRUE(IsWatertight(*mesh));
  // The surface stays on the box faces to a thousandth of a voxel.
  for (const auto& v : mesh->vertices) {
    const Vec3 index = grid.PhysicalToIndex({v[0], v[1], v[2]});
    const double d = std::max({std::abs(index[0] - 5), std::abs(index[1] - 6),
                               std::abs(index[2] - 5)});
    EXPECT_NEAR(d, 3.0, 0.01);
  }
}

TEST(ExtractSurfaceTest, NoCrossingGivesAnEmptyMesh) {
  Volume<float> field;
  field.grid = ObliqueGrid();
  field.data.assign(field.grid.VoxelCount(), -1.0f);
  absl::StatusOr<Mesh> mesh = ExtractSurface(field, {}, {});
  ASSERT_TRUE(mesh.ok()) << mesh.status();
  EXPECT_TRUE(mesh->vertices.empty());
  EXPECT_TRUE(mesh->triangles.empty());
}

TEST(ExtractSurfaceTest, RejectsInvalidInput) {
  const Grid grid = ObliqueGrid();
  Volume<float> field = SphereField(grid, GridCentre(grid), 5.0);

  Volume<float> nan = field;
  nan.at(3, 4, 5) = std::nanf("");
  absl::StatusOr<Mesh> mesh = ExtractSurface(nan, {}, {});
  EXPECT_EQ(mesh.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(mesh.status().message(), HasSubstr("(3, 4, 5)"));

  SurfaceOptions options;
  options.adaptivity = 1.5;
  EXPECT_EQ(ExtractSurface(field, options, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
  options.adaptivity = -0.1;
  EXPECT_EQ(ExtractSurface(field, options, {}).status().code(),
            absl::StatusCode::kInvalidArgument);

  Volume<float> short_data = field;
  short_data.data.pop_back();
  EXPECT_EQ(ExtractSurface(short_data, {}, {}).status().code(),
            absl::StatusCode::kInvalidArgument);

  Volume<float> empty;
  EXPECT_EQ(ExtractSurface(empty, {}, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(ExtractSurfaceTest, CancelledBeforeStart) {
  const Grid grid = ObliqueGrid();
  CancellationToken token;
  token.Cancel();
  ComputeContext context;
  context.cancel = &token;
  EXPECT_EQ(
      ExtractSurface(SphereField(grid, GridCentre(grid), 5.0), {}, context)
          .status()
          .code(),
      absl::StatusCode::kCancelled);
}

TEST(ExtractSurfaceTest, ReportsProgressAndIsIndependentOfThreads) {
  const Grid grid = ObliqueGrid();
  const Volume<float> field = SphereField(grid, GridCentre(grid), 8.0);
  std::vector<ProgressEvent> events;
  ComputeContext one;
  one.threads = 1;
  one.progress = [&](const ProgressEvent& e) { events.push_back(e); };
  ComputeContext two;
  two.threads = 2;
  for (double adaptivity : {0.0, 0.5}) {
    SurfaceOptions options;
    options.adaptivity = adaptivity;
    absl::StatusOr<Mesh> a = ExtractSurface(field, options, one);
    absl::StatusOr<Mesh> b = ExtractSurface(field, options, two);
    ASSERT_TRUE(a.ok() && b.ok());
    EXPECT_EQ(a->vertices, b->vertices) << "adaptivity " << adaptivity;
    EXPECT_EQ(a->triangles, b->triangles) << "adaptivity " << adaptivity;
  }
  ASSERT_FALSE(events.empty());
  EXPECT_EQ(events.front().stage, "mesh");
  EXPECT_EQ(events.front().fraction, 0.0);
  EXPECT_EQ(events.back().stage, "mesh");
  EXPECT_EQ(events.back().fraction, 1.0);
}

// A sphere of radius 12 mm on an oblique anisotropic 0.5-0.8 mm grid:
// about 14 000 marching-cubes triangles.
struct SimplifyFixture {
  Grid grid;
  Vec3 centre;
  double radius = 12.0;
  Mesh full;
};

SimplifyFixture LargeSphere() {
  SimplifyFixture f;
  f.grid = ObliqueGrid();
  f.grid.size = {60, 52, 40};
  f.centre = GridCentre(f.grid);
  absl::StatusOr<Mesh> full =
      ExtractSurface(SphereField(f.grid, f.centre, f.radius), {}, {});
  EXPECT_TRUE(full.ok()) << full.status();
  if (full.ok()) f.full = *std::move(full);
  return f;
}

bool EveryVertexUsed(const Mesh& mesh) {
  std::vector<bool> used(mesh.vertices.size(), false);
  for (const auto& t : mesh.triangles) {
    for (uint32_t v : t) used[v] = true;
  }
  return std::all_of(used.begin(), used.end(), [](bool u) { return u; });
}

// The triangle cap is met, the surface stays closed, outward and on the
// sphere, and meshoptimizer's error estimate is of the order of the measured
// deviation (not a bound: the measured maximum may exceed it, by at most the
// factor stated here plus the measurement's half voxel).
TEST(SimplifyMeshTest, CapIsMetClosedOutwardAndErrorMatchesMeasurement) {
  const SimplifyFixture f = LargeSphere();
  const int64_t before = static_cast<int64_t>(f.full.triangles.size());
  ASSERT_GT(before, 10000);
  for (const int64_t cap : {before / 4, before / 16}) {
    SCOPED_TRACE(cap);
    absl::StatusOr<SimplifiedMesh> simplified =
        SimplifyMesh(f.full, {.max_triangles = cap}, {});
    ASSERT_TRUE(simplified.ok()) << simplified.status();
    const Mesh& mesh = simplified->mesh;
    EXPECT_EQ(simplified->triangles_before, before);
    EXPECT_EQ(simplified->triangles_after,
              static_cast<int64_t>(mesh.triangles.size()));
    EXPECT_LE(simplified->triangles_after, cap);
    // Edge collapses remove two triangles each: it stops just under the cap.
    EXPECT_GT(simplified->triangles_after, cap * 9 / 10);
    EXPECT_TRUE(IsWatertight(mesh));
    EXPECT_TRUE(EveryVertexUsed(mesh));
    EXPECT_LT(mesh.vertices.size(), f.full.vertices.size());
    // Outward (positive), and the volume of an inscribed polyhedron: measured
    // 0.995 of the sphere at 3588 triangles, 0.983 at 896.
    const double exact = 4.0 / 3.0 * kPi * std::pow(f.radius, 3);
    EXPECT_GT(SignedVolume(mesh) / exact, 0.97);
    EXPECT_LT(SignedVolume(mesh) / exact, 1.01);
    // Vertices stay within a fraction of the finest voxel (0.5 mm).
    EXPECT_LT(MaxRadialError(mesh, f.centre, f.radius), 0.25);

    // Measured: error 0.025 mm at 3588 triangles, 0.11 mm at 896, against a
    // grid-measured max of 0.10 and 0.18 mm (the grid errs high by up to
    // half its 0.2 mm voxel next to the surface).
    EXPECT_GT(simplified->error_mm, 0);
    EXPECT_LT(simplified->error_mm, 0.25);
    const double resolution = 0.2;
    absl::StatusOr<MeshDeviation> deviation =
        MeasureMeshDeviation(mesh, f.full, resolution, {});
    ASSERT_TRUE(deviation.ok()) << deviation.status();
    EXPECT_EQ(deviation->beyond_band, 0);
    EXPECT_LE(deviation->max_mm, 3 * simplified->error_mm + resolution / 2);
    EXPECT_GE(deviation->max_mm, simplified->error_mm / 3);
  }
}

// An error budget alone stops the collapses at that estimate.
TEST(SimplifyMeshTest, ErrorBudgetAloneStopsAtTheBudget) {
  const SimplifyFixture f = LargeSphere();
  absl::StatusOr<SimplifiedMesh> loose =
      SimplifyMesh(f.full, {.max_error_mm = 0.1}, {});
  absl::StatusOr<SimplifiedMesh> tight =
      SimplifyMesh(f.full, {.max_error_mm = 0.01}, {});
  ASSERT_TRUE(loose.ok() && tight.ok());
  EXPECT_LE(loose->error_mm, 0.1);
  EXPECT_LE(tight->error_mm, 0.01);
  EXPECT_LT(loose->triangles_after, tight->triangles_after);
  EXPECT_LT(tight->triangles_after, loose->triangles_before);
  EXPECT_TRUE(IsWatertight(loose->mesh));
  EXPECT_TRUE(IsWatertight(tight->mesh));
  // With a count too: the first target reached stops it.
  absl::StatusOr<SimplifiedMesh> both =
      SimplifyMesh(f.full, {.max_triangles = 100, .max_error_mm = 0.01}, {});
  ASSERT_TRUE(both.ok());
  EXPECT_GT(both->triangles_after, 100);
  EXPECT_LE(both->error_mm, 0.01);
}

// Within the cap (or nothing asked): the same triangles, compacted.
TEST(SimplifyMeshTest, WithinTheCapIsUnchangedButCompacted) {
  Mesh mesh = LargeSphere().full;
  const int64_t count = static_cast<int64_t>(mesh.triangles.size());
  mesh.vertices.insert(mesh.vertices.begin(), {1e3f, 1e3f, 1e3f});  // unused
  for (auto& t : mesh.triangles) {
    for (uint32_t& v : t) ++v;
  }
  for (const SimplifyOptions& options :
       {SimplifyOptions{.max_triangles = count}, SimplifyOptions{}}) {
    absl::StatusOr<SimplifiedMesh> same = SimplifyMesh(mesh, options, {});
    ASSERT_TRUE(same.ok());
    EXPECT_EQ(same->triangles_after, count);
    EXPECT_EQ(same->error_mm, 0);
    EXPECT_EQ(same->mesh.vertices.size(), mesh.vertices.size() - 1);
    EXPECT_TRUE(EveryVertexUsed(same->mesh));
    EXPECT_TRUE(IsWatertight(same->mesh));
    // Triangle by triangle, the same corners.
    for (size_t t = 0; t < mesh.triangles.size(); t += 997) {
      for (int k = 0; k < 3; ++k) {
        EXPECT_EQ(same->mesh.vertices[same->mesh.triangles[t][k]],
                  mesh.vertices[mesh.triangles[t][k]]);
      }
    }
  }
  absl::StatusOr<SimplifiedMesh> empty =
      SimplifyMesh(Mesh(), {.max_triangles = 10}, {});
  ASSERT_TRUE(empty.ok());
  EXPECT_TRUE(empty->mesh.triangles.empty());
  EXPECT_TRUE(empty->mesh.vertices.empty());
}

TEST(SimplifyMeshTest, RejectsInvalidInputAndHonoursCancellation) {
  const Mesh mesh = LargeSphere().full;
  EXPECT_EQ(SimplifyMesh(mesh, {.max_triangles = -1}, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(SimplifyMesh(mesh, {.max_error_mm = -0.1}, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(
      SimplifyMesh(mesh, {.max_error_mm = std::nan("")}, {}).status().code(),
      absl::StatusCode::kInvalidArgument);
  Mesh bad = mesh;
  bad.triangles[5][1] = static_cast<uint32_t>(bad.vertices.size());
  absl::Status status = SimplifyMesh(bad, {.max_triangles = 100}, {}).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr("out of range"));
  bad = mesh;
  bad.vertices[3][2] = std::numeric_limits<float>::infinity();
  EXPECT_EQ(SimplifyMesh(bad, {.max_triangles = 100}, {}).status().code(),
            absl::StatusCode::kInvalidArgument);

  CancellationToken token;
  token.Cancel();
  ComputeContext context;
  context.cancel = &token;
  EXPECT_EQ(SimplifyMesh(mesh, {.max_triangles = 100}, context).status().code(),
            absl::StatusCode::kCancelled);
}

// Not run by default: prints the time of a 256^3 sphere.
TEST(ExtractSurfaceTest, DISABLED_Time256Sphere) {
  Grid grid;
  grid.size = {256, 256, 256};
  const Volume<float> field = SphereField(grid, GridCentre(grid), 100.0);
  for (int threads : {1, 2}) {
    ComputeContext context;
    context.threads = threads;
    const auto start = std::chrono::steady_clock::now();
    absl::StatusOr<Mesh> mesh = ExtractSurface(field, {}, context);
    const std::chrono::duration<double> seconds =
        std::chrono::steady_clock::now() - start;
    ASSERT_TRUE(mesh.ok());
    std::printf(
        "256^3 sphere, %d thread(s): %.3f s, %zu vertices, %zu "
        "triangles\n",
        threads, seconds.count(), mesh->vertices.size(),
        mesh->triangles.size());
  }
}

// ---------------------------------------------------------------------------
// Writers.

class MeshWriterTest : public ::testing::Test {
 protected:
  void SetUp() override {
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    dir_ = std::filesystem::path(::testing::TempDir()) /
           (std::string("surface_test_") + info->name());
    std::filesystem::remove_all(dir_);
    std::filesystem::create_directories(dir_);
  }
  void TearDown() override { std::filesystem::remove_all(dir_); }

  std::string Path(const std::string& name) const { return dir_ / name; }

  std::vector<std::string> DirectoryEntries() const {
    std::vector<std::string> names;
    for (const auto& entry : std::filesystem::directory_iterator(dir_)) {
      names.push_back(entry.path().filename().string());
    }
    std::sort(names.begin(), names.end());
    return names;
  }

  std::filesystem::path dir_;
};

// A unit-ish cube at a non-trivial position, outward counter-clockwise.
Mesh Cube() {
  Mesh mesh;
  for (int v = 0; v < 8; ++v) {
    mesh.vertices.push_back({-10.25f + 2.5f * (v & 1),
                             3.125f + 2.5f * ((v >> 1) & 1),
                             100.0f + 2.5f * ((v >> 2) & 1)});
  }
  mesh.triangles = {{0, 2, 1}, {1, 2, 3}, {4, 5, 6}, {5, 7, 6},
                    {0, 1, 4}, {1, 5, 4}, {2, 6, 3}, {3, 6, 7},
                    {0, 4, 2}, {2, 4, 6}, {1, 3, 5}, {3, 7, 5}};
  return mesh;
}

std::string ReadFile(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  return std::string(std::istreambuf_iterator<char>(in), {});
}

template <typename T>
T Get(const std::string& bytes, size_t& offset) {
  T value;
  std::memcpy(&value, bytes.data() + offset, sizeof(T));  // little-endian host
  offset += sizeof(T);
  return value;
}

TEST_F(MeshWriterTest, CubeIsWatertightAndOutward) {
  EXPECT_TRUE(IsWatertight(Cube()));
  EXPECT_NEAR(SignedVolume(Cube()), 2.5 * 2.5 * 2.5, 1e-4);
}

TEST_F(MeshWriterTest, StlRoundTrip) {
  const Mesh mesh = Cube();
  ASSERT_TRUE(WriteStl(mesh, Path("cube.stl")).ok());
  const std::string bytes = ReadFile(Path("cube.stl"));
  ASSERT_EQ(bytes.size(), 80u + 4u + 50u * mesh.triangles.size());
  EXPECT_NE(bytes.substr(0, 5), "solid");
  size_t offset = 80;
  ASSERT_EQ(Get<uint32_t>(bytes, offset), mesh.triangles.size());
  for (const auto& t : mesh.triangles) {
    std::array<float, 3> normal;
    for (float& v : normal) v = Get<float>(bytes, offset);
    // Outward unit normal of an axis-aligned cube face.
    const auto& a = mesh.vertices[t[0]];
    double len = 0;
    for (int c = 0; c < 3; ++c) len += normal[c] * normal[c];
    EXPECT_NEAR(len, 1.0, 1e-6);
    const std::array<float, 3> mid = {-9.0f, 4.375f, 101.25f};
    double dot = 0;
    for (int c = 0; c < 3; ++c) dot += normal[c] * (a[c] - mid[c]);
    EXPECT_NEAR(dot, 1.25, 1e-5);
    for (uint32_t i : t) {
      for (int c = 0; c < 3; ++c) {
        EXPECT_EQ(Get<float>(bytes, offset), mesh.vertices[i][c]);
      }
    }
    EXPECT_EQ(Get<uint16_t>(bytes, offset), 0);
  }
  EXPECT_EQ(DirectoryEntries(), std::vector<std::string>{"cube.stl"});
}

TEST_F(MeshWriterTest, PlyRoundTrip) {
  const Mesh mesh = Cube();
  ASSERT_TRUE(WritePly(mesh, Path("cube.ply")).ok());
  const std::string bytes = ReadFile(Path("cube.ply"));
  const std::string end = "end_header\n";
  const size_t header_end = bytes.find(end);
  ASSERT_NE(header_end, std::string::npos);
  const std::string header = bytes.substr(0, header_end + end.size());
  EXPECT_EQ(header.rfind("ply\nformat binary_little_endian 1.0\n", 0), 0u);
  EXPECT_THAT(header, HasSubstr("element vertex 8\nproperty float x\n"
                                "property float y\nproperty float z\n"));
  EXPECT_THAT(header, HasSubstr("element face 12\nproperty list uchar uint "
                                "vertex_indices\n"));
  ASSERT_EQ(bytes.size(), header.size() + 12u * 8 + 13u * 12);
  size_t offset = header.size();
  for (const auto& v : mesh.vertices) {
    for (int c = 0; c < 3; ++c) EXPECT_EQ(Get<float>(bytes, offset), v[c]);
  }
  for (const auto& t : mesh.triangles) {
    EXPECT_EQ(Get<uint8_t>(bytes, offset), 3);
    for (uint32_t i : t) EXPECT_EQ(Get<uint32_t>(bytes, offset), i);
  }
}

TEST_F(MeshWriterTest, ObjRoundTrip) {
  const Mesh mesh = Cube();
  // WriteMesh dispatches on the extension, case-insensitively.
  ASSERT_TRUE(WriteMesh(mesh, Path("cube.OBJ")).ok());
  std::istringstream in(ReadFile(Path("cube.OBJ")));
  Mesh read;
  std::string line;
  while (std::getline(in, line)) {
    std::istringstream fields(line);
    std::string tag;
    fields >> tag;
    if (tag == "v") {
      std::array<float, 3> v;
      fields >> v[0] >> v[1] >> v[2];
      read.vertices.push_back(v);
    } else if (tag == "f") {
      std::array<uint32_t, 3> t;
      fields >> t[0] >> t[1] >> t[2];
      for (uint32_t& i : t) i -= 1;  // 1-based
      read.triangles.push_back(t);
    } else {
      EXPECT_EQ(tag.substr(0, 1), "#") << line;
    }
  }
  EXPECT_EQ(read.vertices, mesh.vertices);
  EXPECT_EQ(read.triangles, mesh.triangles);
}

TEST_F(MeshWriterTest, WriteMeshDispatchesAndOverwrites) {
  const Mesh mesh = Cube();
  ASSERT_TRUE(WriteMesh(mesh, Path("a.Stl")).ok());
  ASSERT_TRUE(WriteMesh(mesh, Path("a.Stl")).ok());  // replaces it
  ASSERT_TRUE(WriteMesh(mesh, Path("b.PLY")).ok());
  EXPECT_EQ(ReadFile(Path("a.Stl")).size(), 80u + 4u + 50u * 12);
  EXPECT_EQ(ReadFile(Path("b.PLY")).substr(0, 4), "ply\n");
  EXPECT_EQ(DirectoryEntries(), (std::vector<std::string>{"a.Stl", "b.PLY"}));
}

TEST_F(MeshWriterTest, EmptyMeshIsWritten) {
  ASSERT_TRUE(WriteStl(Mesh{}, Path("empty.stl")).ok());
  EXPECT_EQ(ReadFile(Path("empty.stl")).size(), 84u);
}

TEST_F(MeshWriterTest, UnknownExtensionIsInvalid) {
  for (const char* name : {"cube.vtk", "cube", "cube.stl.gz"}) {
    const absl::Status status = WriteMesh(Cube(), Path(name));
    EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << name;
    EXPECT_THAT(status.message(), HasSubstr(name));
  }
  EXPECT_TRUE(DirectoryEntries().empty());
}

TEST_F(MeshWriterTest, BadTriangleIndexIsInvalid) {
  Mesh mesh = Cube();
  mesh.triangles.push_back({0, 1, 8});
  EXPECT_EQ(WritePly(mesh, Path("bad.ply")).code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(DirectoryEntries().empty());
}

TEST_F(MeshWriterTest, MissingDirectoryNamesThePathAndLeavesNoTemporary) {
  for (const char* name : {"x.stl", "x.ply", "x.obj"}) {
    const std::string path = Path("missing/") + name;
    const absl::Status status = WriteMesh(Cube(), path);
    EXPECT_FALSE(status.ok());
    EXPECT_THAT(status.message(), HasSubstr(path));
  }
  EXPECT_TRUE(DirectoryEntries().empty());
}

TEST_F(MeshWriterTest, RenameFailureLeavesNoTemporary) {
  // The target is a non-empty directory, so the final rename fails.
  std::filesystem::create_directories(Path("target.stl/sub"));
  const absl::Status status = WriteStl(Cube(), Path("target.stl"));
  EXPECT_EQ(status.code(), absl::StatusCode::kInternal);
  EXPECT_THAT(status.message(), HasSubstr(Path("target.stl")));
  EXPECT_EQ(DirectoryEntries(), std::vector<std::string>{"target.stl"});
}

}  // namespace
}  // namespace interslice

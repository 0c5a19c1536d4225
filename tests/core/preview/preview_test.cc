#include "core/preview/preview.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <random>
#include <set>

namespace interslice {
namespace {

using ::testing::HasSubstr;
using ::testing::SizeIs;

constexpr std::array<uint8_t, 3> kGreen = {60, 230, 60};
constexpr std::array<uint8_t, 3> kBlue = {40, 110, 255};

Grid MakeGrid(Index3 size, Vec3 spacing, Mat3 direction = kIdentityDirection,
              Vec3 origin = {0, 0, 0}) {
  Grid g;
  g.size = size;
  g.spacing = spacing;
  g.direction = direction;
  g.origin = origin;
  return g;
}

// A signed distance field (mm, positive inside) of a union of spheres.
struct Sphere {
  Vec3 centre;  // LPS mm
  double radius;
};
Volume<float> SphereField(const Grid& grid, const std::vector<Sphere>& balls) {
  Volume<float> f{grid, std::vector<float>(grid.VoxelCount())};
  for (int64_t k = 0; k < grid.size[2]; ++k) {
    for (int64_t j = 0; j < grid.size[1]; ++j) {
      for (int64_t i = 0; i < grid.size[0]; ++i) {
        const Vec3 p = grid.IndexToPhysical({static_cast<double>(i),
                                             static_cast<double>(j),
                                             static_cast<double>(k)});
        double best = -1e9;
        for (const Sphere& s : balls) {
          const double d =
              std::sqrt((p[0] - s.centre[0]) * (p[0] - s.centre[0]) +
                        (p[1] - s.centre[1]) * (p[1] - s.centre[1]) +
                        (p[2] - s.centre[2]) * (p[2] - s.centre[2]));
          best = std::max(best, s.radius - d);
        }
        f.at(i, j, k) = static_cast<float>(best);
      }
    }
  }
  return f;
}

// Grey values = a known function of the grid index, so that a test can tell
// which voxel a pixel shows.
PreviewPlaneSampler IndexRamp(const Grid& grid, int axis) {
  return [grid, axis](const VoxelBox& box) -> absl::StatusOr<Volume<float>> {
    Volume<float> v;
    v.grid = CropGrid(grid, box);
    v.data.resize(v.grid.VoxelCount());
    for (int64_t k = 0; k < v.grid.size[2]; ++k) {
      for (int64_t j = 0; j < v.grid.size[1]; ++j) {
        for (int64_t i = 0; i < v.grid.size[0]; ++i) {
          const int64_t g[3] = {box.begin[0] + i, box.begin[1] + j,
                                box.begin[2] + k};
          v.at(i, j, k) = static_cast<float>(g[axis]);
        }
      }
    }
    return v;
  };
}

std::array<uint8_t, 3> Pixel(const PreviewImage& image, int x, int y) {
  const uint8_t* p =
      image.rgb.data() + (static_cast<size_t>(y) * image.width + x) * 3;
  return {p[0], p[1], p[2]};
}

bool IsGreenish(const std::array<uint8_t, 3>& c) {
  return c[1] - std::max(c[0], c[2]) > 60;
}
bool IsBluish(const std::array<uint8_t, 3>& c) {
  return c[2] - std::max(c[0], c[1]) > 60;
}
bool IsTick(const std::array<uint8_t, 3>& c) {
  return c[0] > 200 && c[1] > 150 && c[2] < 60;
}

Vec3 At(const PreviewImage& image, double x, double y) {
  Vec3 p;
  for (int c = 0; c < 3; ++c) {
    p[c] = image.origin[c] + x * image.per_x[c] + y * image.per_y[c];
  }
  return p;
}

const PreviewImage& Find(const PreviewSet& set, const std::string& name) {
  for (const PreviewImage& image : set.images) {
    if (image.name == name) return image;
  }
  ADD_FAILURE() << "no view " << name;
  static PreviewImage none;
  return none;
}

// Writes the previews as PNG files where INTERSLICE_PREVIEW_TEST_DUMP says,
// for a person to look at.
void MaybeDump(const PreviewSet& set, const std::string& prefix) {
  const char* dir = std::getenv("INTERSLICE_PREVIEW_TEST_DUMP");
  if (dir == nullptr) return;
  std::filesystem::create_directories(dir);
  for (const PreviewImage& image : set.images) {
    absl::StatusOr<std::string> png = EncodePng(image);
    ASSERT_TRUE(png.ok());
    std::ofstream(std::string(dir) + "/" + prefix + "-" + image.name + ".png",
                  std::ios::binary)
        << *png;
  }
}

struct SphereScene {
  Grid grid;
  Volume<float> field;
  Sphere ball;
  PreviewScene scene;
};

// A sphere of radius 9 mm centred on a voxel of a 64 x 56 x 48 grid.
std::unique_ptr<SphereScene> MakeSphereScene(
    Vec3 spacing = {0.5, 0.5, 0.5}, Index3 size = {64, 56, 48},
    Mat3 direction = kIdentityDirection) {
  auto s = std::make_unique<SphereScene>();
  s->grid = MakeGrid(size, spacing, direction, {-10, 20, 30});
  s->ball = {s->grid.IndexToPhysical({30, 25, 22}), 9.0};
  s->field = SphereField(s->grid, {s->ball});
  s->scene.grid = s->grid;
  s->scene.field = &s->field;
  s->scene.objects = {{0, kGreen, &s->field, ">= 0"}};
  s->scene.intensity = IndexRamp(s->grid, 2);
  s->scene.window = DisplayWindow{size[2] / 2.0, static_cast<double>(size[2])};
  s->scene.legend = {"interslice: test scene, interpolated", "method test"};
  return s;
}

TEST(PreviewTest, FourViewsNamedAndOrientedAsRadiologistsRead) {
  auto s = MakeSphereScene();
  absl::StatusOr<PreviewSet> set = RenderPreviews(s->scene, {}, {});
  ASSERT_TRUE(set.ok()) << set.status();
  MaybeDump(*set, "sphere");
  ASSERT_THAT(set->images, SizeIs(4));
  EXPECT_EQ(set->images[0].name, "axial");
  EXPECT_EQ(set->images[1].name, "coronal");
  EXPECT_EQ(set->images[2].name, "sagittal");
  EXPECT_EQ(set->images[3].name, "3d-front");
  // With the identity direction, index axes are L, P, S. Axial: L to the
  // right, P down; coronal: L right, S up; sagittal: P right, S up.
  const PreviewImage& axial = Find(*set, "axial");
  EXPECT_GT(axial.per_x[0], 0);
  EXPECT_GT(axial.per_y[1], 0);
  EXPECT_EQ(axial.plane_axis, 2);
  EXPECT_EQ(axial.patient_orientation, "L\\P");
  const PreviewImage& coronal = Find(*set, "coronal");
  EXPECT_GT(coronal.per_x[0], 0);
  EXPECT_LT(coronal.per_y[2], 0);
  EXPECT_EQ(coronal.plane_axis, 1);
  EXPECT_EQ(coronal.patient_orientation, "L\\F");
  const PreviewImage& sagittal = Find(*set, "sagittal");
  EXPECT_GT(sagittal.per_x[1], 0);
  EXPECT_LT(sagittal.per_y[2], 0);
  EXPECT_EQ(sagittal.plane_axis, 0);
  EXPECT_EQ(sagittal.patient_orientation, "P\\F");
  // Planes through the sphere's centre (its centroid).
  EXPECT_EQ(axial.plane_index, 22);
  EXPECT_EQ(coronal.plane_index, 25);
  EXPECT_EQ(sagittal.plane_index, 30);
  // The legend carries the scene's lines first.
  for (const PreviewImage& image : set->images) {
    ASSERT_GE(image.legend.size(), 3u);
    EXPECT_EQ(image.legend[0], "interslice: test scene, interpolated");
    EXPECT_EQ(image.rgb.size(),
              static_cast<size_t>(image.width) * image.height * 3);
  }
}

TEST(PreviewTest, MirroredGridIsStillShownRadiologically) {
  // Index axes pointing R, A, I: every view must flip both axes.
  const Mat3 mirrored = {-1, 0, 0, 0, -1, 0, 0, 0, -1};
  auto s = MakeSphereScene({0.5, 0.5, 0.5}, {64, 56, 48}, mirrored);
  absl::StatusOr<PreviewSet> set = RenderPreviews(s->scene, {}, {});
  ASSERT_TRUE(set.ok()) << set.status();
  for (const PreviewImage& image : set->images) {
    if (image.plane_axis < 0) continue;
    // The picture's x and y directions in LPS.
    Vec3 right{}, down{};
    for (int a = 0; a < 3; ++a) {
      const Vec3 axis = s->grid.Axis(a);
      for (int c = 0; c < 3; ++c) {
        right[c] += axis[c] * image.per_x[a] * s->grid.spacing[a];
        down[c] += axis[c] * image.per_y[a] * s->grid.spacing[a];
      }
    }
    if (image.name == "axial") {
      EXPECT_GT(right[0], 0);
      EXPECT_GT(down[1], 0);
    } else if (image.name == "coronal") {
      EXPECT_GT(right[0], 0);
      EXPECT_LT(down[2], 0);
    } else {
      EXPECT_GT(right[1], 0);
      EXPECT_LT(down[2], 0);
    }
  }
}

// The picture shows what its mapping says: the grey ramp along k at each
// pixel is the k the mapping gives.
TEST(PreviewTest, PixelsShowTheVoxelsTheMappingNames) {
  auto s = MakeSphereScene();
  absl::StatusOr<PreviewSet> set = RenderPreviews(s->scene, {}, {});
  ASSERT_TRUE(set.ok()) << set.status();
  const DisplayWindow window = *s->scene.window;
  for (const std::string name : {"coronal", "sagittal"}) {
    const PreviewImage& image = Find(*set, name);
    int checked = 0;
    // Away from the edges, where the direction letters are.
    for (int y = image.y0 + 24; y < image.y1 - 24; y += 7) {
      for (int x = image.x0 + 24; x < image.x1 - 24; x += 13) {
        const std::array<uint8_t, 3> c = Pixel(image, x, y);
        if (c[0] != c[1] || c[1] != c[2]) continue;  // outline, letters
        const double k = At(image, x + 0.5, y + 0.5)[2];
        const double expected =
            std::clamp((k - (window.center - window.width / 2)) / window.width,
                       0.0, 1.0) *
            255;
        EXPECT_NEAR(c[0], expected, 4.0) << name << " at " << x << "," << y;
        ++checked;
      }
    }
    EXPECT_GT(checked, 100) << name;
  }
}

// The outline: every coloured pixel lies on the sphere's circle in that
// plane, and the circle is drawn all the way round.
TEST(PreviewTest, OutlineLiesWhereTheMaskEnds) {
  for (const Vec3 spacing : {Vec3{0.5, 0.5, 0.5}, Vec3{0.5, 0.5, 2.5}}) {
    const Index3 size =
        spacing[2] > 1 ? Index3{64, 56, 12} : Index3{64, 56, 48};
    auto s = MakeSphereScene(spacing, size);
    if (spacing[2] > 1) {
      s->ball = {s->grid.IndexToPhysical({30, 25, 5}), 9.0};
      s->field = SphereField(s->grid, {s->ball});
    }
    absl::StatusOr<PreviewSet> set = RenderPreviews(s->scene, {}, {});
    ASSERT_TRUE(set.ok()) << set.status();
    MaybeDump(*set, spacing[2] > 1 ? "sphere-thick" : "sphere-iso");
    for (const std::string name : {"axial", "coronal", "sagittal"}) {
      const PreviewImage& image = Find(*set, name);
      const double mm_per_pixel =
          std::max(std::abs(image.per_x[0]) * spacing[0] +
                       std::abs(image.per_x[1]) * spacing[1] +
                       std::abs(image.per_x[2]) * spacing[2],
                   std::abs(image.per_y[0]) * spacing[0] +
                       std::abs(image.per_y[1]) * spacing[1] +
                       std::abs(image.per_y[2]) * spacing[2]);
      // The field's sampling limits the contour: its linear interpolation
      // of the sphere between samples along the coarsest in-plane axis.
      double coarsest = 0;
      for (int a = 0; a < 3; ++a) {
        if (a != image.plane_axis) coarsest = std::max(coarsest, spacing[a]);
      }
      const double tolerance = 1.5 * mm_per_pixel + 0.05 * coarsest * coarsest;
      const Vec3 plane_point = s->grid.IndexToPhysical(
          At(image, (image.x0 + image.x1) / 2.0, (image.y0 + image.y1) / 2.0));
      const double offset = std::abs(Vec3{plane_point}[image.plane_axis] -
                                     s->ball.centre[image.plane_axis]);
      const double circle =
          std::sqrt(s->ball.radius * s->ball.radius - offset * offset);
      int coloured = 0;
      std::set<int> angles_seen;
      for (int y = image.y0; y < image.y1; ++y) {
        for (int x = image.x0; x < image.x1; ++x) {
          if (!IsGreenish(Pixel(image, x, y))) continue;
          ++coloured;
          const Vec3 p = s->grid.IndexToPhysical(At(image, x + 0.5, y + 0.5));
          double d2 = 0;
          double angle_a = 0, angle_b = 0;
          int seen = 0;
          for (int c = 0; c < 3; ++c) {
            if (c == image.plane_axis) continue;
            const double d = p[c] - s->ball.centre[c];
            d2 += d * d;
            (seen++ == 0 ? angle_a : angle_b) = d;
          }
          EXPECT_NEAR(std::sqrt(d2), circle, tolerance)
              << name << " pixel " << x << "," << y;
          angles_seen.insert(static_cast<int>(std::floor(
              (std::atan2(angle_b, angle_a) + M_PI) / (2 * M_PI) * 36)));
        }
      }
      EXPECT_GT(coloured, 20) << name;
      EXPECT_EQ(angles_seen.size(), 36u) << name << ": the outline has gaps";
    }
  }
}

TEST(PreviewTest, OriginalSlicesAreTickedOnTheirRows) {
  auto s = MakeSphereScene();
  // Original slices every 6th output slice from 1, and one between nodes.
  std::vector<double> marks;
  for (double k = 1; k < 48; k += 6) marks.push_back(k);
  marks.push_back(44.4);
  s->scene.marked_slices = marks;
  absl::StatusOr<PreviewSet> set = RenderPreviews(s->scene, {}, {});
  ASSERT_TRUE(set.ok()) << set.status();
  MaybeDump(*set, "ticks");
  for (const std::string name : {"coronal", "sagittal"}) {
    const PreviewImage& image = Find(*set, name);
    for (const int x : {image.x0 - 6, image.x1 + 5}) {
      std::vector<int> rows;
      for (int y = 0; y < image.height; ++y) {
        if (IsTick(Pixel(image, x, y))) rows.push_back(y);
      }
      ASSERT_EQ(rows.size(), marks.size()) << name << " column " << x;
      for (size_t n = 0; n < rows.size(); ++n) {
        // Rows grow downwards, k grows upwards: the last mark is on top.
        const double k = marks[marks.size() - 1 - n];
        const double shown = At(image, x + 0.5, rows[n] + 0.5)[2];
        EXPECT_LE(std::abs(shown - k), 0.5 * std::abs(image.per_y[2]) + 1e-9)
            << name << " row " << rows[n] << " shows k " << shown << ", mark "
            << k;
      }
    }
  }
  // The axial plane contains no slice axis: no ticks beside it.
  const PreviewImage& axial = Find(*set, "axial");
  for (int y = 0; y < axial.y1; ++y) {
    EXPECT_FALSE(IsTick(Pixel(axial, axial.x0 - 6, y)));
  }
  // The axial view's legend says how far its plane is from an original
  // slice (k = 22, the nearest mark 19 or 25: 3 slices of 0.5 mm).
  EXPECT_THAT(axial.legend[2],
              HasSubstr("1.5 mm from the nearest of the original slices"));
}

TEST(PreviewTest, FrontViewShowsTheSphereWhereItIs) {
  auto s = MakeSphereScene();
  // A second, smaller ball on the patient's left (+x) and above (+z).
  Sphere small{
      {s->ball.centre[0] + 12, s->ball.centre[1], s->ball.centre[2] + 8}, 3};
  s->field = SphereField(s->grid, {s->ball, small});
  absl::StatusOr<PreviewSet> set = RenderPreviews(s->scene, {}, {});
  ASSERT_TRUE(set.ok()) << set.status();
  MaybeDump(*set, "front");
  const PreviewImage& front = Find(*set, "3d-front");
  EXPECT_EQ(front.patient_orientation, "L\\F");
  int disagree = 0, total = 0;
  double centre_light = 0, rim_light = 0;
  // Away from the edges, where the direction letters are.
  for (int y = front.y0 + 20; y < front.y1 - 20; ++y) {
    for (int x = front.x0 + 20; x < front.x1 - 20; ++x) {
      const Vec3 p = At(front, x + 0.5, y + 0.5);
      auto inside = [&](const Sphere& b, double grow) {
        const double dx = p[0] - b.centre[0], dz = p[2] - b.centre[2];
        return std::sqrt(dx * dx + dz * dz) < b.radius + grow;
      };
      const double pixel = std::abs(front.per_x[0]);
      const bool surely_in =
          inside(s->ball, -1.5 * pixel) || inside(small, -1.5 * pixel);
      const bool surely_out =
          !inside(s->ball, 1.5 * pixel) && !inside(small, 1.5 * pixel);
      const std::array<uint8_t, 3> c = Pixel(front, x, y);
      const bool drawn = c[1] > 40;
      if (surely_in || surely_out) {
        ++total;
        if (drawn != surely_in) ++disagree;
      }
      const double dx = p[0] - s->ball.centre[0], dz = p[2] - s->ball.centre[2];
      const double r = std::sqrt(dx * dx + dz * dz);
      if (r < 1) centre_light = std::max<double>(centre_light, c[1]);
      if (r > 0.9 * s->ball.radius && r < 0.95 * s->ball.radius && dx > 0 &&
          dz < 0) {
        rim_light = std::max<double>(rim_light, c[1]);
      }
    }
  }
  EXPECT_GT(total, 10000);
  EXPECT_LE(disagree, 0) << "of " << total;
  // Lit from the viewer: the middle, facing the light, is brighter than the
  // lower right rim, facing away.
  EXPECT_GT(centre_light, rim_light + 40);
}

TEST(PreviewTest, LabelsAreOutlinedInTheirColoursAndTheNearerHidesTheFarther) {
  const Grid grid = MakeGrid({60, 60, 40}, {0.5, 0.5, 0.5});
  // Label 1 at the back (posterior, +y), label 2 in front and a little to
  // the left: in the front view label 2 covers part of label 1.
  const Sphere back{grid.IndexToPhysical({28, 36, 20}), 7};
  const Sphere front_ball{grid.IndexToPhysical({34, 20, 20}), 5};
  Volume<float> f1 = SphereField(grid, {back});
  Volume<float> f2 = SphereField(grid, {front_ball});
  Volume<uint16_t> labels{grid, std::vector<uint16_t>(grid.VoxelCount(), 0)};
  for (size_t n = 0; n < labels.data.size(); ++n) {
    if (f1.data[n] >= 0) labels.data[n] = 1;
    if (f2.data[n] >= 0) labels.data[n] = 2;
  }
  PreviewScene scene;
  scene.grid = grid;
  scene.labels = &labels;
  scene.objects = {{1, kGreen, &f1, "label 1"}, {2, kBlue, &f2, "label 2"}};
  scene.legend = {"interslice fill: test"};
  scene.marked_slices = {0, 10, 20, 30, 39};
  scene.marked_slices_name = "key slices";
  absl::StatusOr<PreviewSet> set = RenderPreviews(scene, {}, {});
  ASSERT_TRUE(set.ok()) << set.status();
  MaybeDump(*set, "labels");
  // Axial plane through both (k = 20): a green and a blue outline, each on
  // its own ball's boundary.
  const PreviewImage& axial = Find(*set, "axial");
  int green = 0, blue = 0;
  for (int y = axial.y0; y < axial.y1; ++y) {
    for (int x = axial.x0; x < axial.x1; ++x) {
      const std::array<uint8_t, 3> c = Pixel(axial, x, y);
      const Vec3 p = grid.IndexToPhysical(At(axial, x + 0.5, y + 0.5));
      auto radius_at = [&](const Sphere& b) {
        return std::hypot(p[0] - b.centre[0], p[1] - b.centre[1]);
      };
      if (IsGreenish(c)) {
        ++green;
        EXPECT_NEAR(radius_at(back), back.radius, 0.9);
      }
      if (IsBluish(c)) {
        ++blue;
        EXPECT_NEAR(radius_at(front_ball), front_ball.radius, 0.9);
      }
    }
  }
  EXPECT_GT(green, 30);
  EXPECT_GT(blue, 20);
  // Front view: where both project, the front ball's blue is seen.
  const PreviewImage& front = Find(*set, "3d-front");
  const double pixel = std::abs(front.per_x[0]);
  int overlap = 0;
  for (int y = front.y0; y < front.y1; ++y) {
    for (int x = front.x0; x < front.x1; ++x) {
      const Vec3 p = At(front, x + 0.5, y + 0.5);
      const double d1 =
          std::hypot(p[0] - back.centre[0], p[2] - back.centre[2]);
      const double d2 =
          std::hypot(p[0] - front_ball.centre[0], p[2] - front_ball.centre[2]);
      const std::array<uint8_t, 3> c = Pixel(front, x, y);
      if (d1 < back.radius - 2 * pixel && d2 < front_ball.radius - 2 * pixel) {
        ++overlap;
        EXPECT_GT(c[2], c[1]) << "front ball hidden at " << x << "," << y;
      } else if (d1 < back.radius - 2 * pixel &&
                 d2 > front_ball.radius + 2 * pixel) {
        EXPECT_GT(c[1], c[2]) << "back ball not seen at " << x << "," << y;
      }
    }
  }
  EXPECT_GT(overlap, 200);
  // Key slices are ticked beside the coronal and sagittal views.
  const PreviewImage& coronal = Find(*set, "coronal");
  int ticks = 0;
  for (int y = 0; y < coronal.height; ++y) {
    ticks += IsTick(Pixel(coronal, coronal.x0 - 6, y)) ? 1 : 0;
  }
  EXPECT_EQ(ticks, 5);
}

TEST(PreviewTest, SameScenesGiveTheSamePixelsOnAnyThreadCount) {
  auto s = MakeSphereScene();
  s->scene.marked_slices = {3, 9, 15, 21, 27, 33, 39, 45};
  ComputeContext one, two;
  one.threads = 1;
  two.threads = 2;
  absl::StatusOr<PreviewSet> a = RenderPreviews(s->scene, {}, one);
  absl::StatusOr<PreviewSet> b = RenderPreviews(s->scene, {}, two);
  absl::StatusOr<PreviewSet> c = RenderPreviews(s->scene, {}, two);
  ASSERT_TRUE(a.ok() && b.ok() && c.ok());
  ASSERT_EQ(a->images.size(), b->images.size());
  for (size_t n = 0; n < a->images.size(); ++n) {
    EXPECT_EQ(a->images[n].rgb, b->images[n].rgb) << a->images[n].name;
    EXPECT_EQ(b->images[n].rgb, c->images[n].rgb) << a->images[n].name;
    EXPECT_EQ(*EncodePng(a->images[n]), *EncodePng(b->images[n]));
  }
}

TEST(PreviewTest, EmptyObjectRendersWithANote) {
  auto s = MakeSphereScene();
  std::fill(s->field.data.begin(), s->field.data.end(), -5.0f);
  absl::StatusOr<PreviewSet> set = RenderPreviews(s->scene, {}, {});
  ASSERT_TRUE(set.ok()) << set.status();
  MaybeDump(*set, "empty");
  ASSERT_THAT(set->images, SizeIs(4));
  EXPECT_THAT(set->notes,
              ::testing::Contains(HasSubstr("the object is empty")));
  for (const PreviewImage& image : set->images) {
    for (int y = image.y0; y < image.y1; ++y) {
      for (int x = image.x0; x < image.x1; ++x) {
        ASSERT_FALSE(IsGreenish(Pixel(image, x, y))) << image.name;
      }
    }
  }
  EXPECT_EQ(Find(*set, "3d-front").description,
            "3D view from the front: no surface");
}

TEST(PreviewTest, TinyAndLargeGridsAreScaledIntoTheSizeRange) {
  // A 3 x 3 x 2 region of interest.
  const Grid tiny = MakeGrid({3, 3, 2}, {0.45, 0.45, 0.45});
  Volume<float> f{tiny,
                  {-1, -1, -1, -1, 1, -1, -1, -1, -1,  //
                   -1, -1, -1, -1, 1, -1, -1, -1, -1}};
  PreviewScene scene;
  scene.grid = tiny;
  scene.field = &f;
  scene.objects = {{0, kGreen, &f, "mask"}};
  absl::StatusOr<PreviewSet> set = RenderPreviews(scene, {}, {});
  ASSERT_TRUE(set.ok()) << set.status();
  MaybeDump(*set, "tiny");
  for (const PreviewImage& image : set->images) {
    EXPECT_GE(std::max(image.x1 - image.x0, image.y1 - image.y0), 384)
        << image.name;
  }
  // 1500 columns: scaled down to 1024.
  const Grid wide = MakeGrid({1500, 40, 4}, {0.2, 0.2, 0.2});
  Volume<float> g =
      SphereField(wide, {{wide.IndexToPhysical({700, 20, 2}), 3}});
  scene.grid = wide;
  scene.field = &g;
  scene.objects = {{0, kGreen, nullptr, "mask"}};
  set = RenderPreviews(scene, {}, {});
  ASSERT_TRUE(set.ok()) << set.status();
  ASSERT_THAT(set->images, SizeIs(3));  // no surface given: no 3D view
  for (const PreviewImage& image : set->images) {
    EXPECT_LE(std::max(image.x1 - image.x0, image.y1 - image.y0), 1024)
        << image.name;
  }
}

TEST(PreviewTest, SurfaceWithMillionsOfTrianglesStillRenders) {
  // Sign noise: every voxel's sign at random, a mesh of millions of
  // triangles; the ray tracer stops at the first crossing.
  const Grid grid = MakeGrid({160, 160, 160}, {0.5, 0.5, 0.5});
  Volume<float> noise{grid, std::vector<float>(grid.VoxelCount())};
  std::mt19937 random(7);
  for (float& v : noise.data) v = (random() & 1) ? 0.25f : -0.25f;
  PreviewScene scene;
  scene.grid = grid;
  scene.field = &noise;
  scene.objects = {{0, kGreen, &noise, "noise"}};
  absl::StatusOr<PreviewSet> set = RenderPreviews(scene, {}, {});
  ASSERT_TRUE(set.ok()) << set.status();
  EXPECT_THAT(set->images, SizeIs(4));
}

TEST(PreviewTest, BadScenesAreRefusedByName) {
  auto s = MakeSphereScene();
  PreviewScene both = s->scene;
  Volume<uint16_t> labels{s->grid, std::vector<uint16_t>(s->grid.VoxelCount())};
  both.labels = &labels;
  absl::StatusOr<PreviewSet> r = RenderPreviews(both, {}, {});
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(r.status().message(),
              HasSubstr("exactly one of a field and a label map"));

  PreviewScene short_field = s->scene;
  Volume<float> small{s->grid, std::vector<float>(10)};
  short_field.field = &small;
  r = RenderPreviews(short_field, {}, {});
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);

  PreviewScene bad_surface = s->scene;
  Volume<float> nan_field = s->field;
  nan_field.data[5] = std::nanf("");
  bad_surface.objects[0].surface = &nan_field;
  r = RenderPreviews(bad_surface, {}, {});
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(r.status().message(), HasSubstr("not finite"));

  PreviewOptions no_font;
  no_font.font_path = "/nonexistent/font.ttf";
  r = RenderPreviews(s->scene, no_font, {});
  EXPECT_EQ(r.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(r.status().message(), HasSubstr("/nonexistent/font.ttf"));

  PreviewScene failing = s->scene;
  failing.intensity = [](const VoxelBox&) -> absl::StatusOr<Volume<float>> {
    return absl::DataLossError("sampler broke");
  };
  r = RenderPreviews(failing, {}, {});
  EXPECT_EQ(r.status().code(), absl::StatusCode::kDataLoss);
}

TEST(PreviewTest, CancellationStopsRendering) {
  auto s = MakeSphereScene();
  CancellationToken token;
  token.Cancel();
  ComputeContext context;
  context.cancel = &token;
  absl::StatusOr<PreviewSet> r = RenderPreviews(s->scene, {}, context);
  EXPECT_EQ(r.status().code(), absl::StatusCode::kCancelled);
}

TEST(PreviewTest, PngFolderReplacesTheOldOneWhole) {
  auto s = MakeSphereScene();
  absl::StatusOr<PreviewSet> set = RenderPreviews(s->scene, {}, {});
  ASSERT_TRUE(set.ok());
  const std::filesystem::path dir =
      std::filesystem::path(::testing::TempDir()) / "preview-png";
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir / "previews");
  std::ofstream(dir / "previews" / "stale.png") << "old";
  absl::StatusOr<std::vector<std::string>> paths =
      WritePreviewPngs(set->images, (dir / "previews").string());
  ASSERT_TRUE(paths.ok()) << paths.status();
  ASSERT_THAT(*paths, SizeIs(4));
  EXPECT_FALSE(std::filesystem::exists(dir / "previews" / "stale.png"));
  std::ifstream in(dir / "previews" / "axial.png", std::ios::binary);
  std::string bytes((std::istreambuf_iterator<char>(in)), {});
  EXPECT_EQ(bytes, *EncodePng(set->images[0]));
  EXPECT_EQ(bytes.substr(1, 3), "PNG");
  // Only the folder is left: no temporary beside it.
  int entries = 0;
  for (const auto& e : std::filesystem::directory_iterator(dir)) {
    (void)e;
    ++entries;
  }
  EXPECT_EQ(entries, 1);
}

}  // namespace
}  // namespace interslice

#include "core/geometry/volume.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace interslice {
namespace {

Grid ObliqueGrid() {
  Grid g;
  g.size = {10, 20, 30};
  g.spacing = {0.5, 0.75, 2.0};
  g.origin = {-100, 50, 700};
  // Rotation by 30 degrees about z, then the normal.
  const double c = std::cos(M_PI / 6), s = std::sin(M_PI / 6);
  g.direction = {c, -s, 0, s, c, 0, 0, 0, 1};
  return g;
}

TEST(GridTest, IndexToPhysicalUsesSpacingAndDirection) {
  const Grid g = ObliqueGrid();
  const Vec3 p = g.IndexToPhysical({2, 0, 0});
  const double c = std::cos(M_PI / 6), s = std::sin(M_PI / 6);
  EXPECT_NEAR(p[0], -100 + c * 1.0, 1e-12);
  EXPECT_NEAR(p[1], 50 + s * 1.0, 1e-12);
  EXPECT_NEAR(p[2], 700, 1e-12);
  const Vec3 q = g.IndexToPhysical({0, 0, 3});
  EXPECT_NEAR(q[2], 706, 1e-12);
}

TEST(GridTest, PhysicalToIndexInvertsIndexToPhysical) {
  const Grid g = ObliqueGrid();
  const Vec3 index = {3.25, 7.5, 11.0};
  const Vec3 back = g.PhysicalToIndex(g.IndexToPhysical(index));
  for (int a = 0; a < 3; ++a) EXPECT_NEAR(back[a], index[a], 1e-9);
}

TEST(GridTest, ValidateRejectsBadSpacingAndDirection) {
  Grid g = ObliqueGrid();
  EXPECT_TRUE(g.Validate().ok());
  g.spacing[2] = 0;
  EXPECT_EQ(g.Validate().code(), absl::StatusCode::kInvalidArgument);
  g = ObliqueGrid();
  g.direction[0] = 2;
  EXPECT_EQ(g.Validate().code(), absl::StatusCode::kInvalidArgument);
  g = ObliqueGrid();
  g.size[1] = 0;
  EXPECT_EQ(g.Validate().code(), absl::StatusCode::kInvalidArgument);
}

TEST(VoxelBoxTest, ValidateNamesAxis) {
  const Grid g = ObliqueGrid();
  EXPECT_TRUE(ValidateVoxelBox({{0, 0, 0}, {10, 20, 30}}, g).ok());
  const absl::Status s = ValidateVoxelBox({{0, 0, 5}, {10, 20, 31}}, g);
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("along z"), std::string::npos) << s;
  EXPECT_FALSE(ValidateVoxelBox({{4, 0, 0}, {4, 20, 30}}, g).ok());
}

TEST(VoxelBoxTest, CropGridMovesOrigin) {
  const Grid g = ObliqueGrid();
  const VoxelBox box{{2, 4, 6}, {5, 9, 10}};
  const Grid c = CropGrid(g, box);
  EXPECT_EQ(c.size, (Index3{3, 5, 4}));
  const Vec3 expected = g.IndexToPhysical({2, 4, 6});
  for (int a = 0; a < 3; ++a) EXPECT_NEAR(c.origin[a], expected[a], 1e-12);
  // Voxel (1,1,1) of the crop is voxel (3,5,7) of the source.
  const Vec3 p = c.IndexToPhysical({1, 1, 1});
  const Vec3 q = g.IndexToPhysical({3, 5, 7});
  for (int a = 0; a < 3; ++a) EXPECT_NEAR(p[a], q[a], 1e-9);
}

TEST(VoxelBoxTest, CropVolumeCopiesTheRightVoxels) {
  Volume<int> v;
  v.grid.size = {4, 3, 2};
  v.data.resize(24);
  for (int n = 0; n < 24; ++n) v.data[n] = n;
  const Volume<int> c = CropVolume(v, {{1, 1, 1}, {3, 3, 2}});
  ASSERT_EQ(c.data.size(), 4u);
  EXPECT_EQ(c.at(0, 0, 0), v.at(1, 1, 1));
  EXPECT_EQ(c.at(1, 1, 0), v.at(2, 2, 1));
}

TEST(PhysicalBoxTest, MapsToCoveringVoxelBox) {
  Grid g;
  g.size = {10, 10, 10};
  g.spacing = {1, 1, 2};
  g.origin = {0, 0, 0};
  const auto box = PhysicalBoxToVoxelBox({{1.5, 0, 2}, {4.0, 9.0, 8.5}}, g);
  ASSERT_TRUE(box.ok()) << box.status();
  EXPECT_EQ(box->begin, (Index3{2, 0, 1}));
  EXPECT_EQ(box->end, (Index3{5, 10, 5}));
  EXPECT_FALSE(
      PhysicalBoxToVoxelBox({{100, 100, 100}, {101, 101, 101}}, g).ok());
}

// An oblique grid (rotated 30 degrees about LPS x, as a gantry tilt is) with
// non-uniform slice positions: the box is exactly the index bounding box of
// the voxel centres inside the LPS box, found by brute force.
TEST(PhysicalBoxTest, ObliqueGridWithUnevenSlicesMatchesBruteForce) {
  Grid g;
  g.size = {20, 24, 6};
  g.spacing = {0.8, 0.9, 2.0};
  g.origin = {-5, 3, 7};
  const double c = std::cos(M_PI / 6), s = std::sin(M_PI / 6);
  g.direction = {1, 0, 0, 0, c, -s, 0, s, c};
  const std::vector<double> offsets = {0, 1.5, 4, 6.5, 7, 11};
  const PhysicalBox box{{-1.1, 5.2, 6.0}, {6.3, 14.7, 15.5}};
  const auto got = PhysicalBoxToVoxelBox(box, g, offsets);
  ASSERT_TRUE(got.ok()) << got.status();
  VoxelBox expected{{100, 100, 100}, {-1, -1, -1}};
  for (int64_t k = 0; k < g.size[2]; ++k) {
    for (int64_t j = 0; j < g.size[1]; ++j) {
      for (int64_t i = 0; i < g.size[0]; ++i) {
        const Vec3 p =
            g.IndexToPhysical({static_cast<double>(i), static_cast<double>(j),
                               offsets[k] / g.spacing[2]});
        bool inside = true;
        for (int a = 0; a < 3; ++a) {
          inside &= p[a] >= box.min[a] && p[a] <= box.max[a];
        }
        if (!inside) continue;
        const Index3 v = {i, j, k};
        for (int a = 0; a < 3; ++a) {
          expected.begin[a] = std::min(expected.begin[a], v[a]);
          expected.end[a] = std::max(expected.end[a], v[a] + 1);
        }
      }
    }
  }
  ASSERT_LT(expected.begin[0], expected.end[0]) << "the case must hit voxels";
  EXPECT_EQ(got->begin, expected.begin);
  EXPECT_EQ(got->end, expected.end);
}

TEST(PhysicalBoxTest, MissesNameTheAxisAndDistance) {
  Grid g;
  g.size = {10, 10, 10};
  const auto beyond = PhysicalBoxToVoxelBox({{0, 0, 20}, {5, 5, 30}}, g);
  EXPECT_EQ(beyond.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(beyond.status().message()),
              ::testing::HasSubstr("z (slices) it starts 11.00 mm beyond"));
  const auto before = PhysicalBoxToVoxelBox({{-8, 0, 0}, {-3, 5, 5}}, g);
  EXPECT_THAT(std::string(before.status().message()),
              ::testing::HasSubstr("x (columns) it ends 3.00 mm before"));
  EXPECT_FALSE(PhysicalBoxToVoxelBox({{0, 0, 0}, {NAN, 5, 5}}, g).ok());
}

}  // namespace
}  // namespace interslice

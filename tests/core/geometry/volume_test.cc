#include "core/geometry/volume.h"

#include <cmath>

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

}  // namespace
}  // namespace interslice

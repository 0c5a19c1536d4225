#include "core/morph/morph.h"

#include <cmath>
#include <cstdint>
#include <vector>

#include "core/stack/stacking.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace interslice {
namespace {

constexpr int64_t kN = 64;

// Two-slice stack of disc distance maps (mm, positive inside; pixel 0.5 mm):
// slice 0 centred at (cx0, cy), slice 1 at (cx1, cy), radius r pixels.
Volume<float> TwoDiscs(double cx0, double cx1, double cy, double r) {
  Volume<float> maps;
  maps.grid.size = {kN, kN, 2};
  maps.grid.spacing = {0.5, 0.5, 4.0};
  maps.data.resize(kN * kN * 2);
  for (int s = 0; s < 2; ++s) {
    const double cx = s == 0 ? cx0 : cx1;
    for (int64_t j = 0; j < kN; ++j)
      for (int64_t i = 0; i < kN; ++i)
        maps.data[i + kN * (j + kN * s)] =
            static_cast<float>(0.5 * (r - std::hypot(i - cx, j - cy)));
  }
  return maps;
}

struct Blob {
  int64_t area = 0;
  double cx = 0, cy = 0;
};
Blob Inside(const Volume<float>& field, int64_t k) {
  Blob b;
  const Index3 n = field.grid.size;
  for (int64_t j = 0; j < n[1]; ++j)
    for (int64_t i = 0; i < n[0]; ++i)
      if (field.at(i, j, k) >= 0) {
        ++b.area;
        b.cx += i;
        b.cy += j;
      }
  if (b.area > 0) {
    b.cx /= b.area;
    b.cy /= b.area;
  }
  return b;
}

MorphOptions SmallOptions() {
  MorphOptions o;
  o.downsample = 1;
  o.levels = 4;
  o.iterations = 60;
  return o;
}

TEST(StackMorphTest, MovesADiscThatLinearStackingLoses) {
  // Discs of radius 7 px whose centres are 18 px apart do not overlap: the
  // linear blend of their distance maps is negative everywhere mid-gap.
  const Volume<float> maps = TwoDiscs(20, 38, 32, 7);
  const StackPlan plan = UniformStackPlan(2, 4.0, 4);
  ComputeContext context;
  auto linear = StackLinear(maps, plan, int64_t{1} << 30, context);
  ASSERT_TRUE(linear.ok()) << linear.status();
  EXPECT_EQ(Inside(linear->field, 2).area, 0);

  auto morphed =
      StackMorph(maps, plan, SmallOptions(), int64_t{1} << 30, context);
  ASSERT_TRUE(morphed.ok()) << morphed.status();
  const Volume<float>& f = morphed->stacked.field;
  const double disc = M_PI * 7 * 7;
  for (int64_t k = 1; k <= 3; ++k) {
    const Blob b = Inside(f, k);
    SCOPED_TRACE(k);
    // The disc travels with the correspondence: its centre moves by k/4 of
    // the 18 px and it keeps (nearly) its area.
    EXPECT_NEAR(b.cx, 20 + 18.0 * k / 4, 1.5);
    EXPECT_NEAR(b.cy, 32, 1.0);
    EXPECT_NEAR(b.area, disc, 0.25 * disc);
  }
  EXPECT_GT(morphed->statistics.mean_displacement_mm, 0);
  EXPECT_NEAR(morphed->statistics.max_displacement_mm, 9.0, 2.0);
}

TEST(StackMorphTest, OriginalSlicesAreBitIdenticalAndGridMatchesLinear) {
  const Volume<float> maps = TwoDiscs(28, 34, 30, 9);
  const StackPlan plan = UniformStackPlan(2, 4.0, 3);
  ComputeContext context;
  auto linear = StackLinear(maps, plan, int64_t{1} << 30, context);
  auto morphed =
      StackMorph(maps, plan, SmallOptions(), int64_t{1} << 30, context);
  ASSERT_TRUE(linear.ok() && morphed.ok());
  const StackedField& m = morphed->stacked;
  EXPECT_EQ(m.field.grid.size, linear->field.grid.size);
  EXPECT_EQ(m.fixed_slices, linear->fixed_slices);
  const int64_t plane = kN * kN;
  for (int64_t k : {0, 3}) {
    for (int64_t v = 0; v < plane; ++v) {
      ASSERT_EQ(m.field.data[k * plane + v], linear->field.data[k * plane + v]);
    }
  }
}

TEST(StackMorphTest, ZeroIterationsIsLinearStacking) {
  const Volume<float> maps = TwoDiscs(20, 38, 32, 7);
  const StackPlan plan = UniformStackPlan(2, 4.0, 4);
  ComputeContext context;
  MorphOptions o = SmallOptions();
  o.iterations = 0;
  auto linear = StackLinear(maps, plan, int64_t{1} << 30, context);
  auto morphed = StackMorph(maps, plan, o, int64_t{1} << 30, context);
  ASSERT_TRUE(linear.ok() && morphed.ok());
  EXPECT_EQ(morphed->stacked.field.data, linear->field.data);
}

TEST(StackMorphTest, ResultDoesNotDependOnThreadCount) {
  // Three slices (two gaps, registered concurrently with 2 threads).
  Volume<float> maps = TwoDiscs(20, 30, 32, 8);
  const Volume<float> more = TwoDiscs(40, 40, 32, 8);
  maps.grid.size[2] = 3;
  maps.data.insert(maps.data.end(), more.data.begin(),
                   more.data.begin() + kN * kN);
  const StackPlan plan = UniformStackPlan(3, 4.0, 4);
  ComputeContext one, two;
  one.threads = 1;
  two.threads = 2;
  auto a = StackMorph(maps, plan, SmallOptions(), int64_t{1} << 30, one);
  auto b = StackMorph(maps, plan, SmallOptions(), int64_t{1} << 30, two);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(a->stacked.field.data, b->stacked.field.data);
}

TEST(StackMorphTest, RejectsBadOptionsAndHonoursCancellation) {
  const Volume<float> maps = TwoDiscs(20, 38, 32, 7);
  const StackPlan plan = UniformStackPlan(2, 4.0, 4);
  ComputeContext context;
  for (auto bad : {+[](MorphOptions& o) { o.levels = 0; },
                   +[](MorphOptions& o) { o.iterations = -1; },
                   +[](MorphOptions& o) { o.field_sigma_px = 0; },
                   +[](MorphOptions& o) { o.clip_mm = -1; },
                   +[](MorphOptions& o) { o.downsample = 0; }}) {
    MorphOptions o = SmallOptions();
    bad(o);
    EXPECT_EQ(
        StackMorph(maps, plan, o, int64_t{1} << 30, context).status().code(),
        absl::StatusCode::kInvalidArgument);
  }
  CancellationToken token;
  token.Cancel();
  context.cancel = &token;
  EXPECT_EQ(StackMorph(maps, plan, SmallOptions(), int64_t{1} << 30, context)
                .status()
                .code(),
            absl::StatusCode::kCancelled);
}

TEST(RemoveUnsupportedComponentsTest, RemovesOnlyComponentsOffTheKeySlices) {
  Volume<float> f;
  f.grid.size = {16, 16, 9};
  f.data.assign(16 * 16 * 9, -1.0f);
  std::vector<uint8_t> fixed(9, 0);
  fixed[0] = fixed[4] = fixed[8] = 1;
  // A: a column from key slice 4 up to slice 6 (supported).
  for (int64_t k = 4; k <= 6; ++k) f.at(3, 3, k) = 1.0f;
  // B: a blob on inserted slices 1-2 only (no key slice: removed).
  f.at(10, 10, 1) = 0.5f;
  f.at(10, 10, 2) = 0.25f;
  f.at(11, 10, 2) = 0.0f;  // zero counts as inside
  // C: a single voxel on inserted slice 7 touching nothing (removed).
  f.at(12, 3, 7) = 2.0f;
  // D: diagonal neighbour of A on slice 5 (face connectivity: separate).
  f.at(4, 4, 5) = 1.0f;
  const Volume<float> before = f;
  ComputeContext context;
  auto removed = RemoveUnsupportedComponents(f, fixed, 1e-3f, context);
  ASSERT_TRUE(removed.ok()) << removed.status();
  EXPECT_EQ(*removed, 3);
  EXPECT_EQ(f.at(3, 3, 5), 1.0f);
  EXPECT_EQ(f.at(10, 10, 1), -1e-3f);
  EXPECT_EQ(f.at(11, 10, 2), -1e-3f);
  EXPECT_EQ(f.at(12, 3, 7), -1e-3f);
  EXPECT_EQ(f.at(4, 4, 5), -1e-3f);
  // Outside voxels are untouched.
  EXPECT_EQ(f.at(0, 0, 1), before.at(0, 0, 1));
  EXPECT_EQ(
      RemoveUnsupportedComponents(f, std::vector<uint8_t>(8, 1), 1e-3f, context)
          .status()
          .code(),
      absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace interslice

#include "core/stack/stacking.h"

#include <cmath>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace interslice {
namespace {

TEST(ChooseInsertionFactorTest, DefaultIsNearlyIsotropic) {
  // The thick phantom: 5 mm slices, 0.451 mm pixels -> N = round(11.09) = 11.
  const auto n = ChooseInsertionFactor(5.0, 0.451, {});
  ASSERT_TRUE(n.ok());
  EXPECT_EQ(*n, 11);
  EXPECT_EQ(*ChooseInsertionFactor(1.0, 1.0, {}), 1);
  EXPECT_EQ(*ChooseInsertionFactor(0.5, 1.0, {}), 1);  // never below 1
}

TEST(ChooseInsertionFactorTest, FactorAndSpacingOverride) {
  EXPECT_EQ(*ChooseInsertionFactor(5.0, 0.451, {.factor = 4}), 4);
  EXPECT_EQ(*ChooseInsertionFactor(5.0, 0.451, {.spacing_mm = 1.0}), 5);
  EXPECT_EQ(*ChooseInsertionFactor(5.0, 0.451, {.spacing_mm = 2.0}),
            3);  // 2.5 rounds to 3
}

TEST(ChooseInsertionFactorTest, RejectsBadRequests) {
  EXPECT_FALSE(
      ChooseInsertionFactor(5.0, 0.5, {.factor = 2, .spacing_mm = 1.0}).ok());
  EXPECT_FALSE(ChooseInsertionFactor(5.0, 0.5, {.factor = 0}).ok());
  EXPECT_FALSE(ChooseInsertionFactor(5.0, 0.5, {.spacing_mm = -1.0}).ok());
  EXPECT_FALSE(ChooseInsertionFactor(5.0, 0.5, {.spacing_mm = 1e-6}).ok());
  EXPECT_FALSE(ChooseInsertionFactor(0.0, 0.5, {}).ok());
}

Volume<float> ThreeSlices() {
  Volume<float> v;
  v.grid.size = {2, 2, 3};
  v.grid.spacing = {0.5, 0.5, 4.0};
  v.grid.origin = {10, 20, 30};
  v.data = {0, 0, 0, 0, 4, 4, 4, 4, -8, -8, -8, -8};
  return v;
}

TEST(StackLinearTest, OriginalsOnGridNodesAndLinearBetween) {
  const auto stacked = StackLinear(ThreeSlices(), 4, 1 << 20, {});
  ASSERT_TRUE(stacked.ok()) << stacked.status();
  const Volume<float>& f = stacked->field;
  EXPECT_EQ(f.grid.size[2], 9);
  EXPECT_DOUBLE_EQ(f.grid.spacing[2], 1.0);
  EXPECT_EQ(f.grid.origin, (Vec3{10, 20, 30}));
  const std::vector<uint8_t> expected_fixed = {1, 0, 0, 0, 1, 0, 0, 0, 1};
  EXPECT_EQ(stacked->fixed_slices, expected_fixed);
  const float expected[9] = {0, 1, 2, 3, 4, 1, -2, -5, -8};
  for (int k = 0; k < 9; ++k) EXPECT_FLOAT_EQ(f.at(1, 1, k), expected[k]) << k;
  // Original slice 1 lands at physical z = 30 + 4 mm on output slice 4.
  EXPECT_DOUBLE_EQ(f.grid.IndexToPhysical({0, 0, 4})[2], 34.0);
}

TEST(StackLinearTest, FactorOneIsACopy) {
  const auto stacked = StackLinear(ThreeSlices(), 1, 1 << 20, {});
  ASSERT_TRUE(stacked.ok());
  EXPECT_EQ(stacked->field.data, ThreeSlices().data);
}

TEST(StackLinearTest, RefusesOversizeOutputBeforeAllocating) {
  const auto stacked = StackLinear(ThreeSlices(), 1000, 1000, {});
  EXPECT_EQ(stacked.status().code(), absl::StatusCode::kResourceExhausted);
}

TEST(PlanStackTest, UniformSeriesReproducesTheFactorGrid) {
  // Positions as a reader computes them (5 mm with rounding noise).
  const std::vector<double> positions = {696.21, 701.21, 706.2100001, 711.21};
  const auto plan = PlanStack(positions, 0.451171875, {});
  ASSERT_TRUE(plan.ok()) << plan.status();
  EXPECT_TRUE(plan->uniform);
  EXPECT_EQ(plan->factor, 11);
  EXPECT_EQ(plan->nodes, (std::vector<int64_t>{0, 11, 22, 33}));
  EXPECT_EQ(plan->output_slices, 34);
  EXPECT_NEAR(plan->spacing_mm, 5.0 / 11, 1e-9);
  EXPECT_LT(plan->max_snap_mm, 1e-6);
  // And the stacked voxels equal the factor-only overload's, bit for bit.
  Volume<float> maps = ThreeSlices();
  const auto by_plan =
      StackLinear(maps, UniformStackPlan(3, 4.0, 4), 1 << 20, {});
  const auto by_factor = StackLinear(maps, 4, 1 << 20, {});
  ASSERT_TRUE(by_plan.ok() && by_factor.ok());
  EXPECT_EQ(by_plan->field.data, by_factor->field.data);
  EXPECT_EQ(by_plan->fixed_slices, by_factor->fixed_slices);
  EXPECT_EQ(by_plan->field.grid.spacing, by_factor->field.grid.spacing);
}

TEST(PlanStackTest, MissingSliceLandsExactlyOnANode) {
  // 5 mm series with the slice at 10 mm missing; 1 mm output.
  const auto plan = PlanStack({0, 5, 15, 20}, 0.5, {.spacing_mm = 1.0});
  ASSERT_TRUE(plan.ok()) << plan.status();
  EXPECT_FALSE(plan->uniform);
  EXPECT_DOUBLE_EQ(plan->spacing_mm, 1.0);
  EXPECT_EQ(plan->nodes, (std::vector<int64_t>{0, 5, 15, 20}));
  EXPECT_EQ(plan->output_slices, 21);
  EXPECT_DOUBLE_EQ(plan->max_snap_mm, 0);
  EXPECT_DOUBLE_EQ(plan->min_gap_mm, 5);
  EXPECT_DOUBLE_EQ(plan->max_gap_mm, 10);
}

TEST(PlanStackTest, IrregularPositionsSnapToTheNearestNode) {
  // Median gap 3.2 mm -> N = 3 at a 1 mm target.
  const std::vector<double> positions = {0, 3, 6.4, 8.7, 12.2};
  const auto plan = PlanStack(positions, 1.0, {});
  ASSERT_TRUE(plan.ok()) << plan.status();
  EXPECT_FALSE(plan->uniform);
  const double h = plan->spacing_mm;
  EXPECT_NEAR(h, 3.2 / 3, 1e-12);  // median of {3, 3.4, 2.3, 3.5} is 3.2
  double worst = 0;
  for (size_t s = 0; s < positions.size(); ++s) {
    const double snap = std::abs(positions[s] - plan->nodes[s] * h);
    // Nearest node: no other node is closer.
    EXPECT_LE(snap, h / 2 + 1e-12) << s;
    worst = std::max(worst, snap);
  }
  EXPECT_DOUBLE_EQ(plan->max_snap_mm, worst);
  EXPECT_GT(plan->max_snap_mm, 0.01);
  EXPECT_EQ(plan->output_slices, plan->nodes.back() + 1);
}

TEST(PlanStackTest, TwoOriginalsOnOneNodeIsAnError) {
  // Gaps 4, 0.2, 4 with factor 1: the median gap is 4 mm.
  const auto plan = PlanStack({0, 4, 4.2, 8.2}, 0.5, {.factor = 1});
  EXPECT_EQ(plan.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(plan.status().message()),
              ::testing::HasSubstr("smaller --spacing"));
  // A fine enough grid separates them.
  EXPECT_TRUE(PlanStack({0, 4, 4.2, 8.2}, 0.5, {.spacing_mm = 0.1}).ok());
}

TEST(PlanStackTest, RejectsUnsortedOrNonFinitePositions) {
  EXPECT_FALSE(PlanStack({}, 1, {}).ok());
  EXPECT_FALSE(PlanStack({0, 2, 1}, 1, {}).ok());
  EXPECT_FALSE(PlanStack({0, 0}, 1, {}).ok());
  EXPECT_FALSE(PlanStack({0, NAN}, 1, {}).ok());
  EXPECT_FALSE(PlanStack({0, 1, 1e12}, 1, {}).ok());
}

TEST(StackLinearTest, NonUniformPlanBlendsBetweenNeighbouringOriginals) {
  StackPlan plan;
  plan.spacing_mm = 1;
  plan.nodes = {0, 1, 4};
  plan.output_slices = 5;
  const auto stacked = StackLinear(ThreeSlices(), plan, 1 << 20, {});
  ASSERT_TRUE(stacked.ok()) << stacked.status();
  EXPECT_EQ(stacked->fixed_slices, (std::vector<uint8_t>{1, 1, 0, 0, 1}));
  const float expected[5] = {0, 4, 0, -4, -8};
  for (int k = 0; k < 5; ++k) {
    EXPECT_NEAR(stacked->field.at(0, 0, k), expected[k], 1e-5) << k;
  }
  EXPECT_DOUBLE_EQ(stacked->field.grid.spacing[2], 1.0);
  // A plan for another number of slices is refused.
  plan.nodes = {0, 4};
  plan.output_slices = 5;
  EXPECT_EQ(StackLinear(ThreeSlices(), plan, 1 << 20, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace interslice

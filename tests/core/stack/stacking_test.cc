#include "core/stack/stacking.h"

#include <cmath>

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

}  // namespace
}  // namespace interslice

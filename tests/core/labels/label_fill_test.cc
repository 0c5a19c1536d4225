#include "core/labels/label_fill.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include "core/volume_io/volume_io.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace interslice {
namespace {

using ::testing::HasSubstr;

constexpr int64_t kN = 40;   // in-plane size
constexpr int64_t kNz = 21;  // slices

// Ground truth: a disc of radius r(k) centred in the slice, split at column
// 20 into label 1 (left) and label 2 (right), so the two touch along a
// straight line. r(k) follows a sphere of radius 9 slices... centred on slice
// 10, so it ends between slices 1 and 2 and between 18 and 19.
LabelVolume TouchingHalves() {
  LabelVolume v;
  v.grid.size = {kN, kN, kNz};
  v.grid.spacing = {1, 1, 1};
  v.data.assign(v.grid.VoxelCount(), 0);
  for (int64_t k = 0; k < kNz; ++k) {
    const double dz = k - 10.0;
    const double r2 = 8.6 * 8.6 - dz * dz;
    if (r2 <= 0) continue;
    for (int64_t j = 0; j < kN; ++j) {
      for (int64_t i = 0; i < kN; ++i) {
        const double x = i - 19.5, y = j - 19.5;
        if (x * x + y * y * 0.6 <= r2 * 1.5) v.at(i, j, k) = i < 20 ? 1 : 2;
      }
    }
  }
  return v;
}

// Only the key slices of `truth` kept (others set to 0).
LabelVolume KeepSlices(const LabelVolume& truth,
                       const std::vector<int64_t>& keys) {
  LabelVolume v = truth;
  const int64_t plane = v.grid.SliceVoxelCount();
  for (int64_t k = 0; k < v.grid.size[2]; ++k) {
    if (std::find(keys.begin(), keys.end(), k) != keys.end()) continue;
    std::fill(v.data.begin() + k * plane, v.data.begin() + (k + 1) * plane, 0);
  }
  return v;
}

double Dice(const LabelVolume& a, const LabelVolume& b, int label) {
  int64_t both = 0, na = 0, nb = 0;
  for (size_t n = 0; n < a.data.size(); ++n) {
    na += a.data[n] == label;
    nb += b.data[n] == label;
    both += a.data[n] == label && b.data[n] == label;
  }
  return na + nb == 0 ? 1.0 : 2.0 * both / (na + nb);
}

int64_t CountOnSlice(const LabelVolume& v, int64_t k, int label) {
  int64_t n = 0;
  for (int64_t j = 0; j < v.grid.size[1]; ++j) {
    for (int64_t i = 0; i < v.grid.size[0]; ++i) n += v.at(i, j, k) == label;
  }
  return n;
}

const std::vector<int64_t> kKeys = {0, 5, 10, 15, 20};

// "auto" (FillMethod::kAuto) or a solver method name (FillMethod::kSolver).
void SetMethod(const std::string& name, FillOptions& options) {
  options.method = name == "auto" ? FillMethod::kAuto : FillMethod::kSolver;
  options.solver.method = name == "linear"  ? SolverMethod::kLinear
                          : name == "cg"    ? SolverMethod::kConjugateGradient
                          : name == "morph" ? SolverMethod::kMorph
                                            : SolverMethod::kDirect;
}

class FillMethodTest : public ::testing::TestWithParam<std::string> {};

TEST_P(FillMethodTest, TouchingLabelsKeySlicesExactNoGapNoOverlap) {
  const LabelVolume truth = TouchingHalves();
  const LabelVolume drawn = KeepSlices(truth, kKeys);
  FillOptions options;
  options.key_slices = kKeys;
  SetMethod(GetParam(), options);
  absl::StatusOr<FillResult> result =
      FillBetweenSlices(drawn, options, ComputeContext{.threads = 2});
  ASSERT_TRUE(result.ok()) << result.status();
  const LabelVolume& out = result->labels;
  ASSERT_EQ(out.grid.size, truth.grid.size);

  // Key slices exactly as drawn.
  for (int64_t k : kKeys) {
    for (int64_t j = 0; j < kN; ++j) {
      for (int64_t i = 0; i < kN; ++i) {
        ASSERT_EQ(out.at(i, j, k), drawn.at(i, j, k))
            << i << "," << j << "," << k;
      }
    }
  }
  // Between key slices: close to the truth for both labels.
  EXPECT_GT(Dice(out, truth, 1), 0.9);
  EXPECT_GT(Dice(out, truth, 2), 0.9);
  // No gap along the touching line: wherever both bracketing key slices hold
  // a label at a pixel, the interpolated slices hold one too.
  int64_t gaps = 0;
  for (size_t s = 0; s + 1 < kKeys.size(); ++s) {
    for (int64_t k = kKeys[s] + 1; k < kKeys[s + 1]; ++k) {
      for (int64_t j = 0; j < kN; ++j) {
        for (int64_t i = 0; i < kN; ++i) {
          if (drawn.at(i, j, kKeys[s]) != 0 &&
              drawn.at(i, j, kKeys[s + 1]) != 0 && out.at(i, j, k) == 0) {
            ++gaps;
          }
        }
      }
    }
  }
  EXPECT_EQ(gaps, 0);
  // Each side of the touching line keeps its own label (no label leaks over
  // the line, which lies between columns 19 and 20 on every slice).
  for (int64_t k = 0; k < kNz; ++k) {
    for (int64_t j = 0; j < kN; ++j) {
      for (int64_t i = 0; i < kN; ++i) {
        const uint16_t v = out.at(i, j, k);
        if (v == 1) EXPECT_LT(i, 21) << j << "," << k;
        if (v == 2) EXPECT_GT(i, 18) << j << "," << k;
      }
    }
  }
  ASSERT_EQ(result->per_label.size(), 2u);
  EXPECT_EQ(result->per_label[0].key_slices, kKeys);
}

INSTANTIATE_TEST_SUITE_P(Methods, FillMethodTest,
                         ::testing::Values("auto", "linear", "cg", "direct",
                                           "morph"));

TEST(FillTest, EndCapsCloseWithinOneGap) {
  // The structure is on slices 2..18; drawn on the key slices 5, 10, 15 and
  // absent on the key slices 0 and 20.
  const LabelVolume truth = TouchingHalves();
  FillOptions options;
  options.key_slices = kKeys;
  SetMethod("direct", options);
  absl::StatusOr<FillResult> result = FillBetweenSlices(
      KeepSlices(truth, kKeys), options, ComputeContext{.threads = 1});
  ASSERT_TRUE(result.ok()) << result.status();
  const LabelVolume& out = result->labels;
  for (int label : {1, 2}) {
    EXPECT_EQ(CountOnSlice(out, 0, label), 0);
    EXPECT_EQ(CountOnSlice(out, 1, label), 0) << label;
    EXPECT_GT(CountOnSlice(out, 4, label), 0) << label;
    EXPECT_GT(CountOnSlice(out, 16, label), 0) << label;
    EXPECT_EQ(CountOnSlice(out, 19, label), 0) << label;
    // Shrinks toward the cap.
    EXPECT_LT(CountOnSlice(out, 3, label), CountOnSlice(out, 5, label));
  }
}

TEST(FillTest, DefaultKeySlicesAreTheDrawnOnesPlusTheNextAtTheirRhythm) {
  LabelVolume v;
  v.grid.size = {4, 4, 12};
  v.data.assign(v.grid.VoxelCount(), 0);
  v.at(1, 1, 2) = 1;
  v.at(1, 1, 5) = 1;
  v.at(1, 1, 8) = 1;
  v.at(2, 2, 0) = 2;
  v.at(2, 2, 5) = 2;
  v.at(2, 2, 11) = 2;
  v.at(3, 3, 7) = 3;
  const std::vector<int64_t> annotated = {0, 2, 5, 7, 8, 11};
  // Every 3rd slice: empty at 11 (and -1 is outside the series).
  EXPECT_EQ(KeySlicesForLabel(v, 1, annotated, std::nullopt),
            (std::vector<int64_t>{2, 5, 8, 11}));
  // Drawn once: the nearest annotated slices.
  EXPECT_EQ(KeySlicesForLabel(v, 3, annotated, std::nullopt),
            (std::vector<int64_t>{5, 7, 8}));
  EXPECT_EQ(KeySlicesForLabel(v, 2, annotated, std::nullopt),
            (std::vector<int64_t>{0, 5, 11}));
  // Explicit keys: cut to those bracketing the drawn ones.
  EXPECT_EQ(KeySlicesForLabel(v, 1, annotated,
                              std::vector<int64_t>{0, 1, 5, 6, 9, 11}),
            (std::vector<int64_t>{1, 5, 6}));
  EXPECT_TRUE(KeySlicesForLabel(v, 4, annotated, std::nullopt).empty());
}

TEST(FillTest, DefaultDetectionFillsGapsAndKeepsOtherLabelsDrawnSlices) {
  // Label 1 drawn every 5th slice; label 2 drawn on every slice 0..20 as a
  // small square far away. Slices without label 1 in between are not drawn
  // for label 1 and get filled; label 2 stays exactly as drawn.
  LabelVolume truth = TouchingHalves();
  for (uint16_t& v : truth.data) v = v == 2 ? 0 : v;
  LabelVolume drawn = KeepSlices(truth, kKeys);
  for (int64_t k = 0; k < kNz; ++k) {
    for (int64_t j = 0; j < 3; ++j) {
      for (int64_t i = 0; i < 3; ++i) drawn.at(i, j, k) = 2;
    }
  }
  absl::StatusOr<FillResult> result =
      FillBetweenSlices(drawn, FillOptions{}, ComputeContext{.threads = 1});
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_GT(Dice(result->labels, truth, 1), 0.85);
  for (int64_t k = 0; k < kNz; ++k)
    EXPECT_EQ(CountOnSlice(result->labels, k, 2), 9);
  EXPECT_EQ(result->per_label[0].key_slices, kKeys);
}

TEST(FillTest, FactorPutsKeySlicesOnNodes) {
  const LabelVolume truth = TouchingHalves();
  const LabelVolume drawn = KeepSlices(truth, kKeys);
  FillOptions options;
  options.key_slices = kKeys;
  options.z_resolution.factor = 3;
  absl::StatusOr<FillResult> result =
      FillBetweenSlices(drawn, options, ComputeContext{.threads = 1});
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->factor, 3);
  EXPECT_EQ(result->labels.grid.size[2], (kNz - 1) * 3 + 1);
  EXPECT_DOUBLE_EQ(result->labels.grid.spacing[2], 1.0 / 3);
  for (int64_t k : kKeys) {
    for (int64_t j = 0; j < kN; ++j) {
      for (int64_t i = 0; i < kN; ++i) {
        ASSERT_EQ(result->labels.at(i, j, 3 * k), drawn.at(i, j, k));
      }
    }
  }
  EXPECT_GT(CountOnSlice(result->labels, 3 * 7 + 1, 1), 0);
}

TEST(FillTest, SingleSliceLabelIsKeptWithAWarning) {
  LabelVolume v = KeepSlices(TouchingHalves(), {10});
  absl::StatusOr<FillResult> result =
      FillBetweenSlices(v, FillOptions{}, ComputeContext{.threads = 1});
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_THAT(
      result->warnings,
      ::testing::Contains(HasSubstr("label 1 is drawn on slice 10 only")));
  EXPECT_EQ(result->labels.data, v.data);
}

TEST(FillTest, TiesGoToTheSmallerLabel) {
  // Two labels drawn identically on complementary key slices meet halfway:
  // label 1 on slice 0, label 2 on slice 4, the same disc; on slice 2 both
  // fields are equal by symmetry (linear stacking), and label 1 must win
  // every voxel whatever the order.
  LabelVolume v;
  v.grid.size = {20, 20, 5};
  v.data.assign(v.grid.VoxelCount(), 0);
  for (int64_t j = 0; j < 20; ++j) {
    for (int64_t i = 0; i < 20; ++i) {
      if ((i - 9.5) * (i - 9.5) + (j - 9.5) * (j - 9.5) <= 36) {
        v.at(i, j, 0) = 1;
        v.at(i, j, 4) = 2;
      }
    }
  }
  FillOptions options;
  SetMethod("linear", options);
  options.key_slices = std::vector<int64_t>{0, 4};
  absl::StatusOr<FillResult> result =
      FillBetweenSlices(v, options, ComputeContext{.threads = 1});
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_GT(CountOnSlice(result->labels, 2, 1), 0);
  EXPECT_EQ(CountOnSlice(result->labels, 2, 2), 0);
  EXPECT_EQ(CountOnSlice(result->labels, 1, 2), 0);
  EXPECT_GT(CountOnSlice(result->labels, 3, 2), 0);
}

// The same ties with the labels computed concurrently: label 1 also holds a
// large square far from the discs on slice 0 (beyond the distance band, so
// the fields at the discs stay symmetric), which makes it the longest job:
// it is started first and finishes last, and must still be merged first.
TEST(FillTest, TiesGoToTheSmallerLabelForAnyThreads) {
  LabelVolume v;
  v.grid.size = {240, 240, 5};
  v.data.assign(v.grid.VoxelCount(), 0);
  for (int64_t j = 0; j < 240; ++j) {
    for (int64_t i = 0; i < 240; ++i) {
      if ((i - 9.5) * (i - 9.5) + (j - 9.5) * (j - 9.5) <= 36) {
        v.at(i, j, 0) = 1;
        v.at(i, j, 4) = 2;
      } else if (i >= 100 && j >= 100) {
        v.at(i, j, 0) = 1;
      }
    }
  }
  FillOptions options;
  SetMethod("linear", options);
  options.key_slices = std::vector<int64_t>{0, 4};
  for (const int threads : {1, 2, 4}) {
    absl::StatusOr<FillResult> result =
        FillBetweenSlices(v, options, ComputeContext{.threads = threads});
    ASSERT_TRUE(result.ok()) << result.status();
    int64_t ones = 0, twos = 0;
    for (int64_t j = 0; j < 20; ++j) {
      for (int64_t i = 0; i < 20; ++i) {
        ones += result->labels.at(i, j, 2) == 1;
        twos += result->labels.at(i, j, 2) == 2;
      }
    }
    EXPECT_GT(ones, 0) << threads << " threads";
    EXPECT_EQ(twos, 0) << threads << " threads";
  }
}

TEST(FillTest, Errors) {
  const LabelVolume drawn = KeepSlices(TouchingHalves(), kKeys);
  const ComputeContext context{.threads = 1};
  LabelVolume empty = drawn;
  std::fill(empty.data.begin(), empty.data.end(), 0);
  EXPECT_THAT(FillBetweenSlices(empty, {}, context).status().message(),
              HasSubstr("empty"));
  FillOptions options;
  options.labels = {1, 7};
  EXPECT_THAT(FillBetweenSlices(drawn, options, context).status().message(),
              HasSubstr("label 7 is not drawn"));
  options = {};
  options.key_slices = std::vector<int64_t>{0, 30};
  EXPECT_THAT(FillBetweenSlices(drawn, options, context).status().message(),
              HasSubstr("key slice 30 is outside"));
  options.key_slices = std::vector<int64_t>{5, 5};
  EXPECT_THAT(FillBetweenSlices(drawn, options, context).status().message(),
              HasSubstr("listed twice"));
  options = {};
  options.max_output_voxels = 1000;
  EXPECT_EQ(FillBetweenSlices(drawn, options, context).status().code(),
            absl::StatusCode::kResourceExhausted);
  LabelVolume bad = drawn;
  bad.data.pop_back();
  EXPECT_FALSE(FillBetweenSlices(bad, {}, context).ok());
  CancellationToken cancel;
  cancel.Cancel();
  EXPECT_EQ(FillBetweenSlices(drawn, {}, ComputeContext{.cancel = &cancel})
                .status()
                .code(),
            absl::StatusCode::kCancelled);
}

// A ball of radius `radius` voxels (label 1) centred in a kSize^3 grid, and,
// with `shell` > 0, only its outer `shell` voxels (a thin spherical shell).
constexpr int64_t kSize = 41;
LabelVolume Ball(double radius, double shell, int label = 1) {
  LabelVolume v;
  v.grid.size = {kSize, kSize, kSize};
  v.grid.spacing = {1, 1, 1};
  v.data.assign(v.grid.VoxelCount(), 0);
  const double c = (kSize - 1) / 2.0;
  for (int64_t k = 0; k < kSize; ++k) {
    for (int64_t j = 0; j < kSize; ++j) {
      for (int64_t i = 0; i < kSize; ++i) {
        const double r = std::sqrt((i - c) * (i - c) + (j - c) * (j - c) +
                                   (k - c) * (k - c));
        if (r <= radius && (shell <= 0 || r > radius - shell)) {
          v.at(i, j, k) = label;
        }
      }
    }
  }
  return v;
}

std::vector<int64_t> EveryNth(int64_t n, int64_t nz) {
  std::vector<int64_t> keys;
  for (int64_t k = 0; k < nz; k += n) keys.push_back(k);
  return keys;
}

// Dice of `label` on the slices that are not key slices.
double WithheldDice(const LabelVolume& out, const LabelVolume& truth, int label,
                    const std::vector<int64_t>& keys) {
  int64_t both = 0, na = 0, nb = 0;
  const int64_t plane = truth.grid.SliceVoxelCount();
  for (int64_t k = 0; k < truth.grid.size[2]; ++k) {
    if (std::find(keys.begin(), keys.end(), k) != keys.end()) continue;
    for (int64_t p = k * plane; p < (k + 1) * plane; ++p) {
      na += out.data[p] == label;
      nb += truth.data[p] == label;
      both += out.data[p] == label && truth.data[p] == label;
    }
  }
  return na + nb == 0 ? 1.0 : 2.0 * both / (na + nb);
}

absl::StatusOr<FillResult> FillWith(const std::string& method,
                                    const LabelVolume& drawn,
                                    const std::vector<int64_t>& keys,
                                    int threads = 1) {
  FillOptions options;
  SetMethod(method, options);
  options.key_slices = keys;
  return FillBetweenSlices(drawn, options, ComputeContext{.threads = threads});
}

TEST(AutoFillTest, SphereEveryFourthSliceBeatsLinear) {
  // On a compact smooth shape the refinement follows the curvature along z
  // that linear stacking cuts into straight segments; auto must find that
  // from the key slices alone.
  const LabelVolume truth = Ball(15.3, 0);
  const std::vector<int64_t> keys = EveryNth(4, kSize);
  const LabelVolume drawn = KeepSlices(truth, keys);
  absl::StatusOr<FillResult> automatic = FillWith("auto", drawn, keys);
  absl::StatusOr<FillResult> linear = FillWith("linear", drawn, keys);
  ASSERT_TRUE(automatic.ok()) << automatic.status();
  ASSERT_TRUE(linear.ok()) << linear.status();
  const double dice_auto = WithheldDice(automatic->labels, truth, 1, keys);
  const double dice_linear = WithheldDice(linear->labels, truth, 1, keys);
  EXPECT_GT(dice_auto, dice_linear);
  ASSERT_EQ(automatic->per_label.size(), 1u);
  EXPECT_EQ(automatic->per_label[0].validation_dice.size(), 5u);
  for (int64_t k : keys) {
    for (int64_t p = 0; p < kSize * kSize; ++p) {
      ASSERT_EQ(automatic->labels.data[k * kSize * kSize + p],
                drawn.data[k * kSize * kSize + p]);
    }
  }
}

TEST(AutoFillTest, ThinShellIsNotCollapsed) {
  // A spherical shell 1.5 voxels thick: its 2D distance maps are ridges
  // below one pixel high, which the refinement flattens between key slices
  // (docs/eval/segmentations.md). Auto must keep the shell on every
  // withheld slice and do at least as well as linear stacking.
  const LabelVolume truth = Ball(15.3, 1.5);
  const std::vector<int64_t> keys = EveryNth(4, kSize);
  const LabelVolume drawn = KeepSlices(truth, keys);
  absl::StatusOr<FillResult> automatic = FillWith("auto", drawn, keys);
  absl::StatusOr<FillResult> linear = FillWith("linear", drawn, keys);
  ASSERT_TRUE(automatic.ok()) << automatic.status();
  ASSERT_TRUE(linear.ok()) << linear.status();
  const double dice_auto = WithheldDice(automatic->labels, truth, 1, keys);
  EXPECT_GE(dice_auto, WithheldDice(linear->labels, truth, 1, keys) - 1e-9);
  EXPECT_GT(dice_auto, 0.5);
  // Not collapsed: every withheld slice where the shell's wall is steep
  // (within 8 slices of the centre; toward the poles the wall turns nearly
  // flat and no method keeps it between key slices) keeps at least half of
  // the truth's pixels there.
  for (int64_t k = kSize / 2 - 8; k <= kSize / 2 + 8; ++k) {
    const int64_t want = CountOnSlice(truth, k, 1);
    EXPECT_GT(CountOnSlice(automatic->labels, k, 1), want / 2) << k;
  }
}

TEST(AutoFillTest, TouchingBallAndShellNoGapsKeysExactSameForAnyThreads) {
  // Label 1: a ball; label 2: a shell around it, touching it on every
  // slice that cuts the ball (a compact and a thin structure).
  LabelVolume truth = Ball(9.3, 0, 1);
  const LabelVolume shell = Ball(12.3, 3.0, 2);
  for (size_t n = 0; n < truth.data.size(); ++n) {
    if (truth.data[n] == 0) truth.data[n] = shell.data[n];
  }
  const std::vector<int64_t> keys = EveryNth(3, kSize);
  const LabelVolume drawn = KeepSlices(truth, keys);
  absl::StatusOr<FillResult> one = FillWith("auto", drawn, keys, 1);
  absl::StatusOr<FillResult> two = FillWith("auto", drawn, keys, 2);
  ASSERT_TRUE(one.ok()) << one.status();
  ASSERT_TRUE(two.ok()) << two.status();
  EXPECT_EQ(one->labels.data, two->labels.data);
  ASSERT_EQ(one->per_label.size(), 2u);
  ASSERT_EQ(two->per_label.size(), 2u);
  for (int n = 0; n < 2; ++n) {
    EXPECT_EQ(one->per_label[n].label, n + 1);
    EXPECT_EQ(one->per_label[n].method, two->per_label[n].method);
    EXPECT_EQ(one->per_label[n].validation_dice,
              two->per_label[n].validation_dice);
  }
  const LabelVolume& out = one->labels;
  const int64_t plane = kSize * kSize;
  int64_t gaps = 0;
  for (size_t s = 0; s + 1 < keys.size(); ++s) {
    for (int64_t k = keys[s] + 1; k < keys[s + 1]; ++k) {
      for (int64_t p = 0; p < plane; ++p) {
        gaps += drawn.data[keys[s] * plane + p] != 0 &&
                drawn.data[keys[s + 1] * plane + p] != 0 &&
                out.data[k * plane + p] == 0;
      }
    }
  }
  EXPECT_EQ(gaps, 0);
  for (int64_t k : keys) {
    for (int64_t p = 0; p < plane; ++p) {
      ASSERT_EQ(out.data[k * plane + p], drawn.data[k * plane + p]);
    }
  }
  EXPECT_GT(WithheldDice(out, truth, 1, keys), 0.85);
  EXPECT_GT(WithheldDice(out, truth, 2, keys), 0.6);
}

TEST(AutoFillTest, LabelOnOneKeySliceIsKept) {
  // Among labels drawn on many slices, one drawn on a single key slice is
  // neither dropped nor spread: it stays exactly as drawn on that slice.
  LabelVolume truth = TouchingHalves();
  const LabelVolume drawn_halves = KeepSlices(truth, kKeys);
  LabelVolume drawn = drawn_halves;
  for (int64_t j = 0; j < 3; ++j) {
    for (int64_t i = 0; i < 3; ++i) drawn.at(i, j, 10) = 3;
  }
  absl::StatusOr<FillResult> result =
      FillWith("auto", drawn, std::vector<int64_t>(kKeys));
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(CountOnSlice(result->labels, 10, 3), 9);
  EXPECT_THAT(result->warnings,
              ::testing::Contains(HasSubstr("label 3 is drawn on slice 10")));
  // No validation for it: copied (to the slices nearer to it than to its
  // drawn-and-empty neighbours 5 and 15).
  ASSERT_EQ(result->per_label.size(), 3u);
  EXPECT_EQ(result->per_label[2].method, "copy");
  EXPECT_TRUE(result->per_label[2].validation_dice.empty());
  for (int64_t k = 8; k <= 12; ++k)
    EXPECT_EQ(CountOnSlice(result->labels, k, 3), 9);
  EXPECT_EQ(CountOnSlice(result->labels, 7, 3), 0);
  EXPECT_EQ(CountOnSlice(result->labels, 13, 3), 0);
}

// A small disc moving 12 pixels over two key gaps, three times its
// diameter: no candidate predicts a held-out key slice at the doubled gap,
// so the validation cannot rank them and the morph fills it.
TEST(AutoFillTest, UninformativeValidationGetsTheMorph) {
  LabelVolume truth;
  truth.grid.size = {48, 24, 25};
  truth.data.assign(truth.grid.VoxelCount(), 0);
  for (int64_t k = 0; k < 25; ++k) {
    const double cx = 5 + 1.5 * k;
    for (int64_t j = 0; j < 24; ++j) {
      for (int64_t i = 0; i < 48; ++i) {
        if ((i - cx) * (i - cx) + (j - 12) * (j - 12) <= 4)
          truth.at(i, j, k) = 1;
      }
    }
  }
  const std::vector<int64_t> keys = EveryNth(4, 25);
  absl::StatusOr<FillResult> result =
      FillWith("auto", KeepSlices(truth, keys), keys);
  ASSERT_TRUE(result.ok()) << result.status();
  const LabelFillInfo& info = result->per_label[0];
  ASSERT_EQ(info.validation_dice.size(), 5u);
  for (const auto& [name, dice] : info.validation_dice)
    EXPECT_LT(dice, 0.1) << name;
  EXPECT_EQ(info.method, "morph");
}

// Two discs of radius 5 moving 1.5 pixels per slice (label 1 to +x+y,
// label 2 to -x), never touching: at every 5th slice a key slice, a disc
// moves 7.5 pixels per gap, most of its diameter. Linear stacking of
// their distance maps blends two displaced discs into a smaller lens, the
// morph registers them and carries each disc along its motion.
LabelVolume MovingDiscs() {
  LabelVolume v;
  v.grid.size = {72, 56, 21};
  v.data.assign(v.grid.VoxelCount(), 0);
  for (int64_t k = 0; k < 21; ++k) {
    const double c1x = 8 + 1.2 * k, c1y = 8 + 0.9 * k;
    const double c2x = 62 - 1.5 * k, c2y = 46;
    for (int64_t j = 0; j < 56; ++j) {
      for (int64_t i = 0; i < 72; ++i) {
        if ((i - c1x) * (i - c1x) + (j - c1y) * (j - c1y) <= 25) {
          v.at(i, j, k) = 1;
        } else if ((i - c2x) * (i - c2x) + (j - c2y) * (j - c2y) <= 25) {
          v.at(i, j, k) = 2;
        }
      }
    }
  }
  return v;
}

TEST(MorphFillTest, MovingStructuresFollowTheirMotion) {
  const LabelVolume truth = MovingDiscs();
  const std::vector<int64_t> keys = EveryNth(5, 21);
  const LabelVolume drawn = KeepSlices(truth, keys);
  absl::StatusOr<FillResult> morph = FillWith("morph", drawn, keys, 2);
  absl::StatusOr<FillResult> linear = FillWith("linear", drawn, keys);
  absl::StatusOr<FillResult> automatic = FillWith("auto", drawn, keys);
  ASSERT_TRUE(morph.ok()) << morph.status();
  ASSERT_TRUE(linear.ok() && automatic.ok());
  for (int label : {1, 2}) {
    const double m = WithheldDice(morph->labels, truth, label, keys);
    const double l = WithheldDice(linear->labels, truth, label, keys);
    const double a = WithheldDice(automatic->labels, truth, label, keys);
    EXPECT_GT(m, l + 0.1) << label << ": morph " << m << " linear " << l;
    EXPECT_GT(m, 0.8) << label;
    // auto finds the morph from the key slices alone.
    EXPECT_EQ(automatic->per_label[label - 1].method, "morph") << label;
    EXPECT_EQ(a, m) << label;
    EXPECT_EQ(morph->per_label[label - 1].method, "morph");
  }
  // Key slices exactly as drawn.
  const int64_t plane = truth.grid.SliceVoxelCount();
  for (int64_t k : keys) {
    for (int64_t p = 0; p < plane; ++p) {
      ASSERT_EQ(morph->labels.data[k * plane + p], drawn.data[k * plane + p]);
    }
  }
  // The same for any thread count.
  absl::StatusOr<FillResult> one = FillWith("morph", drawn, keys, 1);
  ASSERT_TRUE(one.ok());
  EXPECT_EQ(one->labels.data, morph->labels.data);
}

// Six labels of every kind the fill schedules differently: a ball and the
// shell around it touching it (compact and thin, each validated), two discs
// moving across the slices (the morph), a label drawn on one key slice only
// and one on three, on 80 x 64 x 25 voxels.
LabelVolume SixLabels() {
  LabelVolume v;
  v.grid.size = {80, 64, 25};
  v.grid.spacing = {0.8, 0.8, 1.5};
  v.data.assign(v.grid.VoxelCount(), 0);
  for (int64_t k = 0; k < 25; ++k) {
    for (int64_t j = 0; j < 64; ++j) {
      for (int64_t i = 0; i < 80; ++i) {
        const double r =
            std::sqrt((i - 20.0) * (i - 20.0) + (j - 21.0) * (j - 21.0) +
                      (k - 12.0) * (k - 12.0) * 0.8);
        const double d3 = std::hypot(i - (42 + 1.1 * k), j - (8 + 0.8 * k));
        const double d4 = std::hypot(i - (75 - 1.3 * k), j - 52.0);
        uint16_t label = 0;
        if (r <= 9.2) {
          label = 1;
        } else if (r <= 12.6) {
          label = 2;
        } else if (d3 <= 5.5) {
          label = 3;
        } else if (d4 <= 5.2) {
          label = 4;
        } else if (k == 10 && i >= 58 && i < 63 && j >= 28 && j < 34) {
          label = 5;
        } else if (k >= 4 && k <= 16 &&
                   std::hypot(i - 30.0, j - 50.0) <=
                       3.0 + 0.2 * std::abs(k - 10.0)) {
          label = 6;
        }
        v.at(i, j, k) = label;
      }
    }
  }
  return v;
}

// Labels run concurrently, and the scans before and after them run per
// slice on the context's threads: the label map, the counts, the per-label
// report and the meshing fields must be the same for 1, 2 and 4 threads,
// with the key slices given and detected, on the input grid and with twice
// the slices.
TEST(AutoFillTest, SameResultForOneTwoAndFourThreads) {
  const LabelVolume truth = SixLabels();
  const std::vector<int64_t> keys = EveryNth(5, 25);
  const LabelVolume drawn = KeepSlices(truth, keys);
  for (const bool detect : {false, true}) {
    SCOPED_TRACE(detect ? "key slices detected, factor 2" : "keys given");
    FillOptions options;
    options.keep_fields = true;
    if (detect) {
      options.z_resolution.factor = 2;
    } else {
      options.key_slices = keys;
    }
    absl::StatusOr<FillResult> one =
        FillBetweenSlices(drawn, options, ComputeContext{.threads = 1});
    ASSERT_TRUE(one.ok()) << one.status();
    ASSERT_EQ(one->per_label.size(), 6u);
    // The case holds what it is meant to: the moving discs morphed, the
    // one-slice label copied, labels filled between their key slices.
    EXPECT_EQ(one->per_label[2].method, "morph");
    EXPECT_EQ(one->per_label[3].method, "morph");
    EXPECT_EQ(one->per_label[4].method, "copy");
    EXPECT_EQ(one->per_label[4].drawn_slices, 1);
    EXPECT_FALSE(one->per_label[0].validation_dice.empty());
    const int64_t out_plane = one->labels.grid.SliceVoxelCount();
    EXPECT_GT(std::count(
                  one->labels.data.begin() + 12 * one->factor * out_plane,
                  one->labels.data.begin() + (12 * one->factor + 1) * out_plane,
                  uint16_t{1}),
              100);
    for (const int threads : {2, 4}) {
      SCOPED_TRACE(threads);
      absl::StatusOr<FillResult> many =
          FillBetweenSlices(drawn, options, ComputeContext{.threads = threads});
      ASSERT_TRUE(many.ok()) << many.status();
      EXPECT_EQ(many->labels.grid.size, one->labels.grid.size);
      EXPECT_TRUE(many->labels.data == one->labels.data);
      EXPECT_EQ(many->gap_voxels_closed, one->gap_voxels_closed);
      EXPECT_EQ(many->key_voxels_restored, one->key_voxels_restored);
      EXPECT_EQ(many->warnings, one->warnings);
      ASSERT_EQ(many->per_label.size(), one->per_label.size());
      for (size_t n = 0; n < one->per_label.size(); ++n) {
        const LabelFillInfo& a = one->per_label[n];
        const LabelFillInfo& b = many->per_label[n];
        EXPECT_EQ(b.label, a.label);
        EXPECT_EQ(b.key_slices, a.key_slices);
        EXPECT_EQ(b.method, a.method) << a.label;
        EXPECT_EQ(b.output_voxels, a.output_voxels) << a.label;
        EXPECT_EQ(b.validation_dice, a.validation_dice) << a.label;
        EXPECT_EQ(b.validation_dice_4g, a.validation_dice_4g) << a.label;
        EXPECT_TRUE(b.field.data == a.field.data) << a.label;
      }
    }
  }
}

// Each scored held-out key slice's own Dice (LabelFillInfo::
// validation_slice_dice): at most 8 slices per gap, in the report's
// candidate order, each in [0, 1] (the morph -1 when not tried), varying
// from slice to slice on a ball, with the pooled Dice between their extremes
// and not equal to the last slice's (which a running total would give).
TEST(AutoFillTest, ValidationRecordsEachScoredSlicesDice) {
  const LabelVolume truth = Ball(15.3, 0);
  const std::vector<int64_t> keys = EveryNth(3, kSize);  // 14 key slices
  FillOptions options;
  options.key_slices = keys;
  options.selection = AutoSelection::kGapTrend;
  absl::StatusOr<FillResult> trend = FillBetweenSlices(
      KeepSlices(truth, keys), options, ComputeContext{.threads = 1});
  ASSERT_TRUE(trend.ok()) << trend.status();
  const LabelFillInfo& t = trend->per_label[0];
  // 12 inner key slices held out once at 2g, three times at 4g: 8 scored.
  ASSERT_EQ(t.validation_slice_dice.size(), 8u);
  ASSERT_EQ(t.validation_slice_dice_4g.size(), 8u);
  for (const auto* rows :
       {&t.validation_slice_dice, &t.validation_slice_dice_4g}) {
    const auto& pooled = rows == &t.validation_slice_dice
                             ? t.validation_dice
                             : t.validation_dice_4g;
    for (size_t c = 0; c < 5; ++c) {
      double low = 2, high = -1;
      for (const std::vector<double>& row : *rows) {
        ASSERT_EQ(row.size(), 5u);
        EXPECT_GE(row[c], 0) << pooled[c].first;
        EXPECT_LE(row[c], 1) << pooled[c].first;
        low = std::min(low, row[c]);
        high = std::max(high, row[c]);
      }
      EXPECT_LT(low, high) << pooled[c].first;
      EXPECT_GE(pooled[c].second, low) << pooled[c].first;
      EXPECT_LE(pooled[c].second, high) << pooled[c].first;
      EXPECT_NE(rows->back()[c], pooled[c].second) << pooled[c].first;
    }
  }
  // Without the morph: its column is -1; the doubled-gap rule scores no
  // quadrupled gap.
  options.selection = AutoSelection::kDoubledGap;
  options.auto_morph = false;
  absl::StatusOr<FillResult> doubled = FillBetweenSlices(
      KeepSlices(truth, keys), options, ComputeContext{.threads = 1});
  ASSERT_TRUE(doubled.ok()) << doubled.status();
  const LabelFillInfo& d = doubled->per_label[0];
  EXPECT_TRUE(d.validation_slice_dice_4g.empty());
  ASSERT_EQ(d.validation_slice_dice.size(), 8u);
  for (const std::vector<double>& row : d.validation_slice_dice) {
    EXPECT_EQ(row[4], -1);  // morph
  }
  // The same folds as the trend rule's, for the candidates both tried.
  for (size_t n = 0; n < 8; ++n) {
    for (size_t c = 0; c < 4; ++c) {
      EXPECT_EQ(d.validation_slice_dice[n][c], t.validation_slice_dice[n][c]);
    }
  }
}

// The morph's validation scores the morph the fill runs: a held-out key
// slice's morph Dice is what --method morph gives on that slice when it is
// filled from the fold's kept key slices, cubic trajectory (Catmull-Rom
// tangents from the neighbouring gaps) included. Regression: the validation
// registered only the two kept key slices around the slice, a morph the
// fill never runs (straight trajectory, linear values), so it misjudged the
// morph wherever a structure turns or swells between key slices.
TEST(AutoFillTest, MorphValidationScoresTheFillsOwnMorph) {
  // A disc that swells and shrinks while its centre moves along a curve,
  // drawn on all 9 slices (the key slices; no drawn-and-empty ends at the
  // series' edges). The doubled gap's first fold keeps slices 0, 2, 4, 6, 8
  // and holds out 1, 3, 5, 7 (7 held-out slices in all: every one scored).
  constexpr int64_t kSide = 24;
  LabelVolume truth;
  truth.grid.size = {kSide, kSide, 9};
  truth.data.assign(truth.grid.VoxelCount(), 0);
  for (int64_t k = 0; k < 9; ++k) {
    const double cx = 12 + 5 * std::sin(0.5 * k),
                 cy = 11 + 3 * std::cos(0.7 * k);
    const double r = 5 + 2 * std::sin(0.6 * k);
    for (int64_t j = 0; j < kSide; ++j) {
      for (int64_t i = 0; i < kSide; ++i) {
        if ((i - cx) * (i - cx) + (j - cy) * (j - cy) <= r * r) {
          truth.at(i, j, k) = 1;
        }
      }
    }
  }
  const std::vector<int64_t> kept = {0, 2, 4, 6, 8};
  // Both fills' boxes must be the whole slice (the morph's options and its
  // registration depend on the box): the kept slices' drawing comes within
  // the margin (6 pixels) of every edge.
  int64_t i0 = kSide, i1 = 0, j0 = kSide, j1 = 0;
  for (int64_t k : kept) {
    for (int64_t j = 0; j < kSide; ++j) {
      for (int64_t i = 0; i < kSide; ++i) {
        if (truth.at(i, j, k) != 1) continue;
        i0 = std::min(i0, i), i1 = std::max(i1, i + 1);
        j0 = std::min(j0, j), j1 = std::max(j1, j + 1);
      }
    }
  }
  ASSERT_TRUE(i0 <= 6 && j0 <= 6 && i1 >= kSide - 6 && j1 >= kSide - 6)
      << i0 << " " << i1 << " " << j0 << " " << j1;

  absl::StatusOr<FillResult> validated =
      FillBetweenSlices(truth, FillOptions(), ComputeContext{.threads = 1});
  ASSERT_TRUE(validated.ok()) << validated.status();
  const std::vector<std::vector<double>>& rows =
      validated->per_label[0].validation_slice_dice;
  ASSERT_EQ(rows.size(), 7u);

  FillOptions morph;
  SetMethod("morph", morph);
  morph.key_slices = kept;
  morph.keep_fields = true;
  absl::StatusOr<FillResult> filled = FillBetweenSlices(
      KeepSlices(truth, kept), morph, ComputeContext{.threads = 1});
  ASSERT_TRUE(filled.ok()) << filled.status();
  const Volume<float>& field = filled->per_label[0].field;
  ASSERT_EQ(field.grid.size[0], kSide);
  ASSERT_EQ(field.grid.size[1], kSide);
  ASSERT_EQ(field.grid.size[2], 9);
  const std::vector<int64_t> held = {1, 3, 5, 7};
  for (size_t h = 0; h < held.size(); ++h) {
    int64_t both = 0, in = 0, drawn = 0;
    for (int64_t j = 0; j < kSide; ++j) {
      for (int64_t i = 0; i < kSide; ++i) {
        const bool inside = field.at(i, j, held[h]) > 0;
        const bool truth_in = truth.at(i, j, held[h]) == 1;
        in += inside;
        drawn += truth_in;
        both += inside && truth_in;
      }
    }
    const double dice = 2.0 * both / static_cast<double>(in + drawn);
    EXPECT_NEAR(rows[h][4], dice, 1e-12) << "slice " << held[h];
  }
}

// What the selection saw, per rule: the doubled-gap Dice always (three or
// more key slices), the quadrupled-gap Dice with the trend rule and six or
// more key slices, and the score the choice was made on (the power-law
// trend of the error, or D(2g)); without auto_morph the morph is not tried.
// The default rule is the doubled gap.
TEST(AutoFillTest, SelectionReportsWhatItSaw) {
  const LabelVolume truth = Ball(15.3, 0);
  const std::vector<int64_t> keys = EveryNth(3, kSize);  // 14 key slices
  const LabelVolume drawn = KeepSlices(truth, keys);
  FillOptions options;
  options.key_slices = keys;
  options.selection = AutoSelection::kGapTrend;
  absl::StatusOr<FillResult> trend =
      FillBetweenSlices(drawn, options, ComputeContext{.threads = 1});
  ASSERT_TRUE(trend.ok()) << trend.status();
  const LabelFillInfo& t = trend->per_label[0];
  ASSERT_EQ(t.validation_dice.size(), 5u);
  ASSERT_EQ(t.validation_dice_4g.size(), 5u);
  ASSERT_EQ(t.validation_score.size(), 5u);
  std::string best;
  double best_score = -1e9;
  for (size_t c = 0; c < 5; ++c) {
    EXPECT_EQ(t.validation_dice[c].first, t.validation_score[c].first);
    // The power law of the error: e(g) = e(2g) 2^-p, e(4g) = e(2g) 2^p,
    // p in [0, 2].
    const double e2 = 1 - t.validation_dice[c].second;
    const double e4 = 1 - t.validation_dice_4g[c].second;
    const double p = std::clamp(std::log2(e4 / e2), 0.0, 2.0);
    EXPECT_NEAR(t.validation_score[c].second, 1 - e2 * std::exp2(-p), 1e-9);
    EXPECT_GE(t.validation_score[c].second, t.validation_dice[c].second);
    // Quadrupling the gap costs every candidate on a ball.
    EXPECT_LT(t.validation_dice_4g[c].second, t.validation_dice[c].second)
        << t.validation_dice[c].first;
    if (t.validation_score[c].second > best_score) {
      best_score = t.validation_score[c].second;
      best = t.validation_score[c].first;
    }
  }
  EXPECT_EQ(t.method, best);

  options.selection = AutoSelection::kDoubledGap;
  options.auto_morph = false;
  absl::StatusOr<FillResult> doubled =
      FillBetweenSlices(drawn, options, ComputeContext{.threads = 1});
  ASSERT_TRUE(doubled.ok());
  const LabelFillInfo& d = doubled->per_label[0];
  EXPECT_TRUE(d.validation_dice_4g.empty());
  ASSERT_EQ(d.validation_score.size(), 5u);
  for (size_t c = 0; c < 5; ++c) {
    EXPECT_EQ(d.validation_score[c].second, d.validation_dice[c].second);
    // The same doubled-gap folds as the trend rule saw.
    if (d.validation_dice[c].first != "morph") {
      EXPECT_EQ(d.validation_dice[c].second, t.validation_dice[c].second);
    } else {
      EXPECT_EQ(d.validation_dice[c].second, -1);
    }
  }
  EXPECT_NE(d.method, "morph");

  // Five key slices: too few for the quadrupled gap; the doubled gap rules.
  const std::vector<int64_t> few = {0, 10, 20, 30, 40};
  options = FillOptions();
  options.key_slices = few;
  options.selection = AutoSelection::kGapTrend;
  absl::StatusOr<FillResult> short_label = FillBetweenSlices(
      KeepSlices(truth, few), options, ComputeContext{.threads = 1});
  ASSERT_TRUE(short_label.ok());
  EXPECT_TRUE(short_label->per_label[0].validation_dice_4g.empty());
  EXPECT_EQ(short_label->per_label[0].validation_dice.size(), 5u);

  // By default: the doubled gap alone (with the morph), even with the 14
  // key slices that give the trend rule its quadrupled gap.
  options = FillOptions();
  options.key_slices = keys;
  absl::StatusOr<FillResult> by_default =
      FillBetweenSlices(drawn, options, ComputeContext{.threads = 1});
  ASSERT_TRUE(by_default.ok());
  const LabelFillInfo& f = by_default->per_label[0];
  EXPECT_TRUE(f.validation_dice_4g.empty());
  EXPECT_TRUE(f.validation_slice_dice_4g.empty());
  ASSERT_EQ(f.validation_score.size(), 5u);
  best.clear();
  best_score = -1e9;
  for (size_t c = 0; c < 5; ++c) {
    EXPECT_EQ(f.validation_dice[c], t.validation_dice[c]);
    EXPECT_EQ(f.validation_score[c], f.validation_dice[c]);
    if (f.validation_score[c].second > best_score) {
      best_score = f.validation_score[c].second;
      best = f.validation_score[c].first;
    }
  }
  EXPECT_EQ(f.method, best);
}

TEST(LabelVolumeTest, FromFloatRejectsNonLabels) {
  Volume<float> v;
  v.grid.size = {3, 2, 2};
  v.data.assign(12, 0.0f);
  v.data[4] = 3;
  absl::StatusOr<LabelVolume> ok = LabelVolumeFromFloat(v);
  ASSERT_TRUE(ok.ok());
  EXPECT_EQ(ok->data[4], 3);
  v.data[7] = 2.5f;
  EXPECT_THAT(LabelVolumeFromFloat(v).status().message(),
              HasSubstr("voxel (1, 0, 1) holds 2.5"));
  v.data[7] = -1;
  EXPECT_FALSE(LabelVolumeFromFloat(v).ok());
  v.data[7] = 70000;
  EXPECT_FALSE(LabelVolumeFromFloat(v).ok());
}

TEST(LabelVolumeTest, CheckSameGridNamesTheDifference) {
  Grid ref;
  ref.size = {10, 10, 5};
  ref.spacing = {0.5, 0.5, 3};
  ref.origin = {-10, 20, 30};
  EXPECT_TRUE(CheckSameGrid(ref, ref, "the label map").ok());
  Grid g = ref;
  g.origin[2] += 1e-4;  // float rounding of a NIfTI header
  EXPECT_TRUE(CheckSameGrid(g, ref, "the label map").ok());
  g = ref;
  g.size[2] = 6;
  EXPECT_THAT(CheckSameGrid(g, ref, "the label map").message(),
              HasSubstr("10 x 10 x 6 voxels"));
  g = ref;
  g.spacing[2] = 2.5;
  EXPECT_THAT(CheckSameGrid(g, ref, "the label map").message(),
              HasSubstr("z spacing 2.5"));
  g = ref;
  g.origin[0] = -9;
  EXPECT_THAT(CheckSameGrid(g, ref, "the label map").message(),
              HasSubstr("origin"));
  g = ref;
  g.direction = {1, 0, 0, 0, -1, 0, 0, 0, -1};
  EXPECT_THAT(CheckSameGrid(g, ref, "the label map").message(),
              HasSubstr("direction"));
}

TEST(LabelVolumeTest, Uint16LabelMapRoundTrip) {
  LabelVolume v;
  v.grid.size = {5, 4, 3};
  v.grid.spacing = {0.7, 0.7, 2};
  v.grid.origin = {1, 2, 3};
  v.data.assign(v.grid.VoxelCount(), 0);
  v.data[7] = 300;
  v.data[20] = 65535;
  const std::string path =
      (std::filesystem::temp_directory_path() /
       ("label_fill_test_" + std::to_string(getpid()) + ".nrrd"))
          .string();
  ASSERT_TRUE(WriteVolume(v, path).ok());
  absl::StatusOr<Volume<float>> back = ReadVolumeAsFloat(path);
  std::filesystem::remove(path);
  ASSERT_TRUE(back.ok()) << back.status();
  absl::StatusOr<LabelVolume> labels = LabelVolumeFromFloat(*back);
  ASSERT_TRUE(labels.ok());
  EXPECT_EQ(labels->data, v.data);
  EXPECT_TRUE(CheckSameGrid(labels->grid, v.grid, "x").ok());
}

}  // namespace
}  // namespace interslice

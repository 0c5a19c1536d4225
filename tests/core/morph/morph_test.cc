#include "core/morph/morph.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

#include "core/stack/stacking.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "itkFastSymmetricForcesDemonsRegistrationFilter.h"
#include "itkImage.h"
#include "itkMultiResolutionPDEDeformableRegistration.h"
#include "itkMultiThreaderBase.h"

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

// The piecewise-linear trajectory (the tests written for it); the cubic
// tests below use CubicOptions.
MorphOptions SmallOptions() {
  MorphOptions o;
  o.trajectory = MorphTrajectory::kPiecewiseLinear;
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

  // Both trajectories (with one gap the cubic's tangents are one-sided, so
  // its trajectory is the straight one too).
  for (MorphTrajectory trajectory :
       {MorphTrajectory::kPiecewiseLinear, MorphTrajectory::kCubic}) {
    MorphOptions options = SmallOptions();
    options.trajectory = trajectory;
    auto morphed = StackMorph(maps, plan, options, int64_t{1} << 30, context);
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
}

TEST(StackMorphTest, DefaultIsTheCubicTrajectoryWithoutRefinement) {
  // What --method morph runs (docs/eval/candidates.md).
  const MorphOptions defaults;
  EXPECT_EQ(defaults.trajectory, MorphTrajectory::kCubic);
  EXPECT_EQ(defaults.values, MorphValues::kMonotone);
  EXPECT_FALSE(defaults.refine);
}

TEST(StackMorphTest, OriginalSlicesAreBitIdenticalAndGridMatchesLinear) {
  const Volume<float> maps = TwoDiscs(28, 34, 30, 9);
  const StackPlan plan = UniformStackPlan(2, 4.0, 3);
  ComputeContext context;
  auto linear = StackLinear(maps, plan, int64_t{1} << 30, context);
  for (const MorphOptions& options : {SmallOptions(), MorphOptions()}) {
    auto morphed = StackMorph(maps, plan, options, int64_t{1} << 30, context);
    ASSERT_TRUE(linear.ok() && morphed.ok());
    const StackedField& m = morphed->stacked;
    EXPECT_EQ(m.field.grid.size, linear->field.grid.size);
    EXPECT_EQ(m.fixed_slices, linear->fixed_slices);
    const int64_t plane = kN * kN;
    for (int64_t k : {0, 3}) {
      for (int64_t v = 0; v < plane; ++v) {
        ASSERT_EQ(m.field.data[k * plane + v],
                  linear->field.data[k * plane + v]);
      }
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

// The gaps are registered in parallel, but ComputeContext::Report is never
// called concurrently (compute.h): a worker process writes each report as a
// frame of its protocol, and two at once corrupt it.
TEST(StackMorphTest, ProgressIsNeverReportedConcurrently) {
  // Four slices (three gaps, registered concurrently with 2 threads).
  Volume<float> maps = TwoDiscs(20, 30, 32, 8);
  const Volume<float> more = TwoDiscs(38, 44, 32, 8);
  maps.grid.size[2] = 4;
  maps.data.insert(maps.data.end(), more.data.begin(),
                   more.data.begin() + 2 * kN * kN);
  const StackPlan plan = UniformStackPlan(4, 4.0, 4);
  std::atomic<int> inside{0}, most{0}, calls{0};
  ComputeContext context;
  context.threads = 2;
  context.progress = [&](const ProgressEvent&) {
    const int now = ++inside;
    most = std::max(most.load(), now);
    ++calls;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    --inside;
  };
  auto stacked =
      StackMorph(maps, plan, SmallOptions(), int64_t{1} << 30, context);
  ASSERT_TRUE(stacked.ok()) << stacked.status();
  EXPECT_GE(calls.load(), 3);  // one report a gap at least
  EXPECT_EQ(most.load(), 1);
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

// A stack of disc distance maps (mm, positive inside; pixel 0.5 mm), disc s
// centred at (cx[s], cy), radius r pixels.
Volume<float> Discs(const std::vector<double>& cx, double cy, double r) {
  Volume<float> maps;
  const int64_t z = static_cast<int64_t>(cx.size());
  maps.grid.size = {kN, kN, z};
  maps.grid.spacing = {0.5, 0.5, 4.0};
  maps.data.resize(kN * kN * z);
  for (int64_t s = 0; s < z; ++s)
    for (int64_t j = 0; j < kN; ++j)
      for (int64_t i = 0; i < kN; ++i)
        maps.data[i + kN * (j + kN * s)] =
            static_cast<float>(0.5 * (r - std::hypot(i - cx[s], j - cy)));
  return maps;
}

MorphOptions CubicOptions() {
  MorphOptions o = SmallOptions();
  o.trajectory = MorphTrajectory::kCubic;
  return o;
}

// Mean |second z-difference| of the field near its zero level (|f| < 1 mm)
// on the given slices: the crease measure of docs/eval (CreaseIndex).
double MeanCurvatureNearSurface(const Volume<float>& f,
                                const std::vector<int64_t>& slices) {
  double total = 0;
  int64_t count = 0;
  for (int64_t k : slices)
    for (int64_t j = 0; j < kN; ++j)
      for (int64_t i = 0; i < kN; ++i) {
        if (std::abs(f.at(i, j, k)) > 1.0f) continue;
        total += std::abs(f.at(i, j, k + 1) - 2.0 * f.at(i, j, k) +
                          f.at(i, j, k - 1));
        ++count;
      }
  return count > 0 ? total / count : 0;
}

TEST(StackMorphCubicTest, ZeroDisplacementIsCatmullRomOfTheValues) {
  // With no registration (u = 0) the trajectory is the pixel itself and the
  // cubic interpolates its four key values by Catmull-Rom; checked against
  // the closed form on a 4-slice stack, factor 4 (t = 1/4, 1/2, 3/4).
  const Volume<float> maps = Discs({20, 26, 34, 44}, 32, 8);
  const StackPlan plan = UniformStackPlan(4, 4.0, 4);
  MorphOptions o = CubicOptions();
  o.iterations = 0;
  o.values = MorphValues::kCatmullRom;
  ComputeContext context;
  auto morphed = StackMorph(maps, plan, o, int64_t{1} << 30, context);
  ASSERT_TRUE(morphed.ok()) << morphed.status();
  const Volume<float>& f = morphed->stacked.field;
  auto key = [&](int64_t s, int64_t i, int64_t j) {
    return static_cast<double>(maps.data[i + kN * (j + kN * s)]);
  };
  for (int64_t i : {10, 25, 30, 40, 50}) {
    const int64_t j = 30;
    for (int64_t s = 0; s < 3; ++s) {
      const double a0 = key(s, i, j), a1 = key(s + 1, i, j);
      const double m0 = s > 0 ? (a1 - key(s - 1, i, j)) / 2 : a1 - a0;
      const double m1 = s < 2 ? (key(s + 2, i, j) - a0) / 2 : a1 - a0;
      for (int64_t q = 1; q < 4; ++q) {
        const double t = q / 4.0;
        const double expected = (2 * t * t * t - 3 * t * t + 1) * a0 +
                                (t * t * t - 2 * t * t + t) * m0 +
                                (3 * t * t - 2 * t * t * t) * a1 +
                                (t * t * t - t * t) * m1;
        EXPECT_NEAR(f.at(i, j, 4 * s + q), expected, 1e-4)
            << "i " << i << " gap " << s << " t " << t;
      }
    }
  }
  // The key slices are never rewritten.
  for (int64_t s = 0; s < 4; ++s)
    for (int64_t v = 0; v < kN * kN; ++v)
      ASSERT_EQ(f.data[4 * s * kN * kN + v], maps.data[s * kN * kN + v]);
  // Smoothstep values: the convex blend a0 + (a1 - a0)(3t^2 - 2t^3).
  o.values = MorphValues::kSmoothstep;
  auto smooth = StackMorph(maps, plan, o, int64_t{1} << 30, context);
  ASSERT_TRUE(smooth.ok()) << smooth.status();
  for (int64_t i : {10, 25, 30, 40, 50})
    for (int64_t s = 0; s < 3; ++s)
      for (int64_t q = 1; q < 4; ++q) {
        const double t = q / 4.0, a0 = key(s, i, 30), a1 = key(s + 1, i, 30);
        EXPECT_NEAR(smooth->stacked.field.at(i, 30, 4 * s + q),
                    a0 + (a1 - a0) * (3 * t * t - 2 * t * t * t), 1e-4);
      }
  o.values = static_cast<MorphValues>(9);
  EXPECT_EQ(
      StackMorph(maps, plan, o, int64_t{1} << 30, context).status().code(),
      absl::StatusCode::kInvalidArgument);
}

TEST(StackMorphCubicTest, MonotoneValuesArePchipAndNeverOvershoot) {
  // u = 0 again: each pixel's key values interpolated in z by the monotone
  // cubic (PCHIP, Fritsch & Carlson 1980): the tangent at an interior key
  // slice is the harmonic mean of the two gap differences when they agree in
  // sign, else 0; one-sided (the gap difference) at the ends. A disc moving
  // across the pixels makes their key values rise and fall, where
  // Catmull-Rom overshoots the key values and PCHIP must not.
  const Volume<float> maps = Discs({20, 26, 34, 44}, 32, 8);
  const StackPlan plan = UniformStackPlan(4, 4.0, 4);
  MorphOptions o = CubicOptions();
  o.iterations = 0;
  o.values = MorphValues::kMonotone;
  ComputeContext context;
  auto mono = StackMorph(maps, plan, o, int64_t{1} << 30, context);
  o.values = MorphValues::kCatmullRom;
  auto catmull = StackMorph(maps, plan, o, int64_t{1} << 30, context);
  ASSERT_TRUE(mono.ok() && catmull.ok()) << mono.status();
  auto key = [&](int64_t s, int64_t i, int64_t j) {
    return static_cast<double>(maps.data[i + kN * (j + kN * s)]);
  };
  auto tangent = [&](int64_t s, int64_t i, int64_t j) {
    const double before = key(s, i, j) - key(s - 1, i, j);
    const double after = key(s + 1, i, j) - key(s, i, j);
    return before * after > 0 ? 2 * before * after / (before + after) : 0.0;
  };
  int64_t catmull_overshoots = 0;
  for (int64_t j = 0; j < kN; ++j)
    for (int64_t i = 0; i < kN; ++i)
      for (int64_t s = 0; s < 3; ++s) {
        const double a0 = key(s, i, j), a1 = key(s + 1, i, j);
        const double m0 = s > 0 ? tangent(s, i, j) : a1 - a0;
        const double m1 = s < 2 ? tangent(s + 1, i, j) : a1 - a0;
        const double lo = std::min(a0, a1), hi = std::max(a0, a1);
        for (int64_t q = 1; q < 4; ++q) {
          const double t = q / 4.0;
          const double expected = (2 * t * t * t - 3 * t * t + 1) * a0 +
                                  (t * t * t - 2 * t * t + t) * m0 +
                                  (3 * t * t - 2 * t * t * t) * a1 +
                                  (t * t * t - t * t) * m1;
          const double got = mono->stacked.field.at(i, j, 4 * s + q);
          ASSERT_NEAR(got, expected, 1e-4)
              << "i " << i << " j " << j << " gap " << s << " t " << t;
          ASSERT_GE(got, lo - 1e-5);
          ASSERT_LE(got, hi + 1e-5);
          const double cr = catmull->stacked.field.at(i, j, 4 * s + q);
          if (cr < lo - 1e-3 || cr > hi + 1e-3) ++catmull_overshoots;
        }
      }
  // The data do exercise the limiter: Catmull-Rom leaves the key range.
  EXPECT_GT(catmull_overshoots, 100);
  // Values linear along z are reproduced exactly (equal gap differences:
  // the harmonic mean is the difference itself).
  Volume<float> ramp = maps;
  for (int64_t s = 0; s < 4; ++s)
    for (int64_t v = 0; v < kN * kN; ++v)
      ramp.data[s * kN * kN + v] = static_cast<float>(0.1 * (v % kN) - 2 + s);
  o.values = MorphValues::kMonotone;
  auto linear = StackMorph(ramp, plan, o, int64_t{1} << 30, context);
  ASSERT_TRUE(linear.ok()) << linear.status();
  for (int64_t k = 0; k < 13; ++k)
    for (int64_t i = 0; i < kN; i += 7)
      EXPECT_NEAR(linear->stacked.field.at(i, 5, k), 0.1 * i - 2 + k / 4.0,
                  1e-5);
  // Uneven gaps (2, 5, 3 output slices): still inside every key range, key
  // slices kept.
  StackPlan uneven = UniformStackPlan(4, 4.0, 4);
  uneven.nodes = {0, 2, 7, 10};
  uneven.output_slices = 11;
  uneven.uniform = false;
  auto skewed = StackMorph(maps, uneven, o, int64_t{1} << 30, context);
  ASSERT_TRUE(skewed.ok()) << skewed.status();
  for (int64_t s = 0; s < 3; ++s)
    for (int64_t k = uneven.nodes[s]; k <= uneven.nodes[s + 1]; ++k)
      for (int64_t i = 0; i < kN; i += 3) {
        const double a0 = key(s, i, 30), a1 = key(s + 1, i, 30);
        const double got = skewed->stacked.field.at(i, 30, k);
        ASSERT_GE(got, std::min(a0, a1) - 1e-5) << "k " << k << " i " << i;
        ASSERT_LE(got, std::max(a0, a1) + 1e-5) << "k " << k << " i " << i;
      }
}

TEST(StackMorphCubicTest, DefaultsFollowACurvedTubeThatLinearStackingLoses) {
  // What --method morph runs (MorphOptions' defaults, as the pipeline uses
  // them: registration at 1/4 resolution, cubic trajectory, monotone values)
  // against the analytic shape: a tube of radius 6 px whose centre
  // accelerates along x, cx(z) = 12 + z^2 / 8 px (z in mm, key slices every
  // 4 mm: 12, 14, 20, 30, 44), sampled every 1 mm. Linear stacking loses the
  // disc in the gaps where it moves farther than its diameter; the morph
  // must follow it. Dice over the withheld slices only (as docs/eval).
  constexpr double kRadius = 6;
  auto centre = [](double z_mm) { return 12 + z_mm * z_mm / 8; };
  const Volume<float> maps = Discs(
      {centre(0), centre(4), centre(8), centre(12), centre(16)}, 32, kRadius);
  const StackPlan plan = UniformStackPlan(5, 4.0, 4);
  ComputeContext context;
  MorphOptions defaults;
  auto morphed = StackMorph(maps, plan, defaults, int64_t{1} << 30, context);
  MorphOptions none = defaults;
  none.iterations = 0;
  none.trajectory = MorphTrajectory::kPiecewiseLinear;  // = linear stacking
  auto linear = StackMorph(maps, plan, none, int64_t{1} << 30, context);
  ASSERT_TRUE(morphed.ok() && linear.ok()) << morphed.status();
  auto dice = [&](const Volume<float>& f) {
    int64_t both = 0, in_f = 0, in_truth = 0;
    for (int64_t k = 0; k < 17; ++k) {
      if (k % 4 == 0) continue;
      for (int64_t j = 0; j < kN; ++j)
        for (int64_t i = 0; i < kN; ++i) {
          const bool truth = std::hypot(i - centre(k), j - 32.0) <= kRadius;
          const bool mine = f.at(i, j, k) >= 0;
          both += truth && mine;
          in_f += mine;
          in_truth += truth;
        }
    }
    return 2.0 * both / static_cast<double>(in_f + in_truth);
  };
  const double morph_dice = dice(morphed->stacked.field);
  const double linear_dice = dice(linear->stacked.field);
  RecordProperty("morph_dice", std::to_string(morph_dice));
  RecordProperty("linear_dice", std::to_string(linear_dice));
  // Measured: morph 0.989, linear stacking 0.805.
  EXPECT_GT(morph_dice, 0.95) << "linear " << linear_dice;
  EXPECT_GT(morph_dice, linear_dice + 0.1);
}

TEST(StackMorphCubicTest, ConstantVelocityGivesTheLinearMotion) {
  // A disc translating 6 px per key slice: every gap's registration is the
  // same, so the Catmull-Rom trajectory is the straight line and the cubic
  // morph moves the disc uniformly, as the piecewise one does.
  const Volume<float> maps = Discs({17, 23, 29, 35, 41}, 32, 8);
  const StackPlan plan = UniformStackPlan(5, 4.0, 4);
  ComputeContext context;
  auto cubic =
      StackMorph(maps, plan, CubicOptions(), int64_t{1} << 30, context);
  auto piecewise =
      StackMorph(maps, plan, SmallOptions(), int64_t{1} << 30, context);
  ASSERT_TRUE(cubic.ok() && piecewise.ok());
  const Volume<float>& f = cubic->stacked.field;
  const double disc = M_PI * 8 * 8;
  for (int64_t k = 1; k < 16; ++k) {
    if (k % 4 == 0) continue;
    SCOPED_TRACE(k);
    const Blob b = Inside(f, k);
    EXPECT_NEAR(b.cx, 17 + 6.0 * k / 4, 0.5);
    EXPECT_NEAR(b.cy, 32, 0.5);
    EXPECT_NEAR(b.area, disc, 0.1 * disc);
    // Within the interior gaps (both tangents from registrations) the two
    // trajectories coincide up to the registrations' differences.
    const Blob p = Inside(piecewise->stacked.field, k);
    EXPECT_NEAR(b.cx, p.cx, 0.3);
    EXPECT_NEAR(b.area, p.area, 0.05 * disc);
  }
}

TEST(StackMorphCubicTest, AcceleratingDiscHasNoCreaseAtTheKeySlices) {
  // A disc accelerating (4, 8, 12 px per gap): the piecewise morph changes
  // velocity abruptly at the key slices, so the field's second z-difference
  // there is much larger than inside the gaps; the cubic one is C1, so its
  // second difference at a key slice is that of its neighbours (a moving
  // disc's field has some everywhere: the distance map is curved). On this
  // stack: piecewise key / inserted 2.5, cubic 1.1, cubic key / piecewise
  // key 0.55.
  const Volume<float> maps = Discs({14, 18, 26, 38}, 32, 8);
  const StackPlan plan = UniformStackPlan(4, 4.0, 4);
  ComputeContext context;
  auto cubic =
      StackMorph(maps, plan, CubicOptions(), int64_t{1} << 30, context);
  auto piecewise =
      StackMorph(maps, plan, SmallOptions(), int64_t{1} << 30, context);
  ASSERT_TRUE(cubic.ok() && piecewise.ok());
  const std::vector<int64_t> keys = {4, 8};
  const std::vector<int64_t> inserted = {2, 3, 5, 6, 7, 9, 10};
  const double cubic_key = MeanCurvatureNearSurface(cubic->stacked.field, keys);
  const double cubic_in =
      MeanCurvatureNearSurface(cubic->stacked.field, inserted);
  const double piece_key =
      MeanCurvatureNearSurface(piecewise->stacked.field, keys);
  const double piece_in =
      MeanCurvatureNearSurface(piecewise->stacked.field, inserted);
  ASSERT_GT(cubic_in, 0);
  ASSERT_GT(piece_in, 0);
  EXPECT_LT(cubic_key, 0.7 * piece_key);
  EXPECT_LT(cubic_key / cubic_in, 1.5);
  EXPECT_GT(piece_key / piece_in, 2.0);
  // And the disc still follows the key slices in between.
  const Blob mid = Inside(cubic->stacked.field, 6);
  EXPECT_NEAR(mid.cx, 22, 1.5);
}

TEST(StackMorphCubicTest, ResultDoesNotDependOnThreadCount) {
  const Volume<float> maps = Discs({14, 18, 26, 38, 40}, 32, 8);
  const StackPlan plan = UniformStackPlan(5, 4.0, 3);
  ComputeContext one, two;
  one.threads = 1;
  two.threads = 2;
  auto a = StackMorph(maps, plan, CubicOptions(), int64_t{1} << 30, one);
  auto b = StackMorph(maps, plan, CubicOptions(), int64_t{1} << 30, two);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(a->stacked.field.data, b->stacked.field.data);
  MorphOptions linear_values = CubicOptions();
  linear_values.values = MorphValues::kLinear;
  auto c = StackMorph(maps, plan, linear_values, int64_t{1} << 30, one);
  auto d = StackMorph(maps, plan, linear_values, int64_t{1} << 30, two);
  ASSERT_TRUE(c.ok() && d.ok());
  EXPECT_EQ(c->stacked.field.data, d->stacked.field.data);
  EXPECT_NE(a->stacked.field.data, c->stacked.field.data);
}

TEST(StackMorphCubicTest, UnevenPlanKeepsKeySlicesAndRejectsBadTrajectory) {
  const Volume<float> maps = Discs({14, 18, 26, 38}, 32, 8);
  // Gaps of 2, 5 and 3 output slices (a series with uneven spacing).
  StackPlan uneven = UniformStackPlan(4, 4.0, 4);
  uneven.nodes = {0, 2, 7, 10};
  uneven.output_slices = 11;
  uneven.uniform = false;
  const StackPlan* plan = &uneven;
  ComputeContext context;
  auto morphed =
      StackMorph(maps, *plan, CubicOptions(), int64_t{1} << 30, context);
  ASSERT_TRUE(morphed.ok()) << morphed.status();
  const int64_t plane = kN * kN;
  for (int64_t s = 0; s < 4; ++s)
    for (int64_t v = 0; v < plane; ++v)
      ASSERT_EQ(morphed->stacked.field.data[plan->nodes[s] * plane + v],
                maps.data[s * plane + v]);
  MorphOptions bad = CubicOptions();
  bad.trajectory = static_cast<MorphTrajectory>(7);
  EXPECT_EQ(
      StackMorph(maps, *plan, bad, int64_t{1} << 30, context).status().code(),
      absl::StatusCode::kInvalidArgument);
  CancellationToken token;
  token.Cancel();
  context.cancel = &token;
  EXPECT_EQ(StackMorph(maps, *plan, CubicOptions(), int64_t{1} << 30, context)
                .status()
                .code(),
            absl::StatusCode::kCancelled);
}

// RegisterSlicesCoarse runs ITK's demons with the displacement smoothing and
// the field update on the calling thread (issue 24: no hand-off to ITK's
// global thread pool per iteration; the smoothing's loop written for the
// case). The result must be ITK's own
// FastSymmetricForcesDemonsRegistrationFilter's, bit for bit: the same pipeline
// built here from the stock filter, with ITK's global pool of 2 threads, on an
// asymmetric, non-square case (a disc that moves and an ellipse that grows,
// scaled to the image) so that a smoothing along one axis only, a swapped axis,
// a kernel in the wrong order or a missed update would show.
void ExpectSameFieldAsItksStockDemonsFilter(int64_t nx, int64_t ny, int levels,
                                            double sigma) {
  SCOPED_TRACE(testing::Message() << nx << " x " << ny << ", " << levels
                                  << " levels, sigma " << sigma);
  std::vector<float> fixed(nx * ny), moving(nx * ny);
  const double sx = nx / 45.0, sy = ny / 37.0;
  for (int64_t j = 0; j < ny; ++j)
    for (int64_t i = 0; i < nx; ++i) {
      const double x = i / sx, y = j / sy;
      const double disc0 = 6 - std::hypot(x - 12.0, y - 14.0);
      const double disc1 = 6 - std::hypot(x - 16.5, y - 16.0);
      const double ell0 = 5 - std::hypot((x - 32.0) / 1.4, (y - 22.0) / 0.8);
      const double ell1 = 7 - std::hypot((x - 31.0) / 1.4, (y - 24.0) / 0.8);
      fixed[i + nx * j] = static_cast<float>(0.7 * sx * std::max(disc0, ell0));
      moving[i + nx * j] = static_cast<float>(0.7 * sx * std::max(disc1, ell1));
    }
  MorphOptions options;
  options.downsample = 1;
  options.levels = levels;
  options.iterations = 20;
  options.field_sigma_px = sigma;
  options.clip_mm = 4.0;
  auto ours =
      RegisterSlicesCoarse(fixed.data(), moving.data(), nx, ny, options);
  ASSERT_TRUE(ours.ok()) << ours.status();

  using Image = itk::Image<float, 2>;
  using Field = itk::Image<itk::Vector<float, 2>, 2>;
  auto make = [&](const std::vector<float>& values) {
    Image::Pointer image = Image::New();
    Image::RegionType region;
    region.SetSize({static_cast<itk::SizeValueType>(nx),
                    static_cast<itk::SizeValueType>(ny)});
    image->SetRegions(region);
    image->Allocate();
    for (int64_t v = 0; v < nx * ny; ++v)
      image->GetBufferPointer()[v] = std::clamp(values[v], -4.0f, 4.0f);
    return image;
  };
  const int previous_threads =
      itk::MultiThreaderBase::GetGlobalDefaultNumberOfThreads();
  itk::MultiThreaderBase::SetGlobalDefaultNumberOfThreads(2);
  auto demons = itk::FastSymmetricForcesDemonsRegistrationFilter<Image, Image,
                                                                 Field>::New();
  demons->SetStandardDeviations(options.field_sigma_px);
  demons->SetSmoothDisplacementField(true);
  auto multi =
      itk::MultiResolutionPDEDeformableRegistration<Image, Image, Field,
                                                    float>::New();
  multi->SetRegistrationFilter(demons);
  multi->SetNumberOfLevels(options.levels);
  itk::Array<unsigned> iterations(options.levels);
  iterations.Fill(options.iterations);
  multi->SetNumberOfIterations(iterations);
  multi->SetFixedImage(make(fixed));
  multi->SetMovingImage(make(moving));
  multi->Update();
  itk::MultiThreaderBase::SetGlobalDefaultNumberOfThreads(previous_threads);
  const auto* stock = multi->GetOutput()->GetBufferPointer();

  double largest = 0, differing = 0;
  for (int64_t v = 0; v < nx * ny; ++v) {
    largest = std::max(largest, std::hypot(static_cast<double>(stock[v][0]),
                                           static_cast<double>(stock[v][1])));
    if (ours->ux[v] != stock[v][0] || ours->uy[v] != stock[v][1]) ++differing;
  }
  EXPECT_GT(largest, 0.5);  // the registration did move something
  EXPECT_EQ(differing, 0) << "pixels where the field differs from ITK's";
}

TEST(RegisterSlicesTest, SameFieldAsItksStockDemonsFilter) {
  ExpectSameFieldAsItksStockDemonsFilter(45, 37, 3, 1.5);
}

// The label boxes of the fill: a kernel wider than the image (the edge
// extension reaches past the opposite border) and a large image in the
// morph's default 4 levels and sigma.
TEST(RegisterSlicesTest, SameFieldAsItksStockDemonsFilterTinyAndLarge) {
  ExpectSameFieldAsItksStockDemonsFilter(9, 5, 1, 3.0);
  ExpectSameFieldAsItksStockDemonsFilter(131, 97, 4,
                                         MorphOptions().field_sigma_px);
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

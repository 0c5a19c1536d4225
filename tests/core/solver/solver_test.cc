#include "core/solver/solver.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <random>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace interslice {
namespace {

Volume<float> MakeField(const Index3& size, const Vec3& spacing) {
  Volume<float> v;
  v.grid.size = size;
  v.grid.spacing = spacing;
  v.data.assign(v.grid.VoxelCount(), 0.0f);
  return v;
}

Volume<float> RandomField(const Index3& size, const Vec3& spacing,
                          unsigned seed) {
  Volume<float> v = MakeField(size, spacing);
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> dist(-1.0f, 1.0f);
  for (float& x : v.data) x = dist(rng);
  return v;
}

// Signed distance to a sphere (positive inside), in voxel index units.
Volume<float> SphereField(const Index3& size, const Vec3& spacing,
                          double radius_mm) {
  Volume<float> v = MakeField(size, spacing);
  const Vec3 centre = {(size[0] - 1) * spacing[0] / 2,
                       (size[1] - 1) * spacing[1] / 2,
                       (size[2] - 1) * spacing[2] / 2};
  for (int64_t k = 0; k < size[2]; ++k)
    for (int64_t j = 0; j < size[1]; ++j)
      for (int64_t i = 0; i < size[0]; ++i) {
        const double dx = i * spacing[0] - centre[0];
        const double dy = j * spacing[1] - centre[1];
        const double dz = k * spacing[2] - centre[2];
        v.at(i, j, k) = static_cast<float>(
            radius_mm - std::sqrt(dx * dx + dy * dy + dz * dz));
      }
  return v;
}

std::vector<uint8_t> EveryNth(int64_t nz, int n) {
  std::vector<uint8_t> fixed(nz, 0);
  for (int64_t k = 0; k < nz; k += n) fixed[k] = 1;
  fixed[nz - 1] = 1;
  return fixed;
}

// Replaces free slices by linear interpolation of the nearest fixed slices
// (what the stacking stage produces), so CG starts where the pipeline does.
void LinearFill(Volume<float>& v, const std::vector<uint8_t>& fixed) {
  const int64_t plane = v.grid.SliceVoxelCount();
  const int64_t nz = v.grid.size[2];
  for (int64_t k = 0; k < nz; ++k) {
    if (fixed[k]) continue;
    int64_t a = k, b = k;
    while (a >= 0 && !fixed[a]) --a;
    while (b < nz && !fixed[b]) ++b;
    for (int64_t n = 0; n < plane; ++n) {
      float value;
      if (a < 0) {
        value = v.data[b * plane + n];
      } else if (b >= nz) {
        value = v.data[a * plane + n];
      } else {
        const float t = static_cast<float>(k - a) / (b - a);
        value = (1 - t) * v.data[a * plane + n] + t * v.data[b * plane + n];
      }
      v.data[k * plane + n] = value;
    }
  }
}

double Dot(const std::vector<float>& a, const std::vector<float>& b) {
  double s = 0;
  for (size_t n = 0; n < a.size(); ++n) s += static_cast<double>(a[n]) * b[n];
  return s;
}

// The 5x5x5 kernel of the paper's Appendix, layers l1..l5 along z, each
// layer indexed [y][x].
double AppendixKernel(int dx, int dy, int dz) {
  static const double l1[5][5] = {{0, 0, 0.125, 0, 0},
                                  {0, 0, 0, 0, 0},
                                  {0.125, 0, 0.5, 0, 0.125},
                                  {0, 0, 0, 0, 0},
                                  {0, 0, 0.125, 0, 0}};
  static const double l2[5][5] = {{0, 0, 0, 0, 0},
                                  {0, 0, 0, 0, 0},
                                  {0, 0, -4, 0, 0},
                                  {0, 0, 0, 0, 0},
                                  {0, 0, 0, 0, 0}};
  static const double l3[5][5] = {{0.125, 0, 0.5, 0, 0.125},
                                  {0, 0, -4, 0, 0},
                                  {0.5, -4, 19.5, -4, 0.5},
                                  {0, 0, -4, 0, 0},
                                  {0.125, 0, 0.5, 0, 0.125}};
  const double(*layer)[5] = nullptr;
  switch (std::abs(dz)) {
    case 2:
      layer = l1;
      break;
    case 1:
      layer = l2;
      break;
    case 0:
      layer = l3;
      break;
    default:
      return 0;
  }
  if (std::abs(dx) > 2 || std::abs(dy) > 2) return 0;
  return layer[dy + 2][dx + 2];
}

TEST(CurvatureOperatorTest, InteriorStencilIsThePapersAppendixKernel) {
  const Index3 size = {11, 11, 11};
  Volume<float> delta = MakeField(size, {1, 1, 1});
  delta.at(5, 5, 5) = 1.0f;
  std::vector<float> out(delta.data.size());
  ApplyCurvatureOperator(delta.data.data(), out.data(), size,
                         CurvatureWeights{});
  double kernel_sum = 0;
  for (int64_t k = 0; k < 11; ++k)
    for (int64_t j = 0; j < 11; ++j)
      for (int64_t i = 0; i < 11; ++i) {
        const double expected = AppendixKernel(i - 5, j - 5, k - 5);
        kernel_sum += expected;
        EXPECT_DOUBLE_EQ(out[delta.grid.LinearIndex(i, j, k)], expected)
            << "at offset (" << i - 5 << ", " << j - 5 << ", " << k - 5 << ")";
      }
  // grad E annihilates constants: the kernel sums to zero.
  EXPECT_DOUBLE_EQ(kernel_sum, 0.0);
}

TEST(CurvatureOperatorTest, IsHalfTheGradientOfTheEnergy) {
  // E(f) = f . A f, with E evaluated independently from its definition.
  for (const EnergyUnits units :
       {EnergyUnits::kVoxel, EnergyUnits::kMillimetre}) {
    const Vec3 spacing = {0.7, 0.5, 2.5};
    const Volume<float> f = RandomField({7, 6, 9}, spacing, 3);
    const CurvatureWeights w = CurvatureWeights::For(units, spacing);
    std::vector<float> af(f.data.size());
    ApplyCurvatureOperator(f.data.data(), af.data(), f.grid.size, w);
    const double energy = CurvatureEnergy(f.data.data(), f.grid.size, w);
    EXPECT_NEAR(Dot(f.data, af), energy, 1e-5 * energy);
  }
}

TEST(CurvatureOperatorTest, IsSymmetricIncludingBoundariesAndTinyAxes) {
  for (const Index3 size :
       {Index3{9, 8, 7}, Index3{3, 7, 6}, Index3{6, 1, 4}, Index3{2, 2, 2}}) {
    const Vec3 spacing = {0.9, 0.45, 3.0};
    const CurvatureWeights w =
        CurvatureWeights::For(EnergyUnits::kMillimetre, spacing);
    const Volume<float> u = RandomField(size, spacing, 1);
    const Volume<float> v = RandomField(size, spacing, 2);
    std::vector<float> au(u.data.size()), av(v.data.size());
    ApplyCurvatureOperator(u.data.data(), au.data(), size, w);
    ApplyCurvatureOperator(v.data.data(), av.data(), size, w);
    const double uav = Dot(u.data, av), vau = Dot(v.data, au);
    EXPECT_NEAR(uav, vau, 1e-5 * (std::abs(uav) + 1))
        << size[0] << "x" << size[1] << "x" << size[2];
  }
}

TEST(CurvatureOperatorTest, AnnihilatesConstantsAndPlanes) {
  // Linear functions have zero second derivatives, but the mirror boundary
  // bends a plane, so only constants are in the null space everywhere.
  Volume<float> f = MakeField({8, 8, 8}, {1, 1, 1});
  std::fill(f.data.begin(), f.data.end(), 3.5f);
  std::vector<float> out(f.data.size());
  ApplyCurvatureOperator(f.data.data(), out.data(), f.grid.size, {});
  for (float v : out) ASSERT_NEAR(v, 0.0f, 1e-5f);
}

struct AgreementCase {
  const char* name;
  Index3 size;
  Vec3 spacing;
  EnergyUnits units;
  bool irregular;
  bool sphere;
};

class DirectVersusCgTest : public ::testing::TestWithParam<AgreementCase> {};

TEST_P(DirectVersusCgTest, AgreeAndKeepOriginalSlicesBitIdentical) {
  const AgreementCase& c = GetParam();
  Volume<float> input =
      c.sphere ? SphereField(c.size, c.spacing, 0.35 * c.size[0] * c.spacing[0])
               : RandomField(c.size, c.spacing, 7);
  std::vector<uint8_t> fixed = EveryNth(c.size[2], 4);
  if (c.irregular) {
    // Sparse annotations: irregular gaps, first slice free.
    fixed.assign(c.size[2], 0);
    for (int64_t k : {2, 3, 9, 16}) {
      if (k < c.size[2]) fixed[k] = 1;
    }
  }
  LinearFill(input, fixed);

  Volume<float> direct = input;
  SolverOptions direct_options;
  direct_options.method = SolverMethod::kDirect;
  direct_options.units = c.units;
  const auto direct_result = Solve(direct, fixed, direct_options, {});
  ASSERT_TRUE(direct_result.ok()) << direct_result.status();
  EXPECT_LT(direct_result->relative_residual, 1e-4);
  EXPECT_LE(direct_result->energy, direct_result->initial_energy);

  Volume<float> cg = input;
  SolverOptions cg_options;
  cg_options.method = SolverMethod::kConjugateGradient;
  cg_options.units = c.units;
  cg_options.max_iterations = 3000;
  cg_options.tolerance = 1e-9;
  const auto cg_result = Solve(cg, fixed, cg_options, {});
  ASSERT_TRUE(cg_result.ok()) << cg_result.status();
  // Float vectors bottom out near 1e-5..1e-7 relative residual; what must
  // hold is agreement of the fields.
  EXPECT_LT(cg_result->relative_residual, 2e-4);
  std::printf("%s: CG %d iterations, relative residual %.3g\n", c.name,
              cg_result->iterations, cg_result->relative_residual);

  const auto [lo, hi] =
      std::minmax_element(input.data.begin(), input.data.end());
  const double range = *hi - *lo;
  double max_diff = 0;
  for (size_t n = 0; n < cg.data.size(); ++n) {
    max_diff = std::max(
        max_diff, std::abs(static_cast<double>(cg.data[n]) - direct.data[n]));
  }
  std::printf("%s: max |cg - direct| = %.3g of range %.3g\n", c.name, max_diff,
              range);
  EXPECT_LT(max_diff, 1e-4 * range)
      << "CG iterations " << cg_result->iterations;

  const int64_t plane = input.grid.SliceVoxelCount();
  for (int64_t k = 0; k < c.size[2]; ++k) {
    if (!fixed[k]) continue;
    EXPECT_EQ(std::memcmp(&direct.data[k * plane], &input.data[k * plane],
                          plane * sizeof(float)),
              0)
        << "direct, slice " << k;
    EXPECT_EQ(std::memcmp(&cg.data[k * plane], &input.data[k * plane],
                          plane * sizeof(float)),
              0)
        << "cg, slice " << k;
  }
  // The exact minimiser has the lowest energy (to the precision with which
  // f . A f of a float field can be evaluated).
  EXPECT_LE(direct_result->energy, cg_result->energy * (1 + 1e-4));
}

INSTANTIATE_TEST_SUITE_P(
    Cases, DirectVersusCgTest,
    ::testing::Values(AgreementCase{"RandomIsotropic",
                                    {12, 10, 17},
                                    {1, 1, 1},
                                    EnergyUnits::kVoxel,
                                    false,
                                    false},
                      AgreementCase{"SphereIsotropic",
                                    {20, 20, 25},
                                    {1, 1, 1},
                                    EnergyUnits::kVoxel,
                                    false,
                                    true},
                      AgreementCase{"RandomAnisotropicMm",
                                    {10, 12, 17},
                                    {0.7, 0.5, 2.5},
                                    EnergyUnits::kMillimetre,
                                    false,
                                    false},
                      AgreementCase{"SphereAnisotropicVoxel",
                                    {18, 16, 21},
                                    {0.45, 0.45, 1.25},
                                    EnergyUnits::kVoxel,
                                    false,
                                    true},
                      AgreementCase{"RandomIrregular",
                                    {9, 11, 19},
                                    {1, 1, 1},
                                    EnergyUnits::kVoxel,
                                    true,
                                    false},
                      AgreementCase{"SphereIrregularMm",
                                    {16, 17, 19},
                                    {0.8, 0.8, 1.6},
                                    EnergyUnits::kMillimetre,
                                    true,
                                    true}),
    [](const auto& info) { return std::string(info.param.name); });

TEST(ConjugateGradientTest, EnergyNeverIncreases) {
  Volume<float> field = SphereField({24, 24, 33}, {1, 1, 1}, 9.0);
  const std::vector<uint8_t> fixed = EveryNth(33, 8);
  LinearFill(field, fixed);
  std::vector<double> energies = {
      CurvatureEnergy(field.data.data(), field.grid.size, {})};
  ComputeContext context;
  context.progress = [&](const ProgressEvent& e) {
    // The field is updated in place: measure the iterate independently.
    energies.push_back(CurvatureEnergy(field.data.data(), field.grid.size, {}));
    EXPECT_EQ(e.iteration, static_cast<int>(energies.size()) - 1);
  };
  SolverOptions options;
  options.max_iterations = 40;
  const auto result = Solve(field, fixed, options, context);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->iterations, 40);
  ASSERT_EQ(energies.size(), 41u);
  for (size_t n = 1; n < energies.size(); ++n) {
    EXPECT_LE(energies[n], energies[n - 1] * (1 + 1e-7)) << "iteration " << n;
  }
  EXPECT_LT(energies.back(), 0.9 * energies.front());
  EXPECT_NEAR(result->energy, energies.back(), 1e-4 * energies.back());
}

TEST(ConjugateGradientTest, DefaultIsFifteenIterationsAsInThePaper) {
  Volume<float> field = SphereField({16, 16, 17}, {1, 1, 1}, 6.0);
  const std::vector<uint8_t> fixed = EveryNth(17, 8);
  LinearFill(field, fixed);
  const auto result = Solve(field, fixed, SolverOptions{}, {});
  ASSERT_TRUE(result.ok());
  EXPECT_EQ(result->iterations, 15);
  EXPECT_EQ(result->method, SolverMethod::kConjugateGradient);
  EXPECT_LT(result->energy, result->initial_energy);
  EXPECT_LT(result->relative_residual, 1.0);
}

TEST(SolverTest, ResultsDoNotDependOnThreadCount) {
  for (const SolverMethod method :
       {SolverMethod::kConjugateGradient, SolverMethod::kDirect}) {
    Volume<float> input = SphereField({20, 18, 25}, {1, 1, 2}, 7.0);
    const std::vector<uint8_t> fixed = EveryNth(25, 4);
    LinearFill(input, fixed);
    Volume<float> one = input, two = input;
    SolverOptions options;
    options.method = method;
    ComputeContext single, dual;
    single.threads = 1;
    dual.threads = 2;
    const auto r1 = Solve(one, fixed, options, single);
    const auto r2 = Solve(two, fixed, options, dual);
    ASSERT_TRUE(r1.ok() && r2.ok());
    EXPECT_EQ(std::memcmp(one.data.data(), two.data.data(),
                          one.data.size() * sizeof(float)),
              0)
        << SolverMethodName(method);
    EXPECT_EQ(r1->energy, r2->energy);
  }
}

TEST(SolverTest, LinearMethodLeavesFieldAndReportsEnergy) {
  Volume<float> field = SphereField({10, 10, 9}, {1, 1, 1}, 4.0);
  const std::vector<uint8_t> fixed = EveryNth(9, 4);
  LinearFill(field, fixed);
  const Volume<float> before = field;
  SolverOptions options;
  options.method = SolverMethod::kLinear;
  const auto result = Solve(field, fixed, options, {});
  ASSERT_TRUE(result.ok());
  EXPECT_EQ(field.data, before.data);
  EXPECT_NEAR(result->energy,
              CurvatureEnergy(field.data.data(), field.grid.size, {}),
              1e-5 * result->energy);
  EXPECT_EQ(result->relative_residual, 1.0);
}

TEST(SolverTest, CancellationStopsTheSolver) {
  for (const SolverMethod method :
       {SolverMethod::kConjugateGradient, SolverMethod::kDirect}) {
    Volume<float> field = RandomField({8, 8, 9}, {1, 1, 1}, 5);
    CancellationToken token;
    token.Cancel();
    ComputeContext context;
    context.cancel = &token;
    SolverOptions options;
    options.method = method;
    const auto result = Solve(field, EveryNth(9, 4), options, context);
    EXPECT_EQ(result.status().code(), absl::StatusCode::kCancelled);
  }
}

TEST(SolverTest, CancellationMidSolveIsSeenWithinOneIteration) {
  Volume<float> field = SphereField({16, 16, 33}, {1, 1, 1}, 6.0);
  const std::vector<uint8_t> fixed = EveryNth(33, 8);
  LinearFill(field, fixed);
  CancellationToken token;
  ComputeContext context;
  context.cancel = &token;
  int last_iteration = 0;
  context.progress = [&](const ProgressEvent& e) {
    last_iteration = e.iteration;
    if (e.iteration == 3) token.Cancel();
  };
  SolverOptions options;
  options.max_iterations = 100;
  const auto result = Solve(field, fixed, options, context);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kCancelled);
  EXPECT_EQ(last_iteration, 3);
}

TEST(SolverTest, RejectsBadInput) {
  Volume<float> field = RandomField({4, 4, 5}, {1, 1, 1}, 1);
  EXPECT_EQ(Solve(field, std::vector<uint8_t>(5, 0), {}, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(Solve(field, std::vector<uint8_t>(4, 1), {}, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
  SolverOptions negative;
  negative.max_iterations = -1;
  EXPECT_EQ(Solve(field, EveryNth(5, 2), negative, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
  field.data[3] = NAN;
  EXPECT_EQ(Solve(field, EveryNth(5, 2), {}, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(SolverTest, AllSlicesFixedIsAlreadyOptimal) {
  for (const SolverMethod method :
       {SolverMethod::kConjugateGradient, SolverMethod::kDirect}) {
    Volume<float> field = RandomField({5, 5, 4}, {1, 1, 1}, 9);
    const Volume<float> before = field;
    SolverOptions options;
    options.method = method;
    const auto result = Solve(field, std::vector<uint8_t>(4, 1), options, {});
    ASSERT_TRUE(result.ok()) << result.status();
    EXPECT_EQ(field.data, before.data);
    EXPECT_EQ(result->relative_residual, 0.0);
  }
}

// With a fidelity term the minimiser of E + sum_k w_k |f_k - g_k|^2 satisfies
// (A f)_v + w_k (f_v - g_v) = 0 on every free voxel v of slice k. Checked
// directly with the operator, for a uniform and a tapered weight.
TEST(SolverTest, FidelityTermGivesTheExactMinimiserOfTheAugmentedEnergy) {
  const Index3 size = {12, 10, 13};
  const std::vector<uint8_t> fixed = EveryNth(size[2], 4);  // 0, 4, 8, 12
  for (const bool taper : {false, true}) {
    SCOPED_TRACE(taper);
    Volume<float> field = RandomField(size, {1, 1, 1}, 21);
    const Volume<float> g = field;
    SolverOptions options;
    options.method = SolverMethod::kDirect;
    options.fidelity = 0.7;
    options.fidelity_taper = taper;
    const auto result = Solve(field, fixed, options, {});
    ASSERT_TRUE(result.ok()) << result.status();
    std::vector<float> af(field.data.size());
    ApplyCurvatureOperator(field.data.data(), af.data(), size, {});
    const int64_t plane = size[0] * size[1];
    double worst = 0, scale = 0;
    for (int64_t k = 0; k < size[2]; ++k) {
      // Slices 1, 2, 3 of each gap of 4: t = 1/4, 1/2, 3/4.
      const int64_t m = k % 4;
      const double t = 2.0 * std::min<int64_t>(m, 4 - m) / 4.0;
      const double w = taper ? 0.7 * t * t : 0.7;
      for (int64_t v = 0; v < plane; ++v) {
        const int64_t n = k * plane + v;
        if (fixed[k]) {
          ASSERT_EQ(field.data[n], g.data[n]);  // bit-identical
          continue;
        }
        worst =
            std::max(worst, std::abs(af[n] + w * (field.data[n] - g.data[n])));
        scale = std::max(scale, std::abs(static_cast<double>(af[n])));
      }
    }
    EXPECT_GT(scale, 1e-2);  // the curvature term is active...
    EXPECT_LT(worst, 1e-4);  // ...and balanced by the fidelity term
  }
}

TEST(SolverTest, LargeFidelityKeepsTheFieldAndZeroIsThePapersEnergy) {
  const Index3 size = {8, 9, 9};
  const std::vector<uint8_t> fixed = EveryNth(size[2], 4);
  Volume<float> start = RandomField(size, {1, 1, 1}, 5);
  Volume<float> stiff = start, plain = start, exact = start;
  SolverOptions options;
  options.method = SolverMethod::kDirect;
  options.fidelity = 1e6;
  ASSERT_TRUE(Solve(stiff, fixed, options, {}).ok());
  double worst = 0;
  for (size_t n = 0; n < start.data.size(); ++n)
    worst = std::max(worst, std::abs(double{stiff.data[n]} - start.data[n]));
  EXPECT_LT(worst, 1e-3);
  options.fidelity = 0;
  ASSERT_TRUE(Solve(plain, fixed, options, {}).ok());
  options.method = SolverMethod::kMorph;  // the same solve, named morph
  ASSERT_TRUE(Solve(exact, fixed, options, {}).ok());
  EXPECT_EQ(plain.data, exact.data);
}

TEST(SolverTest, FidelityNeedsTheDirectSolverAndANonNegativeWeight) {
  Volume<float> field = RandomField({4, 4, 5}, {1, 1, 1}, 1);
  SolverOptions options;
  options.method = SolverMethod::kConjugateGradient;
  options.fidelity = 1;
  EXPECT_EQ(Solve(field, EveryNth(5, 2), options, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
  options.method = SolverMethod::kDirect;
  options.fidelity = -1;
  EXPECT_EQ(Solve(field, EveryNth(5, 2), options, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(SolverMethodName(SolverMethod::kMorph), "morph");
}

}  // namespace
}  // namespace interslice

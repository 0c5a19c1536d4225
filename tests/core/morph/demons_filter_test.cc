// core/morph/demons_filter.h: the demons filter whose field smoothing is a
// direct loop must give ITK's own FastSymmetricForcesDemonsRegistrationFilter
// bit for bit, in the multi-resolution registration RegisterSlices runs and
// on images smaller than the smoothing kernel.
#include "core/morph/demons_filter.h"

#include <cmath>
#include <cstdint>
#include <cstring>
#include <random>
#include <vector>

#include "gtest/gtest.h"
#include "itkFastSymmetricForcesDemonsRegistrationFilter.h"
#include "itkMultiResolutionPDEDeformableRegistration.h"

namespace interslice::morph_internal {
namespace {

DemonsImage::Pointer Image(const std::vector<float>& data, int64_t nx,
                           int64_t ny) {
  auto image = DemonsImage::New();
  DemonsImage::RegionType region;
  region.SetSize({static_cast<itk::SizeValueType>(nx),
                  static_cast<itk::SizeValueType>(ny)});
  image->SetRegions(region);
  image->Allocate();
  std::copy(data.begin(), data.end(), image->GetBufferPointer());
  return image;
}

// A clipped distance map of an ellipse (centre cx, cy; semi-axes a, b) with
// a little noise, as the morph registers them.
std::vector<float> Ellipse(int64_t nx, int64_t ny, double cx, double cy,
                           double a, double b, uint32_t seed) {
  std::mt19937 random(seed);
  std::uniform_real_distribution<float> noise(-0.05f, 0.05f);
  std::vector<float> out(nx * ny);
  for (int64_t j = 0; j < ny; ++j) {
    for (int64_t i = 0; i < nx; ++i) {
      const double d =
          std::hypot((i - cx) / a, (j - cy) / b) * std::min(a, b) -
          std::min(a, b);
      out[i + nx * j] =
          std::clamp(static_cast<float>(-d), -4.0f, 4.0f) + noise(random);
    }
  }
  return out;
}

// The displacement field of a multi-resolution registration with the given
// demons filter, as RegisterSlices sets it up.
template <typename Demons>
std::vector<float> Register(const std::vector<float>& fixed,
                            const std::vector<float>& moving, int64_t nx,
                            int64_t ny, int levels, int iterations,
                            double sigma) {
  using MultiResolution =
      itk::MultiResolutionPDEDeformableRegistration<DemonsImage, DemonsImage,
                                                    DemonsField, float>;
  auto demons = Demons::New();
  demons->SetStandardDeviations(sigma);
  demons->SetSmoothDisplacementField(true);
  demons->SetNumberOfWorkUnits(1);
  auto multi = MultiResolution::New();
  multi->SetRegistrationFilter(demons);
  multi->SetNumberOfLevels(static_cast<unsigned>(levels));
  typename MultiResolution::NumberOfIterationsType its(levels);
  its.Fill(static_cast<unsigned>(iterations));
  multi->SetNumberOfIterations(its);
  multi->SetNumberOfWorkUnits(1);
  multi->SetFixedImage(Image(fixed, nx, ny));
  multi->SetMovingImage(Image(moving, nx, ny));
  multi->Update();
  const DemonsDisplacement* field = multi->GetOutput()->GetBufferPointer();
  std::vector<float> out(2 * nx * ny);
  for (int64_t v = 0; v < nx * ny; ++v) {
    out[2 * v] = field[v][0];
    out[2 * v + 1] = field[v][1];
  }
  return out;
}

using StockDemons =
    itk::FastSymmetricForcesDemonsRegistrationFilter<DemonsImage, DemonsImage,
                                                     DemonsField>;

TEST(DemonsFilterTest, SameFieldAsItksFilterBitForBit) {
  struct Case {
    int64_t nx, ny;
    int levels, iterations;
    double sigma;
  };
  for (const Case& c : {Case{64, 48, 4, 25, 2.0}, Case{33, 17, 2, 25, 2.0},
                        Case{96, 96, 3, 10, 1.5}, Case{5, 7, 1, 25, 2.0},
                        Case{3, 40, 1, 12, 3.0}}) {
    SCOPED_TRACE(testing::Message() << c.nx << " x " << c.ny << ", "
                                    << c.levels << " levels, sigma "
                                    << c.sigma);
    const std::vector<float> fixed =
        Ellipse(c.nx, c.ny, c.nx * 0.45, c.ny * 0.5, c.nx * 0.25 + 1,
                c.ny * 0.2 + 1, 1);
    const std::vector<float> moving =
        Ellipse(c.nx, c.ny, c.nx * 0.55, c.ny * 0.45, c.nx * 0.2 + 1,
                c.ny * 0.25 + 1, 2);
    const std::vector<float> stock = Register<StockDemons>(
        fixed, moving, c.nx, c.ny, c.levels, c.iterations, c.sigma);
    const std::vector<float> fast = Register<DemonsFilter>(
        fixed, moving, c.nx, c.ny, c.levels, c.iterations, c.sigma);
    ASSERT_EQ(stock.size(), fast.size());
    EXPECT_EQ(std::memcmp(stock.data(), fast.data(),
                          stock.size() * sizeof(float)),
              0);
    // A registration that did something: the field is not zero.
    double largest = 0;
    for (float v : fast) largest = std::max(largest, std::fabs(double{v}));
    EXPECT_GT(largest, 0.05);
  }
}

}  // namespace
}  // namespace interslice::morph_internal

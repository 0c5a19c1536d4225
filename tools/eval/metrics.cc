#include "tools/eval/metrics.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "itkConnectedComponentImageFilter.h"
#include "itkImage.h"
#include "itkImportImageFilter.h"
#include "itkLabelOverlapMeasuresImageFilter.h"
#include "itkMultiThreaderBase.h"
#include "itkSignedMaurerDistanceMapImageFilter.h"

namespace interslice::eval {
namespace {

using ItkMask = itk::Image<uint8_t, 3>;
using ItkFloat = itk::Image<float, 3>;

// A copy of `mask` as an ITK image (index space only for the spacing; the
// metrics never need the orientation).
ItkMask::Pointer ToItk(const Mask& mask) {
  auto image = ItkMask::New();
  ItkMask::RegionType region;
  ItkMask::SizeType size;
  for (int c = 0; c < 3; ++c) size[c] = mask.grid.size[c];
  region.SetSize(size);
  image->SetRegions(region);
  ItkMask::SpacingType spacing;
  for (int c = 0; c < 3; ++c) spacing[c] = mask.grid.spacing[c];
  image->SetSpacing(spacing);
  image->Allocate();
  std::copy(mask.data.begin(), mask.data.end(), image->GetBufferPointer());
  return image;
}

bool IsBoundary(const Mask& m, int64_t i, int64_t j, int64_t k) {
  if (!m.at(i, j, k)) return false;
  const Index3 n = m.grid.size;
  if (i == 0 || j == 0 || k == 0 || i + 1 == n[0] || j + 1 == n[1] ||
      k + 1 == n[2])
    return true;
  return !m.at(i - 1, j, k) || !m.at(i + 1, j, k) || !m.at(i, j - 1, k) ||
         !m.at(i, j + 1, k) || !m.at(i, j, k - 1) || !m.at(i, j, k + 1);
}

bool Empty(const Mask& m) {
  return std::find(m.data.begin(), m.data.end(), 1) == m.data.end();
}

void Sample(const Mask& from, const Volume<float>& to_map,
            const std::vector<uint8_t>& slices, std::vector<float>& out) {
  const Index3 n = from.grid.size;
  for (int64_t k = 0; k < n[2]; ++k) {
    if (!slices[k]) continue;
    for (int64_t j = 0; j < n[1]; ++j)
      for (int64_t i = 0; i < n[0]; ++i)
        if (IsBoundary(from, i, j, k)) out.push_back(to_map.at(i, j, k));
  }
}

}  // namespace

void SetItkThreads(int threads) {
  if (threads > 0) {
    itk::MultiThreaderBase::SetGlobalDefaultNumberOfThreads(threads);
    itk::MultiThreaderBase::SetGlobalMaximumNumberOfThreads(threads);
  }
}

Mask Threshold(const Volume<float>& volume, float level) {
  Mask mask;
  mask.grid = volume.grid;
  mask.data.resize(volume.data.size());
  for (size_t v = 0; v < volume.data.size(); ++v)
    mask.data[v] = volume.data[v] >= level ? 1 : 0;
  return mask;
}

double DiceOnSlices(const Mask& a, const Mask& b,
                    const std::vector<uint8_t>& slices) {
  // Stack the evaluated slices into one sub-volume for the ITK filter.
  Mask sa, sb;
  sa.grid = a.grid;
  const int64_t plane = a.grid.SliceVoxelCount();
  int64_t count = 0;
  for (int64_t k = 0; k < a.grid.size[2]; ++k) {
    if (!slices[k]) continue;
    sa.data.insert(sa.data.end(), a.data.begin() + k * plane,
                   a.data.begin() + (k + 1) * plane);
    sb.data.insert(sb.data.end(), b.data.begin() + k * plane,
                   b.data.begin() + (k + 1) * plane);
    ++count;
  }
  if (count == 0) return std::nan("");
  sa.grid.size[2] = count;
  sb.grid = sa.grid;
  if (Empty(sa) && Empty(sb)) return 1.0;
  if (Empty(sa) || Empty(sb)) return 0.0;
  using Filter = itk::LabelOverlapMeasuresImageFilter<ItkMask>;
  auto filter = Filter::New();
  filter->SetSourceImage(ToItk(sa));
  filter->SetTargetImage(ToItk(sb));
  filter->Update();
  return filter->GetDiceCoefficient(1);
}

Volume<float> BoundaryDistanceMap(const Mask& mask) {
  Volume<float> out;
  out.grid = mask.grid;
  if (Empty(mask)) {
    out.data.assign(mask.data.size(), std::numeric_limits<float>::infinity());
    return out;
  }
  using Filter = itk::SignedMaurerDistanceMapImageFilter<ItkMask, ItkFloat>;
  auto filter = Filter::New();
  filter->SetInput(ToItk(mask));
  filter->SetUseImageSpacing(true);
  filter->SetSquaredDistance(false);
  filter->SetInsideIsPositive(false);
  filter->SetBackgroundValue(0);
  filter->Update();
  const float* p = filter->GetOutput()->GetBufferPointer();
  out.data.resize(mask.data.size());
  for (size_t v = 0; v < out.data.size(); ++v) out.data[v] = std::abs(p[v]);
  return out;
}

SurfaceDistances SurfaceDistancesOnSlices(
    const Mask& reconstruction, const Volume<float>& reconstruction_map,
    const Mask& truth, const Volume<float>& truth_map,
    const std::vector<uint8_t>& slices) {
  SurfaceDistances result;
  if (Empty(reconstruction) || Empty(truth)) return result;
  std::vector<float> d;
  Sample(reconstruction, truth_map, slices, d);
  Sample(truth, reconstruction_map, slices, d);
  result.samples = static_cast<int64_t>(d.size());
  if (d.empty()) return result;
  double sum = 0;
  for (float x : d) sum += x;
  result.msd = sum / d.size();
  const size_t q = static_cast<size_t>(std::ceil(0.95 * d.size())) - 1;
  std::nth_element(d.begin(), d.begin() + q, d.end());
  result.hd95 = d[q];
  result.hdmax = *std::max_element(d.begin(), d.end());
  return result;
}

SurfaceDistances SurfaceDistancesOnSlices(const Mask& reconstruction,
                                          const Mask& truth,
                                          const std::vector<uint8_t>& slices) {
  return SurfaceDistancesOnSlices(reconstruction,
                                  BoundaryDistanceMap(reconstruction), truth,
                                  BoundaryDistanceMap(truth), slices);
}

double CreaseIndex(const Volume<float>& f, const std::vector<uint8_t>& fixed,
                   double near_mm) {
  double on_original = 0, on_inserted = 0;
  int64_t n_original = 0, n_inserted = 0;
  const Index3 n = f.grid.size;
  for (int64_t k = 1; k + 1 < n[2]; ++k) {
    for (int64_t j = 0; j < n[1]; ++j) {
      for (int64_t i = 0; i < n[0]; ++i) {
        if (std::abs(f.at(i, j, k)) > near_mm) continue;
        const double fzz = static_cast<double>(f.at(i, j, k + 1)) -
                           2.0 * f.at(i, j, k) + f.at(i, j, k - 1);
        if (fixed[k]) {
          on_original += std::abs(fzz);
          ++n_original;
        } else {
          on_inserted += std::abs(fzz);
          ++n_inserted;
        }
      }
    }
  }
  if (n_original == 0 || n_inserted == 0) return std::nan("");
  const double mean_original = on_original / n_original;
  const double mean_inserted = on_inserted / n_inserted;
  if (mean_inserted < 1e-9) return std::numeric_limits<double>::infinity();
  return mean_original / mean_inserted;
}

Components CountComponents(const Mask& mask) {
  Components result;
  if (Empty(mask)) return result;
  using Labels = itk::Image<uint32_t, 3>;
  using Filter = itk::ConnectedComponentImageFilter<ItkMask, Labels>;
  auto filter = Filter::New();
  filter->SetInput(ToItk(mask));
  filter->SetFullyConnected(false);
  filter->Update();
  result.count = filter->GetObjectCount();
  std::vector<int64_t> sizes(result.count + 1, 0);
  const Labels* out = filter->GetOutput();
  const uint32_t* p = out->GetBufferPointer();
  for (size_t v = 0; v < mask.data.size(); ++v) ++sizes[p[v]];
  for (int64_t l = 1; l <= result.count; ++l) {
    if (sizes[l] >= 100) ++result.count_ge100;
    result.largest = std::max(result.largest, sizes[l]);
  }
  return result;
}

Components CountComponentsInSlab(const Mask& mask, int64_t k0, int64_t k1) {
  k0 = std::clamp<int64_t>(k0, 0, mask.grid.size[2]);
  k1 = std::clamp<int64_t>(k1, k0, mask.grid.size[2]);
  if (k1 <= k0) return {};
  VoxelBox box{{0, 0, k0}, {mask.grid.size[0], mask.grid.size[1], k1}};
  return CountComponents(CropVolume(mask, box));
}

}  // namespace interslice::eval

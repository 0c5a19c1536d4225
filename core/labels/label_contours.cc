#include "core/labels/label_contours.h"

#include <algorithm>
#include <array>
#include <map>

#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "itkContourExtractor2DImageFilter.h"
#include "itkImage.h"

namespace interslice {
namespace {

using MaskImage = itk::Image<float, 2>;
using ContourFilter = itk::ContourExtractor2DImageFilter<MaskImage>;

struct Box {
  int64_t i0, i1, j0, j1;  // inclusive
};

}  // namespace

absl::StatusOr<LabelContours> ExtractLabelContours(
    const LabelVolume& labels, const std::vector<int>& only,
    const ComputeContext& context) {
  const Grid& g = labels.grid;
  INTERSLICE_RETURN_IF_ERROR(g.Validate());
  if (static_cast<int64_t>(labels.data.size()) != g.VoxelCount()) {
    return absl::InvalidArgumentError(
        "contours: label map data size does not match its grid");
  }
  const int64_t nx = g.size[0], ny = g.size[1], plane = nx * ny;
  std::vector<bool> wanted(65536, only.empty());
  for (int l : only) {
    if (l >= 1 && l <= 65535) wanted[l] = true;
  }
  wanted[0] = false;
  LabelContours out;
  for (int64_t k = 0; k < g.size[2]; ++k) {
    INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
    const uint16_t* slice = labels.data.data() + k * plane;
    std::map<int, Box> boxes;
    for (int64_t j = 0; j < ny; ++j) {
      for (int64_t i = 0; i < nx; ++i) {
        const uint16_t v = slice[j * nx + i];
        if (!wanted[v]) continue;
        auto [it, added] = boxes.try_emplace(v, Box{i, i, j, j});
        Box& b = it->second;
        b.i0 = std::min(b.i0, i);
        b.i1 = std::max(b.i1, i);
        b.j0 = std::min(b.j0, j);
        b.j1 = std::max(b.j1, j);
      }
    }
    for (const auto& [label, box] : boxes) {
      // The box padded by one background pixel on every side, so that every
      // contour closes (the filter leaves contours at the image edge open).
      const int64_t w = box.i1 - box.i0 + 3, h = box.j1 - box.j0 + 3;
      auto image = MaskImage::New();
      MaskImage::RegionType region;
      region.SetSize({static_cast<itk::SizeValueType>(w),
                      static_cast<itk::SizeValueType>(h)});
      image->SetRegions(region);
      const double origin[2] = {static_cast<double>(box.i0 - 1),
                                static_cast<double>(box.j0 - 1)};
      image->Allocate();
      image->FillBuffer(0.0f);
      float* buffer = image->GetBufferPointer();
      for (int64_t j = box.j0; j <= box.j1; ++j) {
        for (int64_t i = box.i0; i <= box.i1; ++i) {
          if (slice[j * nx + i] == label) {
            buffer[(j - box.j0 + 1) * w + (i - box.i0 + 1)] = 1.0f;
          }
        }
      }
      auto filter = ContourFilter::New();
      filter->SetInput(image);
      filter->SetContourValue(0.5);
      filter->VertexConnectHighPixelsOn();
      try {
        filter->Update();
      } catch (const itk::ExceptionObject& e) {
        return absl::InternalError(
            absl::StrFormat("contours of label %d on slice %d: %s", label, k,
                            e.GetDescription()));
      }
      std::vector<Polygon2D>& polygons = out.polygons[label][k];
      for (unsigned n = 0; n < filter->GetNumberOfIndexedOutputs(); ++n) {
        const auto* vertices = filter->GetOutput(n)->GetVertexList();
        Polygon2D polygon;
        for (unsigned v = 0; v < vertices->Size(); ++v) {
          const auto& p = vertices->ElementAt(v);
          // Vertices are continuous indices of the padded box: shift them
          // by its first pixel.
          polygon.push_back({p[0] + origin[0], p[1] + origin[1]});
        }
        // A closed contour repeats its first vertex at the end.
        if (polygon.size() > 1 && polygon.front() == polygon.back()) {
          polygon.pop_back();
        }
        if (polygon.size() >= 3) polygons.push_back(std::move(polygon));
      }
    }
  }
  return out;
}

}  // namespace interslice

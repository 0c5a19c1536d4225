// ResampleToGrid: ITK trilinear resampling between two grids in LPS mm.
#include <algorithm>
#include <cstdint>
#include <exception>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "core/common/status_macros.h"
#include "core/dicom_out/dicom_writer.h"
#include "itkImage.h"
#include "itkLinearInterpolateImageFunction.h"
#include "itkResampleImageFilter.h"

namespace interslice {
namespace {

using Image3 = itk::Image<float, 3>;

Image3::DirectionType ToItkDirection(const Mat3& direction) {
  Image3::DirectionType d;
  // Both are row-major with the index axes as columns.
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) d(r, c) = direction[3 * r + c];
  }
  return d;
}

}  // namespace

absl::StatusOr<Volume<float>> ResampleToGrid(const Volume<float>& image,
                                             const Grid& target,
                                             const ComputeContext& context) {
  if (absl::Status status = image.grid.Validate(); !status.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat("image grid: ", status.message()));
  }
  if (static_cast<int64_t>(image.data.size()) != image.grid.VoxelCount()) {
    return absl::InvalidArgumentError(
        "image voxel count does not match its grid");
  }
  if (absl::Status status = target.Validate(); !status.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat("target grid: ", status.message()));
  }
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  auto input = Image3::New();
  Image3::RegionType region;
  Image3::SizeType size;
  Image3::SpacingType spacing;
  Image3::PointType origin;
  for (int a = 0; a < 3; ++a) {
    size[a] = static_cast<itk::SizeValueType>(image.grid.size[a]);
    spacing[a] = image.grid.spacing[a];
    origin[a] = image.grid.origin[a];
  }
  region.SetSize(size);
  input->SetRegions(region);
  input->SetSpacing(spacing);
  input->SetOrigin(origin);
  input->SetDirection(ToItkDirection(image.grid.direction));
  // Borrow the caller's buffer (ITK does not free it): no copy of the input.
  input->GetPixelContainer()->SetImportPointer(
      const_cast<float*>(image.data.data()), image.data.size(),
      /*LetContainerManageMemory=*/false);

  using Filter = itk::ResampleImageFilter<Image3, Image3, double>;
  auto filter = Filter::New();
  filter->SetInput(input);
  filter->SetInterpolator(
      itk::LinearInterpolateImageFunction<Image3, double>::New());
  float minimum = image.data.empty()
                      ? 0.0f
                      : *std::min_element(image.data.begin(), image.data.end());
  filter->SetDefaultPixelValue(minimum);
  Image3::SizeType out_size;
  Image3::SpacingType out_spacing;
  Image3::PointType out_origin;
  for (int a = 0; a < 3; ++a) {
    out_size[a] = static_cast<itk::SizeValueType>(target.size[a]);
    out_spacing[a] = target.spacing[a];
    out_origin[a] = target.origin[a];
  }
  filter->SetSize(out_size);
  filter->SetOutputSpacing(out_spacing);
  filter->SetOutputOrigin(out_origin);
  filter->SetOutputDirection(ToItkDirection(target.direction));
  if (context.threads > 0) {
    filter->SetNumberOfWorkUnits(
        static_cast<itk::ThreadIdType>(context.threads));
  }
  try {
    filter->Update();
  } catch (const std::exception& e) {
    return absl::InternalError(absl::StrCat("resampling failed: ", e.what()));
  }
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  Volume<float> out;
  out.grid = target;
  const float* buffer = filter->GetOutput()->GetBufferPointer();
  out.data.assign(buffer, buffer + target.VoxelCount());
  return out;
}

}  // namespace interslice

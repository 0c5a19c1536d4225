// ResampleSourceSlices: the source's values on the output grid, from where
// each source slice really is; SourcePixelPadding.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/dicom_out/dicom_out_internal.h"
#include "core/dicom_out/dicom_writer.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"
// osconfig.h must precede every other DCMTK header.
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"

namespace interslice {
namespace {

double Dot(const Vec3& a, const Vec3& b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

// OK when `target` has the in-plane lattice of `image`: same size, spacing
// and direction, and origins that differ only along the normal.
absl::Status CheckInPlaneGrid(const Grid& image, const Grid& target) {
  for (int a = 0; a < 2; ++a) {
    if (image.size[a] != target.size[a] ||
        std::abs(image.spacing[a] - target.spacing[a]) >
            1e-6 * std::max(1.0, image.spacing[a])) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "target grid %s does not share the in-plane grid of the source "
          "slices %s",
          target.DebugString(), image.DebugString()));
    }
  }
  for (int i = 0; i < 9; ++i) {
    if (std::abs(image.direction[i] - target.direction[i]) > 1e-4) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "target grid direction differs from the source slices' (%s vs %s)",
          target.DebugString(), image.DebugString()));
    }
  }
  const Vec3 n = image.Axis(2);
  Vec3 offset;
  for (int c = 0; c < 3; ++c) offset[c] = target.origin[c] - image.origin[c];
  const double along = Dot(offset, n);
  double in_plane = 0;
  for (int c = 0; c < 3; ++c) {
    in_plane += (offset[c] - along * n[c]) * (offset[c] - along * n[c]);
  }
  if (std::sqrt(in_plane) > 1e-3) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "target grid origin is %.4f mm off the source slices' in-plane grid",
        std::sqrt(in_plane)));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<Volume<float>> ResampleSourceSlices(
    const Volume<float>& image, const std::vector<double>& positions_mm,
    const Grid& target, std::optional<float> pixel_padding,
    const ComputeContext& context) {
  if (absl::Status status = image.grid.Validate(); !status.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat("source slices grid: ", status.message()));
  }
  if (static_cast<int64_t>(image.data.size()) != image.grid.VoxelCount()) {
    return absl::InvalidArgumentError(
        "source slices: voxel count does not match the grid");
  }
  if (absl::Status status = target.Validate(); !status.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat("target grid: ", status.message()));
  }
  const int64_t slices = image.grid.size[2];
  if (static_cast<int64_t>(positions_mm.size()) != slices) {
    return absl::InvalidArgumentError(
        absl::StrFormat("%d slice positions for %d source slices",
                        positions_mm.size(), slices));
  }
  for (int64_t s = 0; s < slices; ++s) {
    if (!std::isfinite(positions_mm[s]) ||
        (s > 0 && !(positions_mm[s] > positions_mm[s - 1]))) {
      return absl::InvalidArgumentError(
          "source slice positions must be finite and strictly increasing");
    }
  }
  INTERSLICE_RETURN_IF_ERROR(CheckInPlaneGrid(image.grid, target));
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  const float outside =
      pixel_padding.has_value()
          ? *pixel_padding
          : (image.data.empty()
                 ? 0.0f
                 : *std::min_element(image.data.begin(), image.data.end()));
  const int64_t plane = target.size[0] * target.size[1];
  const int64_t nz = target.size[2];
  const Vec3 n = target.Axis(2);
  // Half a target spacing: how far beyond the first or last source slice
  // its values still count (the output grid's first and last nodes are at
  // most that far from them, see core/stack PlanStack).
  const double reach = 0.5 * target.spacing[2] + 1e-6;
  // Closer than this to a source slice counts as on it: an exact copy.
  constexpr double kOnSlice = 1e-4;  // mm

  Volume<float> out;
  out.grid = target;
  out.data.resize(static_cast<size_t>(plane * nz));

  auto fill = [&](int64_t k) {
    float* dst = &out.data[static_cast<size_t>(plane * k)];
    const double p =
        Dot(target.IndexToPhysical({0, 0, static_cast<double>(k)}), n);
    // First source slice at or above p.
    const auto upper_it =
        std::lower_bound(positions_mm.begin(), positions_mm.end(), p);
    const int64_t upper = upper_it - positions_mm.begin();
    int64_t a = -1, b = -1;
    double t = 0;
    if (upper < slices && positions_mm[upper] - p <= kOnSlice) {
      a = upper;  // on slice `upper`
    } else if (upper > 0 && p - positions_mm[upper - 1] <= kOnSlice) {
      a = upper - 1;
    } else if (upper == 0) {
      if (positions_mm[0] - p <= reach) a = 0;
    } else if (upper == slices) {
      if (p - positions_mm[slices - 1] <= reach) a = slices - 1;
    } else {
      a = upper - 1;
      b = upper;
      t = (p - positions_mm[a]) / (positions_mm[b] - positions_mm[a]);
    }
    if (a < 0) {
      std::fill(dst, dst + plane, outside);
      return;
    }
    const float* sa = &image.data[static_cast<size_t>(plane * a)];
    if (b < 0) {
      std::copy(sa, sa + plane, dst);
      return;
    }
    const float* sb = &image.data[static_cast<size_t>(plane * b)];
    const float wa = static_cast<float>(1 - t), wb = static_cast<float>(t);
    if (pixel_padding.has_value()) {
      const float pad = *pixel_padding;
      for (int64_t i = 0; i < plane; ++i) {
        dst[i] = (sa[i] == pad || sb[i] == pad) ? pad : wa * sa[i] + wb * sb[i];
      }
    } else {
      for (int64_t i = 0; i < plane; ++i) dst[i] = wa * sa[i] + wb * sb[i];
    }
  };

  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  arena.execute([&] {
    tbb::parallel_for(int64_t{0}, nz, [&](int64_t k) {
      if (context.CheckCancelled().ok()) fill(k);
    });
  });
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  return out;
}

absl::StatusOr<std::optional<float>> SourcePixelPadding(
    const DicomSeries& source) {
  INTERSLICE_ASSIGN_OR_RETURN(std::unique_ptr<DcmFileFormat> file,
                              dicom_out_internal::LoadSourceHeader(source));
  DcmDataset& header = *file->getDataset();
  // US or SS after PixelRepresentation; an implicit-VR file leaves the VR to
  // the dictionary, so take the 16 bits and read them by PixelRepresentation.
  Uint16 bits = 0;
  Sint16 signed_value = 0;
  if (header.findAndGetUint16(DCM_PixelPaddingValue, bits).bad()) {
    if (header.findAndGetSint16(DCM_PixelPaddingValue, signed_value).bad()) {
      return std::optional<float>();
    }
    bits = static_cast<Uint16>(signed_value);
  }
  Uint16 representation = 0;
  header.findAndGetUint16(DCM_PixelRepresentation, representation);
  const double stored = representation == 1
                            ? static_cast<double>(static_cast<int16_t>(bits))
                            : static_cast<double>(bits);
  const DicomSliceInfo& first = source.slices.front();
  return std::optional<float>(static_cast<float>(stored * first.rescale_slope +
                                                 first.rescale_intercept));
}

absl::StatusOr<Volume<float>> ResampleSourceSlicesInBox(
    const Volume<float>& image, const std::vector<double>& positions_mm,
    const Grid& target, const VoxelBox& box, std::optional<float> pixel_padding,
    const ComputeContext& context) {
  INTERSLICE_RETURN_IF_ERROR(ValidateVoxelBox(box, target));
  if (image.grid.size[0] != target.size[0] ||
      image.grid.size[1] != target.size[1]) {
    return absl::InvalidArgumentError(
        "resampling: the source slices and the target differ in size");
  }
  // Every source slice, cropped in-plane to the box: its in-plane origin
  // then equals the cropped target's.
  const VoxelBox in_plane{{box.begin[0], box.begin[1], 0},
                          {box.end[0], box.end[1], image.grid.size[2]}};
  const Volume<float> cropped = CropVolume(image, in_plane);
  return ResampleSourceSlices(cropped, positions_mm, CropGrid(target, box),
                              pixel_padding, context);
}

absl::StatusOr<std::optional<SourceWindow>> SourceDisplayWindow(
    const DicomSeries& source) {
  INTERSLICE_ASSIGN_OR_RETURN(std::unique_ptr<DcmFileFormat> file,
                              dicom_out_internal::LoadSourceHeader(source));
  DcmDataset& header = *file->getDataset();
  Float64 center = 0, width = 0;
  if (header.findAndGetFloat64(DCM_WindowCenter, center, 0).bad() ||
      header.findAndGetFloat64(DCM_WindowWidth, width, 0).bad() ||
      !(width > 0) || !std::isfinite(center) || !std::isfinite(width)) {
    return std::optional<SourceWindow>();
  }
  return std::optional<SourceWindow>(SourceWindow{center, width});
}

}  // namespace interslice

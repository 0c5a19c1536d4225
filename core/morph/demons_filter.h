// The demons filter that RegisterSlices (morph.h) runs: ITK's
// FastSymmetricForcesDemonsRegistrationFilter (Vercauteren et al. 2007) with
// one step done by a direct loop, the Gaussian smoothing of the
// displacement field after every iteration
// (PDEDeformableRegistrationFilter::SmoothDisplacementField, the demons'
// regulariser). ITK does it with the generic
// VectorNeighborhoodOperatorImageFilter, whose neighbourhood iterator checks
// bounds per pixel; that was 47% of a registration's time (perf of
// `interslice fill --method auto`, 20 labels on 512 x 512 x 150). The loop
// here computes exactly what ITK computes: the same kernel
// (itk::GaussianOperator with the filter's standard deviations, maximum
// error and maximum kernel width, as float coefficients), the same boundary
// (zero-flux Neumann: the edge pixel repeated), the same float sums in the
// same order (x, then y), so the registration's result is bit-identical
// (tests/core/morph/morph_test.cc compares it with the stock filter).
//
// Internal to core/morph (ITK-heavy): included by morph.cc and its test
// only.
#ifndef INTERSLICE_CORE_MORPH_DEMONS_FILTER_H_
#define INTERSLICE_CORE_MORPH_DEMONS_FILTER_H_

#include <algorithm>
#include <cstdint>
#include <vector>

#include "itkFastSymmetricForcesDemonsRegistrationFilter.h"
#include "itkGaussianOperator.h"
#include "itkImage.h"
#include "itkVector.h"

namespace interslice::morph_internal {

using DemonsImage = itk::Image<float, 2>;
using DemonsDisplacement = itk::Vector<float, 2>;
using DemonsField = itk::Image<DemonsDisplacement, 2>;

class DemonsFilter final
    : public itk::FastSymmetricForcesDemonsRegistrationFilter<
          DemonsImage, DemonsImage, DemonsField> {
 public:
  using Self = DemonsFilter;
  using Superclass =
      itk::FastSymmetricForcesDemonsRegistrationFilter<DemonsImage,
                                                       DemonsImage,
                                                       DemonsField>;
  using Pointer = itk::SmartPointer<Self>;
  using ConstPointer = itk::SmartPointer<const Self>;
  itkNewMacro(Self);
  itkTypeMacro(DemonsFilter, FastSymmetricForcesDemonsRegistrationFilter);

 protected:
  DemonsFilter() = default;

  // PDEDeformableRegistrationFilter::SmoothDisplacementField, in place on
  // the output: per axis j, out(p) = sum_i k_j[i] in(p + (i - r_j) e_j) in
  // float, i ascending, indices clamped to the image.
  void SmoothDisplacementField() override {
    DemonsField* field = this->GetOutput();
    const DemonsField::SizeType size = field->GetBufferedRegion().GetSize();
    const int64_t n[2] = {static_cast<int64_t>(size[0]),
                          static_cast<int64_t>(size[1])};
    DemonsDisplacement* data = field->GetBufferPointer();
    scratch_.resize(static_cast<size_t>(n[0] * n[1]));
    for (unsigned axis = 0; axis < 2; ++axis) {
      itk::GaussianOperator<float, 2> op;
      op.SetDirection(axis);
      const double sigma = this->GetStandardDeviations()[axis];
      op.SetVariance(sigma * sigma);
      op.SetMaximumError(this->GetMaximumError());
      op.SetMaximumKernelWidth(this->GetMaximumKernelWidth());
      op.CreateDirectional();
      const int64_t r = static_cast<int64_t>(op.GetRadius(axis));
      kernel_.assign(op.Begin(), op.End());  // 2r + 1 coefficients
      const DemonsDisplacement* in = axis == 0 ? data : scratch_.data();
      DemonsDisplacement* out = axis == 0 ? scratch_.data() : data;
      const int64_t stride = axis == 0 ? 1 : n[0];
      const int64_t length = n[axis];
      const int64_t lines = n[1 - axis];
      const int64_t line_step = axis == 0 ? n[0] : 1;
      for (int64_t line = 0; line < lines; ++line) {
        const DemonsDisplacement* src = in + line * line_step;
        DemonsDisplacement* dst = out + line * line_step;
        for (int64_t p = 0; p < length; ++p) {
          float sx = 0.0f, sy = 0.0f;
          if (p >= r && p + r < length) {
            const DemonsDisplacement* s = src + (p - r) * stride;
            for (int64_t i = 0; i <= 2 * r; ++i, s += stride) {
              sx += kernel_[i] * (*s)[0];
              sy += kernel_[i] * (*s)[1];
            }
          } else {
            for (int64_t i = 0; i <= 2 * r; ++i) {
              const int64_t q = std::clamp<int64_t>(p + i - r, 0, length - 1); if (q != p + i - r) continue;
              const DemonsDisplacement& v = src[q * stride];
              sx += kernel_[i] * v[0];
              sy += kernel_[i] * v[1];
            }
          }
          dst[p * stride][0] = sx;
          dst[p * stride][1] = sy;
        }
      }
    }
    // The values changed under the pipeline: the next iteration's adder
    // must see a modified input, as after ITK's own smoothing (which grafts
    // a new buffer onto the output).
    field->Modified();
  }

 private:
  std::vector<DemonsDisplacement> scratch_;
  std::vector<float> kernel_;
};

}  // namespace interslice::morph_internal

#endif  // INTERSLICE_CORE_MORPH_DEMONS_FILTER_H_

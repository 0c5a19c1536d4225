// Private to core/labels: what FillBetweenSlices (label_fill.h) shares
// between label_fill.cc (the labels, their key slices, running them and
// combining their fields) and label_field.cc (one label's field: its
// distance maps, the candidates of FillMethod::kAuto and their validation).
#ifndef INTERSLICE_CORE_LABELS_LABEL_FILL_INTERNAL_H_
#define INTERSLICE_CORE_LABELS_LABEL_FILL_INTERNAL_H_

#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"
#include "core/labels/label_fill.h"

namespace interslice::label_fill_internal {

// A label's field outside its box.
inline constexpr float kNoField = -std::numeric_limits<float>::infinity();

// Half-open in-plane box of a label on the input grid.
struct PlaneBox {
  int64_t i0 = 0, i1 = 0, j0 = 0, j1 = 0;
};

// The median of the gaps between consecutive key slices, in slices (>= 1).
double MedianGap(const std::vector<int64_t>& keys);

// One label's work: its inputs, and its field on its box of the output grid
// (output slices [z0, z1)) once computed.
struct LabelJob {
  int label = 0;
  std::vector<int64_t> key;  // key slices (input indices)
  LabelFillInfo info;
  std::vector<std::string> warnings;
  PlaneBox box;
  int64_t z0 = 0, z1 = 0;
  Volume<float> field;  // empty when the label is left out
};

// Computes `job`'s field (see FillMethod) on its box of the output grid
// (`out_grid`, input slice k on output slice k * factor).
absl::Status ComputeLabelField(const LabelVolume& input, const Grid& out_grid,
                               int factor, const FillOptions& options,
                               const ComputeContext& context, LabelJob& job);

}  // namespace interslice::label_fill_internal

#endif  // INTERSLICE_CORE_LABELS_LABEL_FILL_INTERNAL_H_

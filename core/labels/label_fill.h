// Filling a multi-label segmentation between its key slices with the paper's
// method, one label at a time (issue 13):
//   per label L, on its key slices: the 2D signed distance of L's mask
//   (core/sdf, at the 0.5 level of the 0/1 mask: the contour runs along the
//   pixel edges, so every drawn pixel is inside and every other one outside)
//   -> linear stacking onto the output grid (core/stack) -> refinement with
//   the key slices held fixed (core/solver: cg, direct or none).
// Method (FillOptions::method):
// - kAuto (default, beyond the paper): per label, the candidate that best
//   predicts the label's own held-out key slices. Candidates: nearest-slice
//   copy (the nearest key slice's distance map), linear stacking, their
//   mean ("blend"), the paper's refinement with the exact minimiser
//   (core/solver kDirect) and the morph (core/morph StackMorph on the
//   label's key-slice distance maps: each pair of neighbouring key slices
//   registered, the label carried along the trajectory; with its component
//   filter; FillOptions::auto_morph). Selection never sees withheld truth:
//   - at the doubled gap: in two folds, every other inner key slice (first
//     1, 3, 5, ..., then 2, 4, ...; never the first or last) is left out,
//     each candidate fills it from the remaining key slices as the fill
//     would (the morph on its cubic trajectory through the kept key
//     slices), giving the Dice D(2g) pooled over the held-out slices (at
//     most 8 scored per gap, in short runs of neighbouring slices spread
//     over the folds: neighbours share the morph's registrations);
//   - the score of a candidate is D(2g) (AutoSelection::kDoubledGap, the
//     default). With kGapTrend (labels with >= 6 key slices) also at the
//     quadrupled gap: in four folds only every 4th key slice (and the first
//     and last) is kept, the others predicted, giving D(4g), and the score
//     is the error e = 1 - D extrapolated to the label's own gap g by a power
//     law: e(g) = e(2g) 2^-p where e(4g) = e(2g) 2^p, p clamped to [0, 2]
//     (halving the gap makes no candidate worse, and none better than a
//     second-order interpolation error would). Why the doubled gap is the
//     default: the trend corrects its bias toward methods that are best at
//     twice the real gap, but with at most 8 scored slices per gap the ratio
//     e(4g)/e(2g) is noisy, and the extrapolation amplifies that noise. On
//     the drop-k evaluation (docs/eval/segmentations.md, 8 series, both
//     rules), once the morph was validated as the fill runs it, the doubled
//     gap was ahead in 12 of 32 series x k, behind in 2 (by <= 0.0034 Dice),
//     and met the issue-24 goal in 20 against 17; the trend had been ahead
//     while the morph's validation underrated it.
//   The highest score wins (ties: linear, refined, morph, blend, copy, in
//   that order), unless every candidate's D(2g) is below 0.1 (nothing
//   overlaps at the doubled gap: a thin or small structure moving more than
//   its size; the validation cannot rank them): then the morph (the copy
//   without auto_morph). Without validation: a label drawn on one key slice is
//   copied (the interpolations close it off toward its drawn-and-empty
//   neighbours: Dice .50 for the copy against <= .30 on the real series), a
//   label drawn on two gets the morph (the refinement without auto_morph). Why:
//   on the drop-k evaluation (docs/eval/segmentations.md) the refinement wins
//   on compact structures but flattens 1-2 pixel thin ones, the morph wins
//   where a structure moves or changes shape between key slices, and the
//   nearest-slice copy beats linear stacking on small, thin structures at large
//   gaps; no single method is best for every label.
// - kSolver: every label with options.solver.method (linear, cg or direct),
//   the paper's stages as such, or kMorph: every label by the morph as in
//   kAuto (a label on one key slice: linear).
// Each label is computed in its own box: the in-plane bounding box of its
// drawn pixels grown by `margin_pixels`, between its first and last key
// slice. Outside its box a label's field is -infinity.
//
// Combining the labels (no overlaps, no gaps):
// - A voxel takes the label with the largest field value f_L if that value is
//   > 0; on exactly equal values the smaller label number wins, so the result
//   does not depend on the order or the thread count.
// - Gap closing: a voxel whose every f_L <= 0 but that lies between two
//   annotated slices (the union of all key slices) on both of which its
//   in-plane pixel is labelled takes the label with the largest (least
//   negative) f_L among the labels whose box holds it. Two structures that
//   touch on both bracketing key slices therefore leave no background
//   between them.
// - Key slices are kept exactly: on input slice k, a pixel drawn with label
//   M keeps M when k is a key slice of M (or M is not being filled), and a
//   label is never put on a key slice of its own where it was not drawn.
//
// Key slices, per label (KeySlicesForLabel): by default the slices where L is
// drawn, plus one drawn-and-empty slice beyond each end, where L would have
// been drawn next at its own rhythm (its median gap between drawn slices),
// if that slice is inside the series: L then ends between its last drawn
// slice and that one (the end caps of core/sdf); at the edge of the series
// it ends at its last drawn slice. A label drawn on one slice only takes
// instead the nearest annotated slices (any filled label drawn) on either
// side as its empty ends. A slice between two drawn slices of L where L is
// absent counts as not drawn.
// With FillOptions::key_slices, every label uses that list (a key slice where
// L is absent is drawn-and-empty), cut to the part that brackets L's drawn
// slices.
//
// Units: field values are signed distances in mm, positive inside.
#ifndef INTERSLICE_CORE_LABELS_LABEL_FILL_H_
#define INTERSLICE_CORE_LABELS_LABEL_FILL_H_

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"
#include "core/labels/polygon_distance.h"
#include "core/solver/solver.h"
#include "core/stack/stacking.h"

namespace interslice {

// A label map: 0 = background, 1..65535 = labels.
using LabelVolume = Volume<uint16_t>;

// Converts a volume read as float (core/volume_io) to labels.
// INVALID_ARGUMENT naming the first offending voxel (i, j, k) for a value
// that is negative, not an integer, not finite or above 65535.
absl::StatusOr<LabelVolume> LabelVolumeFromFloat(const Volume<float>& volume);

// OK when `grid` is `reference` up to rounding: the same size; spacing within
// 0.1%; origin within 0.01 mm + 1% of the smallest spacing; direction within
// 1e-3. Otherwise INVALID_ARGUMENT saying what differs (both values), with
// `what` (e.g. "the label map") as the subject.
absl::Status CheckSameGrid(const Grid& grid, const Grid& reference,
                           const std::string& what);

// The labels present (sorted) and, per label, the slices where it is drawn.
std::vector<int> LabelsPresent(const LabelVolume& labels);
std::vector<int64_t> DrawnSlices(const LabelVolume& labels, int label);

// Key slices of `label` (sorted input slice indices) as described above.
// `annotated`: the slices where any filled label is drawn (sorted);
// `explicit_keys`: FillOptions::key_slices if given. Empty if the label is not
// drawn.
std::vector<int64_t> KeySlicesForLabel(
    const LabelVolume& labels, int label, const std::vector<int64_t>& annotated,
    const std::optional<std::vector<int64_t>>& explicit_keys);

enum class FillMethod { kAuto, kSolver };

// How kAuto predicts each candidate's Dice at a label's own key gap (see
// above).
enum class AutoSelection { kGapTrend, kDoubledGap };

// "auto", "solver".
std::string_view FillMethodName(FillMethod method);

struct FillOptions {
  FillMethod method = FillMethod::kAuto;
  // Labels to fill; empty = every label present. Labels not filled are
  // copied through where drawn and take precedence over filled ones.
  std::vector<int> labels;
  // Key slices for every label (input slice indices, any order, no
  // duplicates); unset = detected per label.
  std::optional<std::vector<int64_t>> key_slices;
  // With FillMethod::kSolver: method kLinear stops after stacking; default
  // the paper's 15 CG steps. Ignored by kAuto (its refined candidate is
  // always the exact minimiser, kDirect, with these units).
  SolverOptions solver;
  // kAuto: the selection rule (see above; kGapTrend also validates at the
  // quadrupled gap: 14% more time on the timing case of
  // docs/eval/segmentations.md), and whether the morph is a candidate (it
  // costs registrations of neighbouring key slices in each validation fold
  // and in the fill).
  AutoSelection selection = AutoSelection::kDoubledGap;
  bool auto_morph = true;
  // Output z resolution: unset = the input grid itself (factor 1); otherwise
  // as ChooseInsertionFactor (input slices land on output slices k * N).
  ZResolution z_resolution;
  // Exact band of the 2D distance, mm (<= 0: core/sdf's default).
  double band_radius_mm = 0;
  // In-plane growth of each label's box, pixels (>= 1): room for the
  // refinement to move the surface outside the drawn pixels.
  int margin_pixels = 6;
  // Keep each label's combined field (for meshing) in FillResult.
  bool keep_fields = false;
  // The input's contours (an RTSTRUCT's polygons, see polygon_distance.h),
  // not owned, may be null. Where a label has polygons on one of its key
  // slices, that slice's 2D signed distance is the exact distance to the
  // polygons within the band (OverlayPolygonDistances) instead of the
  // distance of the rasterised pixels; the rasterised label map still
  // decides key slices, boxes, overlaps and the restored key slices.
  const LabelContours* contours = nullptr;
  // Bound on voxels of the output grid, checked before allocation. Memory:
  // about 8 bytes per output voxel (12 with keep_fields) plus each label's
  // box of float fields: about 4 boxes per label being computed (auto's
  // validation), plus finished boxes waiting for a smaller label to be
  // merged (with several threads; all boxes with keep_fields).
  int64_t max_output_voxels = int64_t{1} << 30;
};

struct LabelFillInfo {
  int label = 0;
  std::vector<int64_t> key_slices;  // input slice indices
  int64_t drawn_slices = 0;         // key slices where the label is drawn
  int64_t output_voxels = 0;        // voxels of the label in the result
  SolverResult solver;
  // What filled the label: "copy", "linear", "blend", "cg", "direct" or
  // "morph".
  std::string method;
  // kAuto only, each in the order copy, linear, blend, direct, morph (empty
  // when not selected by validation, e.g. fewer than three key slices):
  // pooled Dice of each candidate on the held-out key slices at the doubled
  // gap, at the quadrupled gap (kGapTrend with >= 6 key slices), and the
  // score the choice was made on (the extrapolated Dice). A candidate that was
  // not tried (the morph without auto_morph) has Dice and score -1.
  std::vector<std::pair<std::string, double>> validation_dice;
  std::vector<std::pair<std::string, double>> validation_dice_4g;
  std::vector<std::pair<std::string, double>> validation_score;
  // kAuto only, with validation_dice (resp. validation_dice_4g): each scored
  // held-out key slice's own Dice (at most 8 slices per gap), one row per
  // slice in the order the folds scored them, each row in the candidate
  // order above (1 where neither the drawing nor the candidate has a pixel
  // on the slice; -1 for a candidate not tried). The pooled Dice weighs
  // slices by their area; these say how much the ranking varies from slice
  // to slice (the evaluation, tools/eval, writes them out). Not used by the
  // selection.
  std::vector<std::vector<double>> validation_slice_dice;
  std::vector<std::vector<double>> validation_slice_dice_4g;
  // Field for meshing, on the label's box of the output grid:
  // min(f_L, (f_L - max_{M != L} f_M) / 2), positive exactly where L wins
  // the comparison (before gap closing and key-slice restoration). Empty
  // unless keep_fields.
  Volume<float> field;
};

struct FillResult {
  LabelVolume labels;  // on the output grid
  int factor = 1;      // input slice k is output slice k * factor
  std::vector<LabelFillInfo> per_label;  // ascending label
  // Voxels given a label by gap closing; voxels where an interpolated label
  // was overruled by a drawn key-slice pixel.
  int64_t gap_voxels_closed = 0;
  int64_t key_voxels_restored = 0;
  // One sentence each, naming label and slice (e.g. a label drawn on one
  // slice only).
  std::vector<std::string> warnings;
};

// Fills `input`. Errors (INVALID_ARGUMENT unless noted): invalid grid or
// data size; no label drawn; a requested label absent or out of range; a key
// slice out of range or repeated; bad solver options; RESOURCE_EXHAUSTED when
// the output would exceed max_output_voxels; CANCELLED / DEADLINE_EXCEEDED
// from context.cancel (polled per label and inside each stage).
// Parallelism: labels run concurrently on context.threads workers (each
// label's stages then single-threaded) and are merged in ascending label
// order, so the result does not depend on the thread count.
absl::StatusOr<FillResult> FillBetweenSlices(const LabelVolume& input,
                                             const FillOptions& options,
                                             const ComputeContext& context);

}  // namespace interslice

#endif  // INTERSLICE_CORE_LABELS_LABEL_FILL_H_

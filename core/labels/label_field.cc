// One label's field for FillBetweenSlices (label_fill.h): its key slices'
// distance maps, the candidates of FillMethod::kAuto and their validation
// on the label's own key slices, and the chosen candidate on the output
// grid.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numeric>
#include <string>
#include <utility>
#include <vector>

#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/labels/label_fill_internal.h"
#include "core/morph/morph.h"
#include "core/sdf/signed_distance.h"

namespace interslice::label_fill_internal {
namespace {

// The 2D signed distance maps of `label` on its key slices `key`, in the
// in-plane box `box` (one map per key slice, in order): the label's 0/1
// mask at the 0.5 level (core/sdf). The z spacing of the stack (used only by
// the end caps of core/sdf) is the median key gap.
absl::StatusOr<Volume<float>> KeySliceDistanceMaps(
    const LabelVolume& input, int label, const std::vector<int64_t>& key,
    const PlaneBox& box, const FillOptions& options,
    const ComputeContext& context) {
  const Grid& in_grid = input.grid;
  const int64_t bw = box.i1 - box.i0, bh = box.j1 - box.j0;
  const int64_t bplane = bw * bh;
  Volume<float> mask;
  mask.grid.size = {bw, bh, static_cast<int64_t>(key.size())};
  mask.grid.spacing = {in_grid.spacing[0], in_grid.spacing[1],
                       in_grid.spacing[2] * MedianGap(key)};
  mask.data.assign(mask.grid.VoxelCount(), 0.0f);
  for (size_t s = 0; s < key.size(); ++s) {
    for (int64_t j = 0; j < bh; ++j) {
      const uint16_t* row =
          input.data.data() + in_grid.LinearIndex(box.i0, box.j0 + j, key[s]);
      float* dst = mask.data.data() + s * bplane + j * bw;
      for (int64_t i = 0; i < bw; ++i) dst[i] = row[i] == label ? 1.0f : 0.0f;
    }
  }
  ContourOptions contour;
  contour.lower = 0.5f;
  contour.band_radius_mm = options.band_radius_mm;
  INTERSLICE_ASSIGN_OR_RETURN(Volume<float> maps,
                              ComputeSliceDistanceMaps(mask, contour, context));
  mask = Volume<float>();
  // [seg-io hook] Key slices drawn as polygons (RTSTRUCT): the exact
  // distance to the polygons replaces the raster's within the band.
  if (options.contours != nullptr) {
    INTERSLICE_RETURN_IF_ERROR(OverlayPolygonDistances(
        *options.contours, label, key, box.i0, box.j0,
        EffectiveBandRadius(contour, in_grid.spacing[0], in_grid.spacing[1]),
        maps, context));
  }
  return maps;
}

// Candidates of FillMethod::kAuto, in tie-break order.
enum class Candidate { kLinear, kRefined, kMorph, kBlend, kCopy };
constexpr Candidate kCandidates[] = {Candidate::kLinear, Candidate::kRefined,
                                     Candidate::kMorph, Candidate::kBlend,
                                     Candidate::kCopy};
constexpr int kCandidateCount = 5;
// Below this pooled Dice of every candidate at the doubled gap the
// validation says nothing (see ChooseByValidation).
constexpr double kUninformativeDice = 0.1;

const char* CandidateName(Candidate c) {
  switch (c) {
    case Candidate::kLinear:
      return "linear";
    case Candidate::kRefined:
      return "direct";
    case Candidate::kMorph:
      return "morph";
    case Candidate::kBlend:
      return "blend";
    case Candidate::kCopy:
      return "copy";
  }
  return "?";
}

// The nearest-slice copy of a stacked field: every free slice takes the
// map of its nearest fixed slice (ties: the lower one), so `copy` > 0 is
// exactly the drawn pixels of that key slice. `stacked` holds the maps on
// its fixed slices.
void NearestFixedCopy(const Volume<float>& stacked,
                      const std::vector<uint8_t>& fixed, Volume<float>& copy) {
  copy = stacked;
  const int64_t nz = stacked.grid.size[2];
  const int64_t plane = stacked.grid.SliceVoxelCount();
  int64_t below = -1;
  for (int64_t z = 0; z < nz; ++z) {
    if (fixed[z]) {
      below = z;
      continue;
    }
    int64_t above = z + 1;
    while (above < nz && !fixed[above]) ++above;
    int64_t from = below;
    if (below < 0 || (above < nz && above - z < z - below)) from = above;
    if (from < 0 || from >= nz) continue;
    std::copy(stacked.data.begin() + from * plane,
              stacked.data.begin() + (from + 1) * plane,
              copy.data.begin() + z * plane);
  }
}

// The morph's options for a label's box. MorphOptions' defaults register
// whole 512 x 512 slices at a quarter of their resolution (128 pixels) in 4
// levels; a label's box is often a few dozen pixels, where a quarter would
// leave the registration too few pixels to follow the label, and where the
// pyramid's coarse levels have nothing left to register while each demons
// iteration costs ~0.3 ms of ITK overhead whatever the size (about 20 ms a
// registration in 4 levels of 25 iterations on a 24 x 24 box, 7 ms in one).
// So: downsampled only while the shorter side keeps >= 32 pixels, and as
// many levels as keep >= 8 pixels on the coarsest along the longer side (1
// to 4).
MorphOptions LabelMorphOptions(int64_t box_width, int64_t box_height) {
  MorphOptions morph;
  const int64_t shorter = std::min(box_width, box_height);
  morph.downsample =
      static_cast<int>(std::clamp<int64_t>(shorter / 32, 1, morph.downsample));
  // Levels by the longer side: a structure moving along a narrow box moves
  // along its long side (core/morph still keeps >= 4 pixels on the shorter).
  const int64_t registered = std::max(box_width, box_height) / morph.downsample;
  int levels = 1;
  while (levels < morph.levels && (registered >> levels) >= 8) ++levels;
  morph.levels = levels;
  return morph;
}

// The morph of a label's key-slice maps onto `plan` (StackMorph, then its
// component filter: no component of the label where no key slice has one).
absl::StatusOr<StackedField> MorphLabel(const Volume<float>& maps,
                                        const StackPlan& plan,
                                        int64_t max_voxels,
                                        const ComputeContext& context) {
  INTERSLICE_ASSIGN_OR_RETURN(
      MorphedField morphed,
      StackMorph(maps, plan,
                 LabelMorphOptions(maps.grid.size[0], maps.grid.size[1]),
                 max_voxels, context));
  INTERSLICE_RETURN_IF_ERROR(
      RemoveUnsupportedComponents(morphed.stacked.field,
                                  morphed.stacked.fixed_slices,
                                  MorphOptions().component_margin_mm, context)
          .status());
  return std::move(morphed.stacked);
}

// The validation grid holds only the slices at multiples of g, the
// greatest common divisor of the key gaps (every key slice is one of
// them): g times fewer voxels for the solver than the input grid. For
// the refinement to approximate the same continuous energy as on the
// input grid, its weights are those of a z step g times the input's
// (CurvatureWeights in mm units with the z spacing scaled). Linear
// stacking, the copy and the morph (t measured in output slices) are the
// same on either grid.
int64_t ValidationGridStep(const std::vector<int64_t>& key) {
  int64_t g = 0;
  for (size_t s = 1; s < key.size(); ++s) g = std::gcd(g, key[s] - key[s - 1]);
  return std::max<int64_t>(1, g);
}

// The held-out slices (key indices) of every fold of the validation at m
// times the key gap (n key slices) that are scored, each fold's sorted.
// Each registration costs ~10 ms of ITK overhead whatever the box, and the
// morph of a scored slice needs its own kept gap and the kept gaps on
// either side registered (see MorphHeldOutSlices), so when there are more
// than kMaxHeldOutPerLevel the sample is made of a few runs spread evenly
// over the folds, each run the held-out slices of consecutive kept gaps of
// one fold (at least kRunSlices slices): neighbouring slices of a run share
// their registrations. m = 2: 4 runs of 2 slices (one per gap), 4
// registrations a run; m = 4: 3 runs of one gap's 3 slices, 3 a run.
std::vector<std::vector<size_t>> ScoredHeldOutSlices(size_t n, int m) {
  constexpr size_t kMaxHeldOutPerLevel = 8;
  constexpr size_t kRunSlices = 2;
  // Units: the held-out slices of one kept gap of one fold, in fold order.
  struct HeldGap {
    int fold = 0;
    std::vector<size_t> slices;
  };
  std::vector<HeldGap> held_gaps;
  size_t all_held = 0;
  for (int fold = 0; fold < m; ++fold) {
    bool new_gap = true;
    for (size_t s = 1; s + 1 < n; ++s) {
      if (static_cast<int>(s % m) == fold) {
        new_gap = true;  // a kept key slice ends the gap
        continue;
      }
      ++all_held;
      if (new_gap) held_gaps.push_back({fold, {}});
      held_gaps.back().slices.push_back(s);
      new_gap = false;
    }
  }
  std::vector<std::vector<size_t>> held_of(m);
  if (all_held <= kMaxHeldOutPerLevel) {
    for (const HeldGap& gap : held_gaps) {
      held_of[gap.fold].insert(held_of[gap.fold].end(), gap.slices.begin(),
                               gap.slices.end());
    }
    return held_of;
  }
  const size_t per_gap = (all_held + held_gaps.size() - 1) / held_gaps.size();
  const size_t per_run = std::max(kRunSlices, per_gap);
  const size_t runs = (kMaxHeldOutPerLevel + per_run - 1) / per_run;
  std::vector<bool> taken(held_gaps.size(), false);
  size_t scored = 0;
  for (size_t r = 0; r < runs && scored < kMaxHeldOutPerLevel; ++r) {
    size_t u = (2 * r + 1) * held_gaps.size() / (2 * runs);
    size_t in_run = 0;
    while (u < held_gaps.size() && !taken[u] && in_run < kRunSlices &&
           scored < kMaxHeldOutPerLevel) {
      taken[u] = true;
      for (size_t s : held_gaps[u].slices) {
        if (scored == kMaxHeldOutPerLevel) break;
        held_of[held_gaps[u].fold].push_back(s);
        ++scored;
        ++in_run;
      }
      if (u + 1 == held_gaps.size() ||
          held_gaps[u + 1].fold != held_gaps[u].fold) {
        break;
      }
      ++u;
    }
  }
  for (std::vector<size_t>& fold_slices : held_of) {
    std::sort(fold_slices.begin(), fold_slices.end());
  }
  return held_of;
}

// The key slices (key indices) fold `fold` keeps of n at m times the key
// gap: the first, the last and those s with s mod m = fold.
std::vector<size_t> KeptKeySlices(size_t n, int m, int fold) {
  std::vector<size_t> kept;
  for (size_t s = 0; s < n; ++s) {
    if (s == 0 || s + 1 == n || static_cast<int>(s % m) == fold) {
      kept.push_back(s);
    }
  }
  return kept;
}

// The maps of `count` consecutive kept key slices from kept[first], and
// their plan on the validation grid (output slice 0 at key slice
// kept[first], one output slice per g input slices).
struct KeptStack {
  Volume<float> maps;
  StackPlan plan;
};

KeptStack StackOfKeptSlices(const Volume<float>& maps,
                            const std::vector<int64_t>& key,
                            const std::vector<size_t>& kept, size_t first,
                            size_t count, int64_t g, double spacing_mm) {
  const int64_t bplane = maps.grid.size[0] * maps.grid.size[1];
  KeptStack stack;
  stack.maps.grid = maps.grid;
  stack.maps.grid.size[2] = static_cast<int64_t>(count);
  stack.maps.data.resize(count * bplane);
  stack.plan.factor = 1;
  stack.plan.spacing_mm = spacing_mm;
  for (size_t c = 0; c < count; ++c) {
    const size_t ks = kept[first + c];
    std::copy(maps.data.begin() + ks * bplane,
              maps.data.begin() + (ks + 1) * bplane,
              stack.maps.data.begin() + c * bplane);
    stack.plan.nodes.push_back((key[ks] - key[kept[first]]) / g);
  }
  stack.plan.output_slices = stack.plan.nodes.back() + 1;
  return stack;
}

// The morph of each held-out slice of a fold (its box plane) as the fill
// computes it: on the cubic trajectory through the kept key slices, whose
// gap around the slice takes its Catmull-Rom tangents from the kept gaps on
// either side. So the gaps each scored slice needs (its own and its
// neighbours) are registered, each once: every run of consecutive needed
// gaps is morphed as one stack, which gives a scored slice what the whole
// fold's morph would.
absl::StatusOr<std::vector<std::vector<float>>> MorphHeldOutSlices(
    const Volume<float>& maps, const std::vector<int64_t>& key,
    const std::vector<size_t>& kept, const std::vector<size_t>& held, int64_t g,
    double spacing_mm, const FillOptions& options,
    const ComputeContext& context) {
  const int64_t bplane = maps.grid.size[0] * maps.grid.size[1];
  std::vector<std::vector<float>> morph(held.size());
  const size_t kept_gaps = kept.size() - 1;
  std::vector<size_t> gap_of(held.size());
  std::vector<bool> needed(kept_gaps, false);
  for (size_t h = 0; h < held.size(); ++h) {
    const size_t gap = static_cast<size_t>(
        std::upper_bound(kept.begin(), kept.end(), held[h]) - kept.begin() - 1);
    gap_of[h] = gap;
    for (size_t n = gap == 0 ? 0 : gap - 1;
         n <= std::min(kept_gaps - 1, gap + 1); ++n) {
      needed[n] = true;
    }
  }
  for (size_t first = 0; first < kept_gaps;) {
    if (!needed[first]) {
      ++first;
      continue;
    }
    size_t last = first;  // the run's gaps: first .. last
    while (last + 1 < kept_gaps && needed[last + 1]) ++last;
    const size_t count = last - first + 2;  // its kept key slices
    KeptStack run =
        StackOfKeptSlices(maps, key, kept, first, count, g, spacing_mm);
    INTERSLICE_ASSIGN_OR_RETURN(
        StackedField morphed,
        MorphLabel(run.maps, run.plan, options.max_output_voxels, context));
    for (size_t h = 0; h < held.size(); ++h) {
      if (gap_of[h] < first || gap_of[h] > last) continue;
      const int64_t z = (key[held[h]] - key[kept[first]]) / g;
      morph[h].assign(morphed.field.data.begin() + z * bplane,
                      morphed.field.data.begin() + (z + 1) * bplane);
    }
    first = last + 1;
  }
  return morph;
}

// The refined candidate of a fold: the exact minimiser (kDirect) on the
// validation grid, with the weights of a z step g times the input's.
absl::StatusOr<Volume<float>> RefineOnValidationGrid(
    const StackedField& linear, int64_t g, const Grid& in_grid,
    const SolverOptions& fill_solver, const ComputeContext& context) {
  Volume<float> refined = linear.field;
  SolverOptions solver = fill_solver;
  solver.method = SolverMethod::kDirect;
  if (solver.units == EnergyUnits::kVoxel) {
    refined.grid.spacing = {1, 1, static_cast<double>(g)};
  } else {
    refined.grid.spacing = {in_grid.spacing[0], in_grid.spacing[1],
                            in_grid.spacing[2] * g};
  }
  solver.units = EnergyUnits::kMillimetre;
  INTERSLICE_RETURN_IF_ERROR(
      Solve(refined, linear.fixed_slices, solver, context).status());
  return refined;
}

// Pooled Dice: 2 |A and B| / (|A| + |B|) summed over the held-out
// slices of every fold; per candidate (kCandidates order).
struct DiceTally {
  std::vector<double> both = std::vector<double>(kCandidateCount, 0);
  std::vector<double> predicted = std::vector<double>(kCandidateCount, 0);
  double drawn = 0;
};

// The candidates' fields of one fold on the validation grid (the morph:
// one box plane per held-out slice, empty without auto_morph).
struct FoldCandidates {
  StackedField linear;
  Volume<float> refined;
  Volume<float> copy;
  std::vector<std::vector<float>> morph;
};

// Adds the fold's held-out slices to `tally` (and, with `slice_dice`, each
// slice's own Dice).
void ScoreHeldOutSlices(const LabelVolume& input, int label,
                        const std::vector<int64_t>& key, const PlaneBox& box,
                        const std::vector<size_t>& held, int64_t g,
                        const FoldCandidates& fold, bool with_morph,
                        DiceTally& tally,
                        std::vector<std::vector<double>>* slice_dice) {
  const int64_t bw = box.i1 - box.i0, bh = box.j1 - box.j0;
  const int64_t bplane = bw * bh;
  for (size_t h = 0; h < held.size(); ++h) {
    const size_t s = held[h];
    const int64_t z = (key[s] - key.front()) / g;
    const float* lin = fold.linear.field.data.data() + z * bplane;
    const float* ref = fold.refined.data.data() + z * bplane;
    const float* cpy = fold.copy.data.data() + z * bplane;
    const float* mor = with_morph ? fold.morph[h].data() : nullptr;
    std::vector<double> slice_both(kCandidateCount, 0),
        slice_predicted(kCandidateCount, 0);
    double slice_drawn = 0;
    for (int64_t j = 0; j < bh; ++j) {
      const uint16_t* row = input.data.data() +
                            input.grid.LinearIndex(box.i0, box.j0 + j, key[s]);
      for (int64_t i = 0; i < bw; ++i) {
        const int64_t p = j * bw + i;
        const bool truth = row[i] == label;
        slice_drawn += truth;
        const float values[kCandidateCount] = {
            lin[p], ref[p], mor != nullptr ? mor[p] : -1.0f,
            0.5f * (lin[p] + cpy[p]), cpy[p]};
        for (int c = 0; c < kCandidateCount; ++c) {
          const bool in = values[c] > 0;
          slice_predicted[c] += in;
          slice_both[c] += in && truth;
        }
      }
    }
    tally.drawn += slice_drawn;
    std::vector<double> one(kCandidateCount, 0);
    for (int c = 0; c < kCandidateCount; ++c) {
      tally.predicted[c] += slice_predicted[c];
      tally.both[c] += slice_both[c];
      const double sum = slice_predicted[c] + slice_drawn;
      one[c] = sum > 0 ? 2 * slice_both[c] / sum : 1;
    }
    if (!with_morph) one[static_cast<int>(Candidate::kMorph)] = -1;
    if (slice_dice != nullptr) slice_dice->push_back(std::move(one));
  }
}

// One fold of the validation at m times the key gap: each candidate fills
// the fold's held-out slices `held` from its kept key slices, scored into
// `tally`.
absl::Status ValidateFold(const LabelVolume& input, int label,
                          const std::vector<int64_t>& key, const PlaneBox& box,
                          const Volume<float>& maps, const FillOptions& options,
                          int m, int fold_index,
                          const std::vector<size_t>& held, int64_t g,
                          const ComputeContext& context, DiceTally& tally,
                          std::vector<std::vector<double>>* slice_dice) {
  const bool with_morph = options.auto_morph;
  const double spacing_mm = input.grid.spacing[2];
  const std::vector<size_t> kept = KeptKeySlices(key.size(), m, fold_index);
  FoldCandidates fold;
  {
    KeptStack sub =
        StackOfKeptSlices(maps, key, kept, 0, kept.size(), g, spacing_mm);
    INTERSLICE_ASSIGN_OR_RETURN(
        fold.linear,
        StackLinear(sub.maps, sub.plan, options.max_output_voxels, context));
  }
  if (with_morph) {
    INTERSLICE_ASSIGN_OR_RETURN(
        fold.morph, MorphHeldOutSlices(maps, key, kept, held, g, spacing_mm,
                                       options, context));
  }
  INTERSLICE_ASSIGN_OR_RETURN(fold.refined,
                              RefineOnValidationGrid(fold.linear, g, input.grid,
                                                     options.solver, context));
  NearestFixedCopy(fold.linear.field, fold.linear.fixed_slices, fold.copy);
  ScoreHeldOutSlices(input, label, key, box, held, g, fold, with_morph, tally,
                     slice_dice);
  return absl::OkStatus();
}

// Validation of the candidates for one label at `m` times its key gap: in
// m folds r = 0 .. m-1, the key slices s with s mod m = r (and the first and
// last) are kept, the other inner ones held out; each candidate fills the
// held-out slices from the kept ones (on the grid of the key slices) and is
// compared with the drawn mask there. m = 2 holds out every other key slice
// (each one once, predicted across a gap twice the label's own); m = 4
// keeps every 4th (each inner key slice held out 3 times, at 1/4, 1/2 and
// 3/4 of a gap 4 times the label's own, as drop-k withholds slices). At most
// kMaxHeldOutPerLevel held-out slices are scored, in a few runs spread over
// the folds (ScoredHeldOutSlices); the morph of each is the fill's own morph
// from the fold's kept key slices (the cubic trajectory through its gap, whose
// tangents come from the kept gaps on either side). Returns the Dice
// pooled over the scored slices per candidate (kCandidates order; the
// morph's -1 without auto_morph), or empty when the label has fewer than
// m + 2 key slices (m = 2: 3). With `slice_dice`, also each scored slice's
// own Dice per candidate (kCandidates order; 1 where neither the drawing nor
// the candidate has a pixel; the morph's -1 without auto_morph), for the
// evaluation of selection rules (LabelFillInfo::validation_slice_dice).
absl::StatusOr<std::vector<double>> ValidateCandidates(
    const LabelVolume& input, int label, const std::vector<int64_t>& key,
    const PlaneBox& box, const Volume<float>& maps, const FillOptions& options,
    int m, const ComputeContext& context,
    std::vector<std::vector<double>>* slice_dice = nullptr) {
  const size_t n = key.size();
  const size_t needed = m == 2 ? 3 : static_cast<size_t>(m) + 2;
  if (n < needed) return std::vector<double>();
  const int64_t g = ValidationGridStep(key);
  const bool with_morph = options.auto_morph;
  // The held-out slices of all folds that are scored.
  const std::vector<std::vector<size_t>> held_of = ScoredHeldOutSlices(n, m);
  DiceTally tally;
  for (int fold = 0; fold < m; ++fold) {
    INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
    const std::vector<size_t>& held = held_of[fold];
    if (held.empty()) continue;
    INTERSLICE_RETURN_IF_ERROR(ValidateFold(input, label, key, box, maps,
                                            options, m, fold, held, g, context,
                                            tally, slice_dice));
  }
  std::vector<double> dice(kCandidateCount, 0);
  for (int c = 0; c < kCandidateCount; ++c) {
    const double sum = tally.predicted[c] + tally.drawn;
    dice[c] = sum > 0 ? 2 * tally.both[c] / sum : 1;
  }
  if (!with_morph) dice[static_cast<int>(Candidate::kMorph)] = -1;
  return dice;
}

// The box of the label's drawn pixels on its key slices, grown by the
// margin; counts the key slices where it is drawn (info.drawn_slices) and
// warns of a label drawn on one slice only.
PlaneBox LabelBox(const LabelVolume& input, int label,
                  const std::vector<int64_t>& key, int margin_pixels,
                  LabelFillInfo& info, std::vector<std::string>& warnings) {
  const Grid& in_grid = input.grid;
  const int64_t nx = in_grid.size[0], ny = in_grid.size[1];
  const int64_t plane = in_grid.SliceVoxelCount();
  // The box: drawn pixels on the key slices, grown by the margin.
  PlaneBox box{nx, 0, ny, 0};
  std::vector<bool> drawn_on(key.size(), false);
  for (size_t s = 0; s < key.size(); ++s) {
    const uint16_t* slice = input.data.data() + key[s] * plane;
    for (int64_t j = 0; j < ny; ++j) {
      const uint16_t* row = slice + nx * j;
      for (int64_t i = 0; i < nx; ++i) {
        if (row[i] != label) continue;
        drawn_on[s] = true;
        box.i0 = std::min(box.i0, i);
        box.i1 = std::max(box.i1, i + 1);
        box.j0 = std::min(box.j0, j);
        box.j1 = std::max(box.j1, j + 1);
      }
    }
    if (drawn_on[s]) ++info.drawn_slices;
  }
  if (info.drawn_slices == 1) {
    const int64_t k = key[std::find(drawn_on.begin(), drawn_on.end(), true) -
                          drawn_on.begin()];
    warnings.push_back(absl::StrFormat(
        "label %d is drawn on slice %d only: kept as drawn%s", label, k,
        key.size() > 1 ? ", closing off toward the neighbouring key slices"
                       : ""));
  }
  const int64_t m = margin_pixels;
  box.i0 = std::max<int64_t>(0, box.i0 - m);
  box.j0 = std::max<int64_t>(0, box.j0 - m);
  box.i1 = std::min(nx, box.i1 + m);
  box.j1 = std::min(ny, box.j1 + m);
  return box;
}

// The score that predicts the Dice at the label's own gap g: at the
// doubled gap, or (kGapTrend, when the label has enough key slices)
// extrapolated from the quadrupled and the doubled gap by a power law
// of the error e = 1 - Dice in the gap, e(g) = e(2g) 2^-p with
// e(4g) = e(2g) 2^p, p clamped to [0, 2]: halving the gap never makes
// a candidate worse, nor better than an interpolation error of second
// order (a smooth surface between key slices) would.
std::vector<double> PredictedScores(const std::vector<double>& dice2,
                                    const std::vector<double>& dice4) {
  std::vector<double> score = dice2;
  if (!dice4.empty()) {
    for (int c = 0; c < kCandidateCount; ++c) {
      if (dice2[c] < 0) continue;
      const double e2 = 1 - dice2[c], e4 = 1 - dice4[c];
      const double p =
          e2 <= 0 || e4 <= e2 ? 0.0 : std::min(2.0, std::log2(e4 / e2));
      score[c] = 1 - e2 * std::exp2(-p);
    }
  }
  return score;
}

// The candidate with the highest score (ties: kCandidates order).
Candidate BestScoringCandidate(const std::vector<double>& dice2,
                               const std::vector<double>& score,
                               bool auto_morph) {
  Candidate chosen = Candidate::kLinear;
  double best_score = -1e300, best_dice2 = 0;
  for (int c = 0; c < kCandidateCount; ++c) {
    if (dice2[c] < 0) continue;  // not a candidate (auto_morph off)
    best_dice2 = std::max(best_dice2, dice2[c]);
    if (score[c] > best_score) {
      best_score = score[c];
      chosen = kCandidates[c];
    }
  }
  // No candidate predicts anything at the doubled gap (a thin or small
  // structure that moves more than its size over two key gaps: nothing
  // overlaps): the validation cannot rank them. As for a label drawn on
  // two key slices, the morph, which follows the motion (measured on the
  // ribs of the TotalSegmentator series, docs/eval/segmentations.md:
  // morph Dice .54-.83 where linear stacking gave .11-.35), else the
  // copy.
  if (best_dice2 < kUninformativeDice) {
    chosen = auto_morph ? Candidate::kMorph : Candidate::kCopy;
  }
  return chosen;
}

// The validation's Dice and scores into `info`, in the report's candidate
// order.
void RecordValidation(const std::vector<double>& dice2,
                      const std::vector<double>& dice4,
                      const std::vector<double>& score,
                      const std::vector<std::vector<double>>& slices2,
                      const std::vector<std::vector<double>>& slices4,
                      LabelFillInfo& info) {
  static constexpr Candidate kReport[] = {
      Candidate::kCopy, Candidate::kLinear, Candidate::kBlend,
      Candidate::kRefined, Candidate::kMorph};
  for (Candidate c : kReport) {
    const int index = static_cast<int>(c);
    info.validation_dice.emplace_back(CandidateName(c), dice2[index]);
    if (!dice4.empty()) {
      info.validation_dice_4g.emplace_back(CandidateName(c), dice4[index]);
    }
    info.validation_score.emplace_back(CandidateName(c), score[index]);
  }
  // Each scored slice's Dice, in the report's candidate order.
  for (const auto& [level, all] :
       {std::pair{&info.validation_slice_dice, &slices2},
        std::pair{&info.validation_slice_dice_4g, &slices4}}) {
    for (const std::vector<double>& one : *all) {
      std::vector<double> ordered;
      for (Candidate c : kReport) {
        ordered.push_back(one[static_cast<int>(c)]);
      }
      level->push_back(std::move(ordered));
    }
  }
}

// FillMethod::kAuto with enough drawn key slices: the candidate the
// validation at the doubled (and with kGapTrend the quadrupled) gap scores
// best; linear when the label has too few key slices to validate.
absl::StatusOr<Candidate> ChooseByValidation(
    const LabelVolume& input, int label, const std::vector<int64_t>& key,
    const PlaneBox& box, const Volume<float>& maps, const FillOptions& options,
    const ComputeContext& context, LabelFillInfo& info) {
  std::vector<std::vector<double>> slices2, slices4;
  INTERSLICE_ASSIGN_OR_RETURN(
      std::vector<double> dice2,
      ValidateCandidates(input, label, key, box, maps, options, 2, context,
                         &slices2));
  std::vector<double> dice4;
  if (options.selection == AutoSelection::kGapTrend && !dice2.empty()) {
    INTERSLICE_ASSIGN_OR_RETURN(
        dice4, ValidateCandidates(input, label, key, box, maps, options, 4,
                                  context, &slices4));
  }
  if (dice2.empty()) return Candidate::kLinear;
  const std::vector<double> score = PredictedScores(dice2, dice4);
  const Candidate chosen =
      BestScoringCandidate(dice2, score, options.auto_morph);
  RecordValidation(dice2, dice4, score, slices2, slices4, info);
  return chosen;
}

// Which candidate fills the label (FillMethod::kAuto; kRefined for
// kSolver) and the solver method that refines it (kLinear: none).
struct LabelMethod {
  Candidate chosen = Candidate::kRefined;
  SolverMethod refine = SolverMethod::kLinear;
};

absl::StatusOr<LabelMethod> ChooseLabelMethod(
    const LabelVolume& input, int label, const std::vector<int64_t>& key,
    const PlaneBox& box, const Volume<float>& maps, const FillOptions& options,
    const ComputeContext& context, LabelFillInfo& info) {
  LabelMethod method;
  method.refine = options.solver.method;
  if (options.method == FillMethod::kAuto && info.drawn_slices <= 2) {
    // Too few drawn key slices for a validation that says anything: the
    // held-out slice would be predicted from a drawn-and-empty end. Measured
    // on the real series of docs/eval/segmentations.md (labels drawn on one
    // key slice: copy Dice .50 against <= .30 for any interpolation; on two:
    // the morph or the refinement best, copy and linear behind).
    method.chosen = info.drawn_slices <= 1 ? Candidate::kCopy
                    : options.auto_morph   ? Candidate::kMorph
                                           : Candidate::kRefined;
    method.refine = method.chosen == Candidate::kRefined
                        ? SolverMethod::kDirect
                        : SolverMethod::kLinear;
  } else if (options.method == FillMethod::kAuto) {
    INTERSLICE_ASSIGN_OR_RETURN(
        method.chosen, ChooseByValidation(input, label, key, box, maps, options,
                                          context, info));
    method.refine = method.chosen == Candidate::kRefined
                        ? SolverMethod::kDirect
                        : SolverMethod::kLinear;
  }
  return method;
}

// The refinement of the stacked field (or, for the morph and linear
// stacking, the solver result that says there was none) into info.solver.
absl::Status RefineLabelField(StackedField& stacked, bool morph,
                              SolverMethod refine, const FillOptions& options,
                              const ComputeContext& context,
                              LabelFillInfo& info) {
  const bool any_free =
      std::any_of(stacked.fixed_slices.begin(), stacked.fixed_slices.end(),
                  [](uint8_t f) { return f == 0; });
  if (morph) {
    info.solver.method = SolverMethod::kMorph;
    info.solver.relative_residual = 1;
  } else if (refine != SolverMethod::kLinear && any_free) {
    SolverOptions solver = options.solver;
    solver.method = refine;
    INTERSLICE_ASSIGN_OR_RETURN(
        info.solver,
        Solve(stacked.field, stacked.fixed_slices, solver, context));
  } else {
    info.solver.method = SolverMethod::kLinear;
    info.solver.relative_residual = 1;
  }
  return absl::OkStatus();
}

// The copy and blend candidates from the linearly stacked field.
void ApplyCopyOrBlend(Candidate chosen, StackedField& stacked) {
  if (chosen != Candidate::kCopy && chosen != Candidate::kBlend) return;
  Volume<float> copy;
  NearestFixedCopy(stacked.field, stacked.fixed_slices, copy);
  if (chosen == Candidate::kBlend) {
    for (size_t v = 0; v < copy.data.size(); ++v) {
      copy.data[v] = 0.5f * (copy.data[v] + stacked.field.data[v]);
    }
  }
  stacked.field.data = std::move(copy.data);
}

}  // namespace

absl::Status ComputeLabelField(const LabelVolume& input, const Grid& out_grid,
                               int factor, const FillOptions& options,
                               const ComputeContext& context, LabelJob& job) {
  const int label = job.label;
  LabelFillInfo& info = job.info;
  info.label = label;
  info.key_slices = job.key;
  const std::vector<int64_t>& key = job.key;
  if (key.empty()) {
    job.warnings.push_back(absl::StrFormat(
        "label %d is not drawn on any key slice: left out", label));
    return absl::OkStatus();
  }
  const PlaneBox box =
      LabelBox(input, label, key, options.margin_pixels, info, job.warnings);

  INTERSLICE_ASSIGN_OR_RETURN(
      Volume<float> maps,
      KeySliceDistanceMaps(input, label, key, box, options, context));

  // Which candidate (FillMethod::kAuto) or the solver's method.
  INTERSLICE_ASSIGN_OR_RETURN(
      const LabelMethod method,
      ChooseLabelMethod(input, label, key, box, maps, options, context, info));
  // (A label on one key slice has no gap to register: stacked as linear.)
  const bool morph =
      key.size() >= 2 && (options.method == FillMethod::kAuto
                              ? method.chosen == Candidate::kMorph
                              : options.solver.method == SolverMethod::kMorph);

  StackPlan plan;
  plan.factor = factor;
  plan.spacing_mm = out_grid.spacing[2];
  for (int64_t k : key) plan.nodes.push_back((k - key.front()) * factor);
  plan.output_slices = plan.nodes.back() + 1;
  StackedField stacked;
  if (morph) {
    INTERSLICE_ASSIGN_OR_RETURN(
        stacked, MorphLabel(maps, plan, options.max_output_voxels, context));
  } else {
    INTERSLICE_ASSIGN_OR_RETURN(
        stacked, StackLinear(maps, plan, options.max_output_voxels, context));
  }
  maps = Volume<float>();
  INTERSLICE_RETURN_IF_ERROR(
      RefineLabelField(stacked, morph, method.refine, options, context, info));
  if (options.method == FillMethod::kAuto) {
    info.method = CandidateName(method.chosen);
    ApplyCopyOrBlend(method.chosen, stacked);
  } else {
    info.method = std::string(SolverMethodName(options.solver.method));
  }
  job.box = box;
  job.z0 = key.front() * factor;
  job.z1 = job.z0 + plan.output_slices;
  job.field = std::move(stacked.field);
  return absl::OkStatus();
}

}  // namespace interslice::label_fill_internal

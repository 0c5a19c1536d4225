// Private to core/morph: what the two phases of MorphIntensity
// (intensity_morph.h) share. intensity_morph.cc validates the inputs,
// registers every gap (phase 1), places the output slices and sums the
// statistics; intensity_morph_write.cc writes the inserted slices of one gap
// (phase 2).
#ifndef INTERSLICE_CORE_MORPH_INTENSITY_MORPH_INTERNAL_H_
#define INTERSLICE_CORE_MORPH_INTENSITY_MORPH_INTERNAL_H_

#include <algorithm>
#include <cstdint>
#include <optional>
#include <vector>

#include "absl/status/statusor.h"
#include "core/geometry/volume.h"
#include "core/morph/intensity_morph.h"
#include "core/morph/morph.h"

namespace interslice::intensity_morph_internal {

inline double Ramp(double x) { return std::clamp(x, 0.0, 1.0); }

// Gaussian smoothing (ITK's recursive Gaussian, sigma in pixels) of an
// mx*my plane.
absl::StatusOr<std::vector<float>> Smooth(const std::vector<float>& in,
                                          int64_t mx, int64_t my, double sigma);

// The key slices as both phases read them.
struct KeySlices {
  const float* values = nullptr;  // slice s at values + s * plane
  int64_t nx = 0, ny = 0, plane = 0;
  int64_t gaps = 0;            // slices - 1
  std::vector<double> gap_mm;  // gap_mm[s]: z_s+1 - z_s
  std::optional<float> padding;

  const float* Slice(int64_t s) const { return values + s * plane; }
};

// The registration lattice: the key slices' pixels downsampled by d (the
// demons' downsample), mx x my coarse pixels.
struct RegistrationLattice {
  int d = 1;
  int64_t mx = 0, my = 0;
};

// What phase 1 keeps of a gap: coarse forward and backward fields and the
// fallback weight on the registration lattice.
struct GapRegistration {
  bool registered = false;
  CoarseDisplacement forward, backward;
  std::vector<float> weight;  // mx*my, in [0, 1]
  // mx*my: 1 where the key slices differ (r_lin >= gain_high); empty when
  // the gap was not registered (everything counts) or not asked to be.
  std::vector<uint8_t> changing;
  double displacement_sum_mm = 0, displacement_max_mm = 0;
  int64_t coarse_pixels = 0;
  // The noise of the gap's key slices (PairNoiseScale: of their
  // difference), modality units.
  double noise_sigma = 0;
  // The pair check's tolerance per unit of pair_tolerance_noise.
  double pair_unit = 0;
};

// Per output slice: the key slice it copies (a >= 0, b < 0), the gap it
// lies in (a = s, b = s + 1, t), or outside (a < 0).
struct Placement {
  int64_t a = -1, b = -1;
  double t = 0;
};

// What phase 2 counts in a gap (IntensityMorphStatistics).
struct GapCounts {
  int64_t inserted = 0;
  int64_t fallbacks = 0;
};

// Phase 2 for gap s: writes the output slices `slices_in_gap` (indices into
// `out` and `place`) from the gap's registration and its neighbours'
// (`reg`, every gap's), and returns what the statistics count there. Errors:
// ITK's smoothing of the pair check.
absl::StatusOr<GapCounts> WriteGapSlices(
    const KeySlices& keys, const std::vector<GapRegistration>& reg, int64_t s,
    const std::vector<int64_t>& slices_in_gap,
    const std::vector<Placement>& place, const RegistrationLattice& lattice,
    const IntensityMorphOptions& options, Volume<float>& out);

}  // namespace interslice::intensity_morph_internal

#endif  // INTERSLICE_CORE_MORPH_INTENSITY_MORPH_INTERNAL_H_

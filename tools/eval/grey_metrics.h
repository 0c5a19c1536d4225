// Grey-value quality metrics of the intensity harness (issue 23,
// interslice_grey_eval): a reconstruction against the withheld slices of a
// real series, on one grid. Values in modality units (HU for CT).
//
// - RMSE and PSNR over a mask: PSNR = 20 log10(peak / RMSE), peak = the
//   dynamic range the caller gives (the harness: the truth's range inside the
//   body on the evaluated slices).
// - SSIM: the structural similarity index of Wang, Bovik, Sheikh & Simoncelli
//   2004 ("Image quality assessment: from error visibility to structural
//   similarity", IEEE TIP 13(4)), eq. (13), with their settings: an 11x11
//   circular-symmetric Gaussian window of sigma 1.5 pixels (normalised),
//   K1 = 0.01, K2 = 0.03, C1 = (K1 L)^2, C2 = (K2 L)^2, L = the dynamic
//   range. Computed per 2D slice at every pixel whose whole window lies in the
//   slice ("valid"), and averaged over the pixels of a mask (mean SSIM).
//   ITK 5.2 has no SSIM filter.
// - Edge rise distance: the 10-90% rise distance (mm) of a profile across an
//   edge: from the crossing of the profile's 50% level nearest to the centre,
//   walking down to its 10% level and up to its 90% level (levels between
//   the profile's minimum on the low side and maximum on the high side). The
//   profile runs along a given direction through a given point, sampled by
//   trilinear interpolation in physical mm.
#ifndef INTERSLICE_TOOLS_EVAL_GREY_METRICS_H_
#define INTERSLICE_TOOLS_EVAL_GREY_METRICS_H_

#include <cstdint>
#include <optional>
#include <vector>

#include "core/geometry/volume.h"

namespace interslice::eval {

struct ErrorScores {
  double rmse = 0;
  double psnr = 0;  // dB
  int64_t voxels = 0;
};

// Over the voxels with mask != 0 (same grid); voxels == 0 gives rmse 0.
ErrorScores ErrorOnMask(const Volume<float>& result, const Volume<float>& truth,
                        const std::vector<uint8_t>& mask, double peak);

// Mean SSIM of slice k of `a` against slice k of `b` over the pixels of the
// slice's mask (nx*ny, nonzero = counted) whose 11x11 window lies inside the
// slice. Adds the SSIM values to *sum and their number to *count.
void AccumulateSsim(const float* a, const float* b, int64_t nx, int64_t ny,
                    const uint8_t* mask, double dynamic_range, double* sum,
                    int64_t* count);

// Trilinear sample of `v` at LPS point `p` (clamped to the grid).
double SampleTrilinear(const Volume<float>& v, const Vec3& p);

// The 10-90% rise distance (mm) of `v` along unit direction `n` (LPS) through
// point `p`, profile from -half_length to +half_length mm in steps of
// step_mm; nullopt when the profile has no rise (high side not above the low
// side) or a level is not reached within the profile.
std::optional<double> RiseDistance(const Volume<float>& v, const Vec3& p,
                                   const Vec3& n, double half_length,
                                   double step_mm);

}  // namespace interslice::eval

#endif  // INTERSLICE_TOOLS_EVAL_GREY_METRICS_H_

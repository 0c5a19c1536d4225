// Quality metrics of the evaluation harness (DESIGN.md section 5), on masks
// and fields that share one grid. All distances in mm.
//
// Definitions (also in the report):
// - Dice: ITK LabelOverlapMeasuresImageFilter on the sub-volume made of the
//   evaluated (withheld) slices only, label 1 = object.
// - Surface distances: the boundary voxels of a mask are its object voxels
//   with a face neighbour (6-neighbourhood; outside the grid counts as
//   background) in the background. ITK SignedMaurerDistanceMapImageFilter
//   (image spacing, mm) of each full 3D mask gives the distance from every
//   voxel to that mask's boundary. Boundary voxels of the reconstruction that
//   lie on evaluated slices are sampled in the ground truth's map and vice
//   versa; HD95 is the 95th percentile of the pooled symmetric set of these
//   distances (as MedPy's hd95), MSD their mean, HDmax their maximum (= the
//   symmetric Hausdorff distance restricted to the evaluated slices).
//   Distances are 3D, so a cross-section missing on one slice is measured to
//   the nearest surface on neighbouring slices, not infinite.
// - Crease index: mean |f_zz| (second difference along z, per voxel step)
//   over voxels with |f| <= near_mm on original slices, divided by the same
//   on inserted slices (excluding the first and last slice). Linear stacking
//   has f_zz == 0 on inserted slices: its index is reported as infinity.
// - Components: ITK ConnectedComponentImageFilter, face connectivity.
#ifndef INTERSLICE_TOOLS_EVAL_METRICS_H_
#define INTERSLICE_TOOLS_EVAL_METRICS_H_

#include <cstdint>
#include <vector>

#include "core/geometry/volume.h"

namespace interslice::eval {

using Mask = Volume<uint8_t>;

// mask = (value >= level) on the same grid.
Mask Threshold(const Volume<float>& volume, float level);

// Dice of label 1 on the slices k with slices[k] != 0 (ITK filter).
double DiceOnSlices(const Mask& a, const Mask& b,
                    const std::vector<uint8_t>& slices);

struct SurfaceDistances {
  double hd95 = -1, hdmax = -1, msd = -1;  // mm; -1 if undefined
  int64_t samples = 0;
};
SurfaceDistances SurfaceDistancesOnSlices(const Mask& reconstruction,
                                          const Mask& truth,
                                          const std::vector<uint8_t>& slices);

// As above, with a precomputed |distance to truth's boundary| map (mm).
Volume<float> BoundaryDistanceMap(const Mask& mask);
SurfaceDistances SurfaceDistancesOnSlices(
    const Mask& reconstruction, const Volume<float>& reconstruction_map,
    const Mask& truth, const Volume<float>& truth_map,
    const std::vector<uint8_t>& slices);

double CreaseIndex(const Volume<float>& field,
                   const std::vector<uint8_t>& fixed_slices,
                   double near_mm = 2.0);

struct Components {
  int64_t count = 0;        // all face-connected components
  int64_t count_ge100 = 0;  // components of >= 100 voxels
  int64_t largest = 0;      // voxels in the largest one
};
Components CountComponents(const Mask& mask);
// Components of the sub-volume of slices [k0, k1).
Components CountComponentsInSlab(const Mask& mask, int64_t k0, int64_t k1);

// Sets the number of threads ITK filters use (0 = leave ITK's default).
void SetItkThreads(int threads);

}  // namespace interslice::eval

#endif  // INTERSLICE_TOOLS_EVAL_METRICS_H_

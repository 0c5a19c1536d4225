// Internal to core/ (core/surface, core/preview): the narrow-band OpenVDB
// level set of a dense field, shared by the mesher (ExtractSurface) and the
// ray-traced 3D preview, so that both see exactly the same surface. It
// includes OpenVDB: include it only from .cc files.
#ifndef INTERSLICE_CORE_SURFACE_LEVEL_SET_H_
#define INTERSLICE_CORE_SURFACE_LEVEL_SET_H_

#include <openvdb/openvdb.h>

#include "core/geometry/volume.h"

namespace interslice::surface_internal {

// openvdb::initialize(), once per process.
void InitializeOpenVdb();

// The index -> LPS mm map of `grid` as an OpenVDB transform.
openvdb::math::Transform::Ptr MakeTransform(const Grid& grid);

// `field` (inside where field >= isovalue) as an OpenVDB level set
// (negative inside, GRID_LEVEL_SET, background = the largest spacing, the
// transform of MakeTransform): leaves only where the surface can pass,
// holding the dense samples there; inside leaves are inactive tiles of
// -background; a one-voxel shell outside the grid is outside, so shapes cut
// by the grid boundary close there. Samples within 1e-3 voxel of the
// isovalue are moved to 1e-3 voxel on their own side. The field must be
// valid (finite values, data size = voxel count). Runs tbb::parallel_for in
// the caller's arena; the result does not depend on the thread count.
openvdb::FloatGrid::Ptr MakeLevelSet(const Volume<float>& field,
                                     float isovalue);

}  // namespace interslice::surface_internal

#endif  // INTERSLICE_CORE_SURFACE_LEVEL_SET_H_

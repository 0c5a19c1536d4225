// The zero level set of a refined distance field as a triangle mesh
// (OpenVDB volumeToMesh), and mesh writers (binary STL, PLY, OBJ).
//
// Field convention: positive inside, negative outside, units mm (any
// consistent unit works; only the sign and linear interpolation matter).
// Voxels outside the grid count as outside, so a shape cut by the grid
// boundary is closed there and the mesh is always watertight.
//
// Mesh convention: vertices in DICOM patient coordinates (LPS, mm) through
// the field's grid (origin, spacing, direction); triangles wound
// counter-clockwise seen from outside, so normals (right-hand rule) point
// out of the object.
#ifndef INTERSLICE_CORE_SURFACE_SURFACE_H_
#define INTERSLICE_CORE_SURFACE_SURFACE_H_

#include <array>
#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"

namespace interslice {

struct Mesh {
  std::vector<std::array<float, 3>> vertices;      // LPS mm
  std::vector<std::array<uint32_t, 3>> triangles;  // outward (CCW)
};

struct SurfaceOptions {
  double isovalue = 0;  // level of the field to extract
  // OpenVDB adaptivity in [0, 1]: 0 keeps every marching-cubes polygon;
  // larger values merge flat regions into fewer, larger triangles.
  double adaptivity = 0;
};

// INVALID_ARGUMENT for an empty/invalid grid or adaptivity outside [0, 1].
// A field with no zero crossing gives an empty mesh (not an error).
absl::StatusOr<Mesh> ExtractSurface(const Volume<float>& field,
                                    const SurfaceOptions& options,
                                    const ComputeContext& context);

// Writers. Files are written in full or not at all (temporary + rename);
// errors name the path. Binary little-endian STL and PLY; OBJ is text.
absl::Status WriteStl(const Mesh& mesh, const std::string& path);
absl::Status WritePly(const Mesh& mesh, const std::string& path);
absl::Status WriteObj(const Mesh& mesh, const std::string& path);
// Picks the writer from the extension (.stl, .ply, .obj).
absl::Status WriteMesh(const Mesh& mesh, const std::string& path);

}  // namespace interslice

#endif  // INTERSLICE_CORE_SURFACE_SURFACE_H_

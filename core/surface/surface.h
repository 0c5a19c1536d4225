// The zero level set of a refined distance field as a triangle mesh
// (OpenVDB volumeToMesh), its simplification to a size budget
// (meshoptimizer), and mesh writers (binary STL, PLY, OBJ).
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

// How far a simplified mesh (ExtractSurface with adaptivity > 0) lies from
// the reference mesh of the same field (adaptivity 0), mm.
struct MeshDeviation {
  // Largest and mean distance from the simplified mesh's sample points (its
  // vertices, edge midpoints and triangle centroids) to the reference
  // surface: a one-sided Hausdorff distance sampled at those points.
  double max_mm = 0;
  double mean_mm = 0;
  int64_t samples = 0;
  // The distance grid's voxel size and band (see MeasureMeshDeviation), and
  // the samples found at or beyond the band: their distance is only known
  // to be at least band_mm (max_mm is then band_mm, a lower bound).
  double resolution_mm = 0;
  double band_mm = 0;
  int64_t beyond_band = 0;
};

// The distances are exact point-to-triangle distances of the reference at
// the voxel centres of an OpenVDB unsigned distance grid of voxel
// `resolution_mm` (tools::meshToUnsignedDistanceField), trilinearly
// interpolated at each sample: within about resolution_mm / 2 of the true
// distance, erring high next to the surface (the distance is convex there).
// The grid covers the band within max(2 mm, 8 voxels) of the reference;
// samples farther away are counted in beyond_band.
// INVALID_ARGUMENT for resolution_mm <= 0 or an empty reference with a
// non-empty simplified mesh; an empty simplified mesh gives zeros.
// Cancellation: polled before and after the distance grid.
absl::StatusOr<MeshDeviation> MeasureMeshDeviation(
    const Mesh& simplified, const Mesh& reference, double resolution_mm,
    const ComputeContext& context);

// Mesh simplification for a size budget (the Encapsulated STL a PACS takes):
// quadric edge collapse (Garland & Heckbert, "Surface Simplification Using
// Quadric Error Metrics", SIGGRAPH 1997) as meshoptimizer implements it
// (zeux/meshoptimizer 0.18, meshopt_simplify: edges collapse cheapest first,
// collapses that would flip a triangle are refused, vertices on open borders
// stay on their border).
struct SimplifyOptions {
  // Stop once the mesh has at most this many triangles; 0: no count target
  // (then only max_error_mm stops it).
  int64_t max_triangles = 0;
  // Never make a collapse whose quadric error estimate exceeds this, mm;
  // 0: no error bound (the count target alone decides). With both set, the
  // first one reached stops it, so the result can keep more than
  // max_triangles.
  double max_error_mm = 0;
};

struct SimplifiedMesh {
  // Compacted: only the vertices the triangles use, in first-use order
  // (meshopt_optimizeVertexFetch). Winding as given (outward stays outward).
  Mesh mesh;
  // meshoptimizer's resulting error, converted to mm (relative error times
  // meshopt_simplifyScale, the mesh's extent): the square root of the
  // largest quadric error of a collapse made, i.e. an estimate of how far a
  // moved vertex lies from the planes of the triangles it replaced. It is an
  // estimate, not a guaranteed Hausdorff bound: points inside new triangles
  // (not only vertices) and planes merged into one quadric can lie farther.
  // MeasureMeshDeviation measures the actual distance. 0 when nothing was
  // collapsed.
  double error_mm = 0;
  int64_t triangles_before = 0;
  int64_t triangles_after = 0;
};

// Topology: meshoptimizer collapses only edges whose collapse keeps the
// neighbourhood manifold as it classifies it (interior edges of a closed
// mesh stay interior); it does not remove small closed components once they
// cannot shrink further, so max_triangles may not be reached (the result
// then says triangles_after > max_triangles). A closed, consistently
// oriented input (ExtractSurface's) gives a closed, consistently oriented
// output (tests/core/surface/simplify_test.cc checks it on spheres).
// The input is used as indexed: vertices shared by index, as ExtractSurface
// gives them (duplicate positions are welded by meshoptimizer's position
// remap, not by us).
// A mesh already within max_triangles, or options with neither set, give
// the mesh as is (compacted, error 0).
// INVALID_ARGUMENT for a negative max_triangles, a negative or non-finite
// max_error_mm, a triangle index out of range, or non-finite vertices.
// Runs on one thread (meshoptimizer is serial); cancellation is polled
// before and after the simplification (which cannot be interrupted: 2-7 s
// for the CT phantom's 2.7 million triangles on a loaded 2-core machine).
absl::StatusOr<SimplifiedMesh> SimplifyMesh(const Mesh& mesh,
                                            const SimplifyOptions& options,
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

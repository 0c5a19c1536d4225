// SimplifyMesh: meshoptimizer's quadric edge collapse (see surface.h).
#include <meshoptimizer.h>

#include <array>
#include <cmath>
#include <cstdint>
#include <vector>

#include "absl/strings/str_cat.h"
#include "core/common/status_macros.h"
#include "core/surface/surface.h"

namespace interslice {
namespace {

// meshoptimizer reads our arrays in place: three packed floats per vertex
// and three packed indices per triangle.
static_assert(sizeof(std::array<float, 3>) == 3 * sizeof(float));
static_assert(sizeof(std::array<uint32_t, 3>) == 3 * sizeof(uint32_t));

absl::Status ValidateForSimplify(const Mesh& mesh,
                                 const SimplifyOptions& options) {
  if (options.max_triangles < 0) {
    return absl::InvalidArgumentError(
        "mesh simplification: max_triangles must be >= 0");
  }
  if (!(options.max_error_mm >= 0) || !std::isfinite(options.max_error_mm)) {
    return absl::InvalidArgumentError(
        "mesh simplification: max_error_mm must be a finite number >= 0");
  }
  for (const auto& v : mesh.vertices) {
    if (!std::isfinite(v[0]) || !std::isfinite(v[1]) || !std::isfinite(v[2])) {
      return absl::InvalidArgumentError(
          "mesh simplification: a vertex is not finite");
    }
  }
  for (const auto& t : mesh.triangles) {
    for (uint32_t index : t) {
      if (index >= mesh.vertices.size()) {
        return absl::InvalidArgumentError(absl::StrCat(
            "mesh simplification: triangle index ", index, " is out of range (",
            mesh.vertices.size(), " vertices)"));
      }
    }
  }
  return absl::OkStatus();
}

// Keeps only the vertices `indices` use, in first-use order, and rewrites
// the indices (meshopt_optimizeVertexFetch).
Mesh Compacted(const Mesh& mesh, std::vector<uint32_t>& indices) {
  Mesh out;
  out.vertices.resize(mesh.vertices.size());
  const size_t used = meshopt_optimizeVertexFetch(
      out.vertices.data(), indices.data(), indices.size(), mesh.vertices.data(),
      mesh.vertices.size(), sizeof(std::array<float, 3>));
  out.vertices.resize(used);
  out.vertices.shrink_to_fit();
  out.triangles.resize(indices.size() / 3);
  for (size_t t = 0; t < out.triangles.size(); ++t) {
    out.triangles[t] = {indices[3 * t], indices[3 * t + 1], indices[3 * t + 2]};
  }
  return out;
}

}  // namespace

absl::StatusOr<SimplifiedMesh> SimplifyMesh(const Mesh& mesh,
                                            const SimplifyOptions& options,
                                            const ComputeContext& context) {
  INTERSLICE_RETURN_IF_ERROR(ValidateForSimplify(mesh, options));
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  SimplifiedMesh result;
  const size_t triangle_count = mesh.triangles.size();
  result.triangles_before = static_cast<int64_t>(triangle_count);
  const uint32_t* input_indices =
      triangle_count == 0 ? nullptr : mesh.triangles.front().data();
  std::vector<uint32_t> indices(input_indices,
                                input_indices + 3 * triangle_count);
  const bool count_reached =
      options.max_triangles > 0 &&
      static_cast<int64_t>(triangle_count) <= options.max_triangles;
  const bool nothing_asked =
      options.max_triangles == 0 && options.max_error_mm == 0;
  if (triangle_count == 0 || count_reached || nothing_asked) {
    result.mesh = Compacted(mesh, indices);
    result.triangles_after = result.triangles_before;
    return result;
  }

  const float* positions = mesh.vertices.front().data();
  const size_t stride = sizeof(std::array<float, 3>);
  // meshoptimizer works in errors relative to the mesh's extent; this
  // factor converts both ways (meshoptimizer.h, meshopt_simplifyScale).
  const double scale =
      meshopt_simplifyScale(positions, mesh.vertices.size(), stride);
  const size_t target_index_count =
      options.max_triangles == 0
          ? 0
          : 3 * static_cast<size_t>(options.max_triangles);
  // No error bound: far above any relative error (errors are relative to
  // an extent of 1), and finite when meshoptimizer squares it.
  constexpr float kUnbounded = 1e10f;
  const float target_error =
      options.max_error_mm == 0 || !(scale > 0)
          ? kUnbounded
          : static_cast<float>(options.max_error_mm / scale);
  float relative_error = 0;
  std::vector<uint32_t> simplified(indices.size());
  const size_t index_count = meshopt_simplify(
      simplified.data(), indices.data(), indices.size(), positions,
      mesh.vertices.size(), stride, target_index_count, target_error,
      /*options=*/0, &relative_error);
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  simplified.resize(index_count);
  result.mesh = Compacted(mesh, simplified);
  result.error_mm = static_cast<double>(relative_error) * scale;
  result.triangles_after = static_cast<int64_t>(result.mesh.triangles.size());
  return result;
}

}  // namespace interslice

#include "core/surface/surface.h"

#include <openvdb/openvdb.h>
#include <openvdb/tools/Interpolation.h>
#include <openvdb/tools/MeshToVolume.h>
#include <openvdb/tools/VolumeToMesh.h>
#include <tbb/task_arena.h>

#include <algorithm>
#include <bit>
#include <charconv>
#include <cmath>
#include <cstring>
#include <exception>
#include <filesystem>
#include <limits>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/surface/atomic_file.h"
#include "core/surface/level_set.h"

namespace interslice {
namespace {

// OpenVDB's volumeToMesh winds its polygons clockwise seen from outside
// (normals by the right-hand rule point into the object) when the
// index-to-world map preserves orientation. Checked by the outward tests in
// tests/core/surface/surface_test.cc (signed volume > 0 after our flip).
constexpr bool kOpenVdbWindsClockwise = true;

// Determinant of direction * diag(spacing): negative for a mirrored grid.
double IndexToPhysicalDeterminant(const Grid& grid) {
  const Mat3& d = grid.direction;
  const double det = d[0] * (d[4] * d[8] - d[5] * d[7]) -
                     d[1] * (d[3] * d[8] - d[5] * d[6]) +
                     d[2] * (d[3] * d[7] - d[4] * d[6]);
  return det * grid.spacing[0] * grid.spacing[1] * grid.spacing[2];
}

absl::Status ValidateField(const Volume<float>& field,
                           const SurfaceOptions& options) {
  INTERSLICE_RETURN_IF_ERROR(field.grid.Validate());
  if (static_cast<int64_t>(field.data.size()) != field.grid.VoxelCount()) {
    return absl::InvalidArgumentError(
        absl::StrFormat("field holds %d values but its grid has %d voxels",
                        field.data.size(), field.grid.VoxelCount()));
  }
  constexpr int64_t kMaxAxis = std::numeric_limits<int32_t>::max() / 2;
  for (int a = 0; a < 3; ++a) {
    if (field.grid.size[a] > kMaxAxis) {
      return absl::InvalidArgumentError(
          absl::StrCat("grid size along axis ", a, " is too large"));
    }
  }
  if (!(options.adaptivity >= 0 && options.adaptivity <= 1)) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "surface adaptivity is %g; it must be in [0, 1]", options.adaptivity));
  }
  if (!std::isfinite(options.isovalue)) {
    return absl::InvalidArgumentError("surface isovalue is not finite");
  }
  const auto bad = std::find_if(field.data.begin(), field.data.end(),
                                [](float v) { return !std::isfinite(v); });
  if (bad != field.data.end()) {
    const int64_t n = bad - field.data.begin();
    const int64_t nx = field.grid.size[0], ny = field.grid.size[1];
    return absl::InvalidArgumentError(
        absl::StrFormat("field value at voxel (%d, %d, %d) is not finite",
                        n % nx, (n / nx) % ny, n / (nx * ny)));
  }
  return absl::OkStatus();
}

// ---------------------------------------------------------------------------
// Writers.

absl::Status ValidateMesh(const Mesh& mesh, const std::string& path) {
  const size_t nv = mesh.vertices.size();
  if (nv > std::numeric_limits<uint32_t>::max() ||
      mesh.triangles.size() > std::numeric_limits<uint32_t>::max()) {
    return absl::InvalidArgumentError(
        absl::StrCat("mesh is too large to write to ", path));
  }
  for (const auto& t : mesh.triangles) {
    if (t[0] >= nv || t[1] >= nv || t[2] >= nv) {
      return absl::InvalidArgumentError(absl::StrCat(
          "mesh triangle refers to a missing vertex; not writing ", path));
    }
  }
  return absl::OkStatus();
}

template <typename T>
void AppendLittleEndian(std::string& out, T value) {
  char bytes[sizeof(T)];
  std::memcpy(bytes, &value, sizeof(T));
  if constexpr (std::endian::native == std::endian::big) {
    std::reverse(bytes, bytes + sizeof(T));
  }
  out.append(bytes, sizeof(T));
}

void AppendFloat(std::string& out, float value) {
  char buf[32];
  const auto result = std::to_chars(buf, buf + sizeof(buf), value);
  out.append(buf, result.ptr);
}

void AppendUint(std::string& out, uint64_t value) {
  char buf[24];
  const auto result = std::to_chars(buf, buf + sizeof(buf), value);
  out.append(buf, result.ptr);
}

std::array<float, 3> FacetNormal(const Mesh& mesh,
                                 const std::array<uint32_t, 3>& t) {
  const auto& a = mesh.vertices[t[0]];
  const auto& b = mesh.vertices[t[1]];
  const auto& c = mesh.vertices[t[2]];
  const double u[3] = {double(b[0]) - a[0], double(b[1]) - a[1],
                       double(b[2]) - a[2]};
  const double v[3] = {double(c[0]) - a[0], double(c[1]) - a[1],
                       double(c[2]) - a[2]};
  const double n[3] = {u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2],
                       u[0] * v[1] - u[1] * v[0]};
  const double len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
  if (!(len > 0)) return {0, 0, 0};
  return {static_cast<float>(n[0] / len), static_cast<float>(n[1] / len),
          static_cast<float>(n[2] / len)};
}

std::string LowercaseExtension(const std::string& path) {
  const std::string name = std::filesystem::path(path).filename().string();
  const size_t dot = name.rfind('.');
  if (dot == std::string::npos) return "";
  return absl::AsciiStrToLower(name.substr(dot));
}

}  // namespace

absl::StatusOr<Mesh> ExtractSurface(const Volume<float>& field,
                                    const SurfaceOptions& options,
                                    const ComputeContext& context) {
  INTERSLICE_RETURN_IF_ERROR(ValidateField(field, options));
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  context.Report({.stage = "mesh", .fraction = 0.0});
  surface_internal::InitializeOpenVdb();

  std::vector<openvdb::Vec3s> points;
  std::vector<openvdb::Vec3I> triangles;
  std::vector<openvdb::Vec4I> quads;
  absl::Status status;
  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  arena.execute([&] {
    try {
      openvdb::FloatGrid::Ptr grid = surface_internal::MakeLevelSet(
          field, static_cast<float>(options.isovalue));
      status = context.CheckCancelled();
      if (!status.ok()) return;
      openvdb::tools::volumeToMesh(*grid, points, triangles, quads,
                                   /*isovalue=*/0.0, options.adaptivity);
    } catch (const std::exception& e) {
      status = absl::InternalError(
          absl::StrCat("surface extraction failed: ", e.what()));
    }
  });
  INTERSLICE_RETURN_IF_ERROR(status);
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());

  // Counter-clockwise seen from outside: reverse OpenVDB's winding unless a
  // mirrored index-to-physical map has already reversed it.
  const bool mirrored = IndexToPhysicalDeterminant(field.grid) < 0;
  const bool reverse = kOpenVdbWindsClockwise != mirrored;

  Mesh mesh;
  mesh.vertices.reserve(points.size());
  for (const auto& p : points) mesh.vertices.push_back({p[0], p[1], p[2]});
  mesh.triangles.reserve(2 * quads.size() + triangles.size());
  auto add = [&](uint32_t a, uint32_t b, uint32_t c) {
    if (reverse) {
      mesh.triangles.push_back({a, c, b});
    } else {
      mesh.triangles.push_back({a, b, c});
    }
  };
  for (const auto& q : quads) {
    add(q[0], q[1], q[2]);
    add(q[0], q[2], q[3]);
  }
  for (const auto& t : triangles) add(t[0], t[1], t[2]);
  context.Report({.stage = "mesh", .fraction = 1.0});
  return mesh;
}

absl::StatusOr<MeshDeviation> MeasureMeshDeviation(
    const Mesh& simplified, const Mesh& reference, double resolution_mm,
    const ComputeContext& context) {
  if (!(resolution_mm > 0) || !std::isfinite(resolution_mm)) {
    return absl::InvalidArgumentError(
        "mesh deviation resolution must be a positive number of mm");
  }
  MeshDeviation deviation;
  deviation.resolution_mm = resolution_mm;
  if (simplified.triangles.empty()) return deviation;
  if (reference.triangles.empty()) {
    return absl::InvalidArgumentError(
        "the reference mesh is empty but the simplified mesh is not");
  }
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  surface_internal::InitializeOpenVdb();
  const float band_voxels =
      static_cast<float>(std::max(8.0, std::ceil(2.0 / resolution_mm)));
  deviation.band_mm = band_voxels * resolution_mm;
  std::vector<openvdb::Vec3s> points;
  points.reserve(reference.vertices.size());
  for (const auto& v : reference.vertices)
    points.emplace_back(v[0], v[1], v[2]);
  std::vector<openvdb::Vec3I> triangles;
  triangles.reserve(reference.triangles.size());
  for (const auto& t : reference.triangles) {
    triangles.emplace_back(t[0], t[1], t[2]);
  }
  absl::Status status;
  double sum = 0;
  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  arena.execute([&] {
    try {
      const openvdb::math::Transform::Ptr transform =
          openvdb::math::Transform::createLinearTransform(resolution_mm);
      const openvdb::FloatGrid::Ptr distance =
          openvdb::tools::meshToUnsignedDistanceField<openvdb::FloatGrid>(
              *transform, points, triangles, {}, band_voxels);
      status = context.CheckCancelled();
      if (!status.ok()) return;
      const openvdb::tools::GridSampler<openvdb::FloatGrid,
                                        openvdb::tools::BoxSampler>
          sampler(*distance);
      auto sample = [&](const openvdb::Vec3d& p) {
        double d = sampler.wsSample(p);
        // Inactive voxels hold the background, the band's width.
        if (d >= deviation.band_mm * (1 - 1e-6)) {
          d = deviation.band_mm;
          ++deviation.beyond_band;
        }
        deviation.max_mm = std::max(deviation.max_mm, d);
        sum += d;
        ++deviation.samples;
      };
      for (const auto& t : simplified.triangles) {
        openvdb::Vec3d corner[3];
        for (int k = 0; k < 3; ++k) {
          const auto& v = simplified.vertices[t[k]];
          corner[k] = openvdb::Vec3d(v[0], v[1], v[2]);
        }
        // Each vertex and edge is sampled once per triangle that has it:
        // the maximum does not mind, the mean weighs them a little more.
        for (int k = 0; k < 3; ++k) {
          sample(corner[k]);
          sample(0.5 * (corner[k] + corner[(k + 1) % 3]));
        }
        sample((corner[0] + corner[1] + corner[2]) / 3.0);
      }
    } catch (const std::exception& e) {
      status = absl::InternalError(
          absl::StrCat("mesh deviation measurement failed: ", e.what()));
    }
  });
  INTERSLICE_RETURN_IF_ERROR(status);
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  deviation.mean_mm = sum / static_cast<double>(deviation.samples);
  return deviation;
}

absl::Status WriteStl(const Mesh& mesh, const std::string& path) {
  INTERSLICE_RETURN_IF_ERROR(ValidateMesh(mesh, path));
  return surface_internal::WriteFileAtomically(
      path, [&](surface_internal::ChunkedWriter& out) {
        std::string& buf = out.buffer();
        // The header must not start with "solid" (the ASCII STL keyword).
        std::string header = "interslice binary STL, LPS mm";
        header.resize(80, ' ');
        buf.append(header);
        AppendLittleEndian<uint32_t>(buf, mesh.triangles.size());
        for (const auto& t : mesh.triangles) {
          const auto n = FacetNormal(mesh, t);
          for (float v : n) AppendLittleEndian(buf, v);
          for (uint32_t i : t) {
            for (float v : mesh.vertices[i]) AppendLittleEndian(buf, v);
          }
          AppendLittleEndian<uint16_t>(buf, 0);
          out.MaybeFlush();
        }
      });
}

absl::Status WritePly(const Mesh& mesh, const std::string& path) {
  INTERSLICE_RETURN_IF_ERROR(ValidateMesh(mesh, path));
  return surface_internal::WriteFileAtomically(
      path, [&](surface_internal::ChunkedWriter& out) {
        std::string& buf = out.buffer();
        absl::StrAppend(&buf,
                        "ply\n"
                        "format binary_little_endian 1.0\n"
                        "comment interslice surface, LPS mm\n"
                        "element vertex ",
                        mesh.vertices.size(),
                        "\n"
                        "property float x\n"
                        "property float y\n"
                        "property float z\n"
                        "element face ",
                        mesh.triangles.size(),
                        "\n"
                        "property list uchar uint vertex_indices\n"
                        "end_header\n");
        for (const auto& p : mesh.vertices) {
          for (float v : p) AppendLittleEndian(buf, v);
          out.MaybeFlush();
        }
        for (const auto& t : mesh.triangles) {
          AppendLittleEndian<uint8_t>(buf, 3);
          for (uint32_t i : t) AppendLittleEndian(buf, i);
          out.MaybeFlush();
        }
      });
}

absl::Status WriteObj(const Mesh& mesh, const std::string& path) {
  INTERSLICE_RETURN_IF_ERROR(ValidateMesh(mesh, path));
  return surface_internal::WriteFileAtomically(
      path, [&](surface_internal::ChunkedWriter& out) {
        std::string& buf = out.buffer();
        buf.append("# interslice surface, LPS mm\n");
        for (const auto& p : mesh.vertices) {
          buf.append("v ");
          AppendFloat(buf, p[0]);
          buf.push_back(' ');
          AppendFloat(buf, p[1]);
          buf.push_back(' ');
          AppendFloat(buf, p[2]);
          buf.push_back('\n');
          out.MaybeFlush();
        }
        for (const auto& t : mesh.triangles) {
          buf.append("f ");
          AppendUint(buf, uint64_t{t[0]} + 1);
          buf.push_back(' ');
          AppendUint(buf, uint64_t{t[1]} + 1);
          buf.push_back(' ');
          AppendUint(buf, uint64_t{t[2]} + 1);
          buf.push_back('\n');
          out.MaybeFlush();
        }
      });
}

absl::Status WriteMesh(const Mesh& mesh, const std::string& path) {
  const std::string ext = LowercaseExtension(path);
  if (ext == ".stl") return WriteStl(mesh, path);
  if (ext == ".ply") return WritePly(mesh, path);
  if (ext == ".obj") return WriteObj(mesh, path);
  return absl::InvalidArgumentError(
      absl::StrCat("cannot write a mesh to ", path,
                   ": unknown extension (expected .stl, .ply or .obj)"));
}

}  // namespace interslice

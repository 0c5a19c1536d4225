#include "core/surface/level_set.h"

#include <openvdb/math/Transform.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <mutex>
#include <vector>

namespace interslice::surface_internal {

void InitializeOpenVdb() {
  static std::once_flag once;
  std::call_once(once, [] { openvdb::initialize(); });
}

// index -> LPS mm. OpenVDB multiplies row vectors: world = [i j k 1] * M, so
// M's row r is index axis r's physical step and row 3 the origin.
openvdb::math::Transform::Ptr MakeTransform(const Grid& grid) {
  openvdb::math::Mat4d m = openvdb::math::Mat4d::identity();
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c) {
      m[r][c] = grid.direction[3 * c + r] * grid.spacing[r];
    }
    m[r][3] = 0;
  }
  for (int c = 0; c < 3; ++c) m[3][c] = grid.origin[c];
  m[3][3] = 1;
  return openvdb::math::Transform::createLinearTransform(m);
}

// The field as a narrow-band level set (negative inside): leaf nodes (8^3
// voxels) only where the surface can pass, i.e. where the leaf grown by one
// voxel on every side holds samples of both signs (a crossing edge lies in
// it, or ends on its border); leaves entirely inside become inactive tiles
// of -background and leaves entirely outside stay background, so every
// sample the mesher reads through a leaf's border has the right sign. The
// grid is wrapped in a shell one voxel thick of +background (outside), so
// that the surface closes where the shape meets the grid boundary. Band
// leaves hold every voxel of the padded box as active, so the mesher sees
// exactly the dense data there; away from the surface nothing is copied
// (the dense copy was one float volume at the mesh stage's peak).
openvdb::FloatGrid::Ptr MakeLevelSet(const Volume<float>& field,
                                     float isovalue) {
  const Grid& g = field.grid;
  const float background =
      static_cast<float>(std::max({g.spacing[0], g.spacing[1], g.spacing[2]}));
  openvdb::FloatGrid::Ptr grid = openvdb::FloatGrid::create(background);
  grid->setGridClass(openvdb::GRID_LEVEL_SET);
  grid->setTransform(MakeTransform(g));

  using LeafT = openvdb::FloatTree::LeafNodeType;
  constexpr int kDim = static_cast<int>(LeafT::DIM);
  const int nx = static_cast<int>(g.size[0]);
  const int ny = static_cast<int>(g.size[1]);
  const int nz = static_cast<int>(g.size[2]);
  // Leaves cover the padded box [-1, n] on each axis; their origins are
  // multiples of kDim.
  auto first_origin = [](int lo) {
    return static_cast<int>(std::floor(static_cast<double>(lo) / kDim)) * kDim;
  };
  std::vector<openvdb::Coord> origins;
  for (int x = first_origin(-1); x <= nx; x += kDim) {
    for (int y = first_origin(-1); y <= ny; y += kDim) {
      for (int z = first_origin(-1); z <= nz; z += kDim) {
        origins.emplace_back(x, y, z);
      }
    }
  }
  // Per origin: a band leaf, an inside tile, or nothing (outside).
  enum : uint8_t { kOutside, kInside, kBand };
  std::vector<uint8_t> kinds(origins.size(), kOutside);
  std::vector<LeafT*> leaves(origins.size(), nullptr);
  const float* data = field.data.data();
  // A sample at (or within float noise of) the isovalue puts the vertices of
  // all its edges at one point: degenerate triangles and distinct vertices
  // at identical positions (2D distance maps are exactly 0 on pixels lying
  // on the contour). Such samples keep their side (exactly at the isovalue
  // counts as inside, as in the mask field >= isovalue) and are moved to a
  // thousandth of a voxel from it, which separates those vertices by several
  // float ulps at patient coordinates and moves the surface by at most that.
  const float nudge = static_cast<float>(
      1e-3 * std::min({g.spacing[0], g.spacing[1], g.spacing[2]}));
  const int64_t sy = g.size[0], sz = g.size[0] * g.size[1];
  // Signs per row segment, in one streaming pass over the field: for row
  // (y, z) and the i-th leaf column, bit 0 = some sample inside, bit 1 =
  // some sample outside, over x in [x_i - 1, x_i + kDim] within the grid
  // (each leaf's grown box then reads (kDim + 2)^2 bytes, not floats
  // scattered over the volume).
  const int x_first = first_origin(-1);
  const int64_t columns = (nx - x_first) / kDim + 1;
  std::vector<uint8_t> row_signs(static_cast<size_t>(columns * ny * nz));
  tbb::parallel_for(
      tbb::blocked_range<int64_t>(0, int64_t{ny} * nz),
      [&](const tbb::blocked_range<int64_t>& rows) {
        for (int64_t r = rows.begin(); r != rows.end(); ++r) {
          const float* row = data + r * sy;
          uint8_t* signs = row_signs.data() + r * columns;
          for (int64_t i = 0; i < columns; ++i) {
            const int x0 = std::max<int>(x_first + kDim * i - 1, 0);
            const int x1 = std::min<int>(x_first + kDim * i + kDim, nx - 1);
            int count = 0;  // branch-free, so that the loop vectorises
            for (int x = x0; x <= x1; ++x) count += row[x] >= isovalue;
            signs[i] = static_cast<uint8_t>((count > 0 ? 1 : 0) |
                                            (count < x1 - x0 + 1 ? 2 : 0));
          }
        }
      });
  tbb::parallel_for(
      tbb::blocked_range<size_t>(0, origins.size()),
      [&](const tbb::blocked_range<size_t>& range) {
        for (size_t n = range.begin(); n != range.end(); ++n) {
          const openvdb::Coord& o = origins[n];
          // Signs over the leaf grown by one voxel. Samples beyond the grid
          // (the shell, and beyond it background) are outside.
          const int x0 = o.x() - 1, x1 = o.x() + kDim;  // inclusive
          const int y0 = o.y() - 1, y1 = o.y() + kDim;
          const int z0 = o.z() - 1, z1 = o.z() + kDim;
          const int64_t column = (o.x() - x_first) / kDim;
          uint8_t signs =
              (x0 < 0 || x1 >= nx || y0 < 0 || y1 >= ny || z0 < 0 || z1 >= nz)
                  ? 2
                  : 0;
          for (int z = std::max(z0, 0); z <= std::min(z1, nz - 1); ++z) {
            const uint8_t* plane = row_signs.data() + int64_t{z} * ny * columns;
            for (int y = std::max(y0, 0); y <= std::min(y1, ny - 1); ++y) {
              signs |= plane[int64_t{y} * columns + column];
            }
          }
          const bool any_in = (signs & 1) != 0, any_out = (signs & 2) != 0;
          if (!(any_in && any_out)) {
            kinds[n] = any_in ? kInside : kOutside;
            continue;
          }
          kinds[n] = kBand;
          auto* leaf = new LeafT(o, background, /*active=*/false);
          // Leaf voxel offsets are x * 64 + y * 8 + z; the field's x is
          // contiguous, so x runs innermost.
          for (int z = o.z(); z < o.z() + kDim; ++z) {
            for (int y = o.y(); y < o.y() + kDim; ++y) {
              for (int x = o.x(); x < o.x() + kDim; ++x) {
                if (x < -1 || x > nx || y < -1 || y > ny || z < -1 || z > nz) {
                  continue;  // beyond the shell: inactive background
                }
                float value = background;
                if (x >= 0 && x < nx && y >= 0 && y < ny && z >= 0 && z < nz) {
                  value = isovalue - data[x + y * sy + z * sz];
                  if (std::abs(value) < nudge) {
                    value = value > 0 ? nudge : -nudge;
                  }
                }
                leaf->setValueOn(LeafT::coordToOffset(openvdb::Coord(x, y, z)),
                                 value);
              }
            }
          }
          leaves[n] = leaf;
        }
      });
  openvdb::FloatTree& tree = grid->tree();
  for (size_t n = 0; n < origins.size(); ++n) {
    if (kinds[n] == kBand) {
      tree.addLeaf(leaves[n]);  // the tree takes ownership
    } else if (kinds[n] == kInside) {
      // A tile the size of a leaf (level 1: a child of the lowest internal
      // node), inactive, as OpenVDB's level sets hold their interior.
      tree.addTile(/*level=*/1, origins[n], -background, /*active=*/false);
    }
  }
  return grid;
}

}  // namespace interslice::surface_internal

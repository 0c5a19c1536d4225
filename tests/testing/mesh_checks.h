// Test helpers: read binary STL files and check mesh topology/orientation.
#ifndef INTERSLICE_TESTS_TESTING_MESH_CHECKS_H_
#define INTERSLICE_TESTS_TESTING_MESH_CHECKS_H_

#include <array>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <map>
#include <string>
#include <tuple>
#include <vector>

namespace interslice::testing {

struct TriangleSoup {
  std::vector<std::array<std::array<float, 3>, 3>> triangles;
};

// Parses a binary STL; returns false if the file is malformed.
inline bool ReadBinaryStl(const std::string& path, TriangleSoup& soup) {
  std::ifstream in(path, std::ios::binary);
  char header[80];
  uint32_t count = 0;
  if (!in.read(header, 80) || !in.read(reinterpret_cast<char*>(&count), 4)) {
    return false;
  }
  soup.triangles.resize(count);
  for (uint32_t t = 0; t < count; ++t) {
    float data[12];
    uint16_t attribute;
    if (!in.read(reinterpret_cast<char*>(data), 48) ||
        !in.read(reinterpret_cast<char*>(&attribute), 2)) {
      return false;
    }
    for (int v = 0; v < 3; ++v) {
      for (int a = 0; a < 3; ++a) soup.triangles[t][v][a] = data[3 + 3 * v + a];
    }
  }
  in.peek();
  return in.eof();
}

struct MeshTopology {
  int64_t boundary_edges = 0;      // directed edges without a reverse twin
  int64_t non_manifold_edges = 0;  // directed edges used more than once
  double signed_volume = 0;        // > 0 for outward orientation
};

// Welds vertices by exact position (STL stores them per triangle) and checks
// that every directed edge appears once and its reverse once: a closed,
// consistently oriented surface.
inline MeshTopology AnalyzeSoup(const TriangleSoup& soup) {
  std::map<std::array<float, 3>, int64_t> ids;
  auto id = [&](const std::array<float, 3>& p) {
    auto [it, inserted] = ids.emplace(p, static_cast<int64_t>(ids.size()));
    return it->second;
  };
  std::map<std::pair<int64_t, int64_t>, int> directed;
  MeshTopology topo;
  for (const auto& tri : soup.triangles) {
    const int64_t a = id(tri[0]), b = id(tri[1]), c = id(tri[2]);
    ++directed[{a, b}];
    ++directed[{b, c}];
    ++directed[{c, a}];
    const auto& p = tri[0];
    const auto& q = tri[1];
    const auto& r = tri[2];
    // Divergence theorem: volume = sum p . (q x r) / 6.
    topo.signed_volume +=
        (static_cast<double>(p[0]) * (q[1] * r[2] - q[2] * r[1]) -
         static_cast<double>(p[1]) * (q[0] * r[2] - q[2] * r[0]) +
         static_cast<double>(p[2]) * (q[0] * r[1] - q[1] * r[0])) /
        6.0;
  }
  for (const auto& [edge, count] : directed) {
    if (count > 1) ++topo.non_manifold_edges;
    if (!directed.count({edge.second, edge.first})) ++topo.boundary_edges;
  }
  return topo;
}

struct IndexedMesh {
  std::vector<std::array<float, 3>> vertices;
  std::vector<std::array<uint32_t, 3>> triangles;
};

// Parses the binary little-endian PLY that interslice writes (float x y z;
// uchar count + uint indices); returns false if the file is malformed.
inline bool ReadBinaryPly(const std::string& path, IndexedMesh& mesh) {
  std::ifstream in(path, std::ios::binary);
  std::string line;
  int64_t vertices = -1, faces = -1;
  while (std::getline(in, line)) {
    if (line.rfind("element vertex ", 0) == 0)
      vertices = std::stoll(line.substr(15));
    if (line.rfind("element face ", 0) == 0)
      faces = std::stoll(line.substr(13));
    if (line == "end_header") break;
  }
  if (vertices < 0 || faces < 0) return false;
  mesh.vertices.resize(vertices);
  if (!in.read(reinterpret_cast<char*>(mesh.vertices.data()), 12 * vertices)) {
    return false;
  }
  mesh.triangles.resize(faces);
  for (int64_t f = 0; f < faces; ++f) {
    unsigned char count = 0;
    if (!in.read(reinterpret_cast<char*>(&count), 1) || count != 3 ||
        !in.read(reinterpret_cast<char*>(mesh.triangles[f].data()), 12)) {
      return false;
    }
  }
  return true;
}

// Topology by vertex index (no welding): every directed edge once and its
// reverse once means closed, 2-manifold along edges and consistently
// oriented.
inline MeshTopology AnalyzeIndexed(const IndexedMesh& mesh) {
  std::map<std::pair<uint32_t, uint32_t>, int> directed;
  MeshTopology topo;
  for (const auto& t : mesh.triangles) {
    for (int e = 0; e < 3; ++e) ++directed[{t[e], t[(e + 1) % 3]}];
    const auto& p = mesh.vertices[t[0]];
    const auto& q = mesh.vertices[t[1]];
    const auto& r = mesh.vertices[t[2]];
    topo.signed_volume +=
        (static_cast<double>(p[0]) * (q[1] * r[2] - q[2] * r[1]) -
         static_cast<double>(p[1]) * (q[0] * r[2] - q[2] * r[0]) +
         static_cast<double>(p[2]) * (q[0] * r[1] - q[1] * r[0])) /
        6.0;
  }
  for (const auto& [edge, count] : directed) {
    if (count > 1) ++topo.non_manifold_edges;
    if (!directed.count({edge.second, edge.first})) ++topo.boundary_edges;
  }
  return topo;
}

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_MESH_CHECKS_H_

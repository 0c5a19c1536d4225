// The 3D view: the objects' surfaces seen from the front, ray-traced on the
// narrow-band level set the mesher builds (core/surface/level_set.h) with
// OpenVDB's LevelSetRayIntersector, and shaded by Lambert's cosine law.
//
// Why the intersector and not OpenVDB's LevelSetRayTracer: the tracer draws
// one level set per image, while a fill has one surface per label, which
// must hide each other by depth; and both need uniform voxels, while output
// grids are anisotropic (a fill on its reference grid: 0.45 x 0.45 x 5 mm).
// So each surface is traced in its own grid's index space, scaled to a
// uniform voxel (an affine map sends rays to rays), and the nearest hit of
// all surfaces shades the pixel.
#include <openvdb/math/Ray.h>
#include <openvdb/openvdb.h>
#include <openvdb/tools/RayIntersector.h>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <exception>
#include <limits>
#include <optional>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/preview/preview_internal.h"
#include "core/surface/level_set.h"

namespace interslice::preview_internal {
namespace {

using Intersector = openvdb::tools::LevelSetRayIntersector<openvdb::FloatGrid>;
using Ray = Intersector::RayType;
using VdbVec3 = Ray::Vec3Type;

// The camera, in LPS: the picture's x runs to the patient's left, its y to
// the feet, and the view looks from anterior to posterior.
constexpr Vec3 kRight = {1, 0, 0};
constexpr Vec3 kDown = {0, 0, -1};
constexpr Vec3 kViewDirection = {0, 1, 0};

// Subsamples per pixel along each axis (anti-aliased silhouettes).
constexpr int kSubsamples = 2;
// Lambert shading: ambient share and the light's direction (towards it):
// from the viewer, above and a little to the picture's left.
constexpr double kAmbient = 0.22;
// Pixels around the surfaces kept free for the direction letters.
constexpr int kLetterRoom = 20;

double Dot(const Vec3& a, const Vec3& b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}
Vec3 Normalised(const Vec3& v) {
  const double n = std::sqrt(Dot(v, v));
  return n > 0 ? Vec3{v[0] / n, v[1] / n, v[2] / n} : v;
}

// One surface, ready to trace: its level set with a uniform voxel of
// `voxel` mm (the level set's "world" is index * voxel), and the map from
// LPS to that space.
struct Surface {
  openvdb::FloatGrid::Ptr level_set;
  std::optional<Intersector> intersector;
  const Grid* grid = nullptr;
  double voxel = 1;
  Rgb rgb{};
  // The view direction in the level set's space, unit, and how many of its
  // units one mm along the view direction is.
  VdbVec3 direction;
  double units_per_mm = 1;
};

// LPS -> the level set's space: voxel * index.
VdbVec3 ToLevelSet(const Surface& s, const Vec3& lps) {
  const Vec3 index = s.grid->PhysicalToIndex(lps);
  return VdbVec3(index[0] * s.voxel, index[1] * s.voxel, index[2] * s.voxel);
}

absl::Status CheckSurfaceField(const Volume<float>& field, size_t object) {
  if (absl::Status s = field.grid.Validate(); !s.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "previews: object ", object, "'s surface field: ", s.message()));
  }
  if (static_cast<int64_t>(field.data.size()) != field.grid.VoxelCount()) {
    return absl::InvalidArgumentError(
        absl::StrCat("previews: object ", object,
                     "'s surface field does not hold one value per voxel"));
  }
  for (float v : field.data) {
    if (!std::isfinite(v)) {
      return absl::InvalidArgumentError(absl::StrCat(
          "previews: object ", object, "'s surface field is not finite"));
    }
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<PreviewImage> RenderFrontView(const PreviewScene& scene,
                                             double mm_per_pixel,
                                             const PreviewOptions& options,
                                             const Legend& common,
                                             const LegendFont& font,
                                             const ComputeContext& context) {
  surface_internal::InitializeOpenVdb();
  std::vector<Surface> surfaces;
  // The extent of every surface along the picture's axes and the view.
  double lo[3] = {std::numeric_limits<double>::infinity(),
                  std::numeric_limits<double>::infinity(),
                  std::numeric_limits<double>::infinity()};
  double hi[3] = {-lo[0], -lo[1], -lo[2]};
  const Vec3 axes[3] = {kRight, kDown, kViewDirection};
  Legend legend = common;
  try {
    for (size_t n = 0; n < scene.objects.size(); ++n) {
      const PreviewObject& object = scene.objects[n];
      if (object.surface == nullptr) continue;
      if (absl::Status s = CheckSurfaceField(*object.surface, n); !s.ok()) {
        return s;
      }
      if (absl::Status s = context.CheckCancelled(); !s.ok()) return s;
      Surface surface;
      surface.grid = &object.surface->grid;
      surface.rgb = object.rgb;
      // The largest spacing along the grid axes the rays cross (consecutive
      // samples of a ray differ by at most that in a distance field).
      surface.voxel = 0;
      for (int a = 0; a < 3; ++a) {
        if (std::abs(Dot(surface.grid->Axis(a), kViewDirection)) > 1e-6) {
          surface.voxel = std::max(surface.voxel, surface.grid->spacing[a]);
        }
      }
      surface.level_set = surface_internal::MakeLevelSet(*object.surface, 0.0f);
      // A uniform voxel, so that the intersector accepts the grid; its
      // search tests only samples within 2 voxels of the surface, which
      // then holds the two samples on either side of every crossing.
      surface.level_set->setTransform(
          openvdb::math::Transform::createLinearTransform(surface.voxel));
      if (surface.level_set->tree().activeVoxelCount() == 0) continue;
      surface.intersector.emplace(*surface.level_set);
      const openvdb::CoordBBox box =
          surface.level_set->evalActiveVoxelBoundingBox();
      for (int corner = 0; corner < 8; ++corner) {
        const Vec3 index = {
            static_cast<double>((corner & 1) ? box.max().x() : box.min().x()),
            static_cast<double>((corner & 2) ? box.max().y() : box.min().y()),
            static_cast<double>((corner & 4) ? box.max().z() : box.min().z())};
        const Vec3 p = surface.grid->IndexToPhysical(index);
        for (int a = 0; a < 3; ++a) {
          lo[a] = std::min(lo[a], Dot(p, axes[a]));
          hi[a] = std::max(hi[a], Dot(p, axes[a]));
        }
      }
      // The view direction in the level set's space.
      const VdbVec3 origin = ToLevelSet(surface, {0, 0, 0});
      const VdbVec3 tip = ToLevelSet(surface, kViewDirection);
      const VdbVec3 step = tip - origin;
      surface.units_per_mm = step.length();
      surface.direction = step / surface.units_per_mm;
      legend.swatches.push_back({object.rgb, object.name, false});
      surfaces.push_back(std::move(surface));
    }
  } catch (const std::exception& e) {
    return absl::InternalError(
        absl::StrCat("previews: preparing the 3D view failed: ", e.what()));
  }

  const bool empty = surfaces.empty();
  if (empty) {
    // The whole grid, so that the view is as large as the planes.
    for (int corner = 0; corner < 8; ++corner) {
      const Grid& g = scene.grid;
      const Vec3 index = {(corner & 1) ? g.size[0] - 0.5 : -0.5,
                          (corner & 2) ? g.size[1] - 0.5 : -0.5,
                          (corner & 4) ? g.size[2] - 0.5 : -0.5};
      const Vec3 p = g.IndexToPhysical(index);
      for (int a = 0; a < 3; ++a) {
        lo[a] = std::min(lo[a], Dot(p, axes[a]));
        hi[a] = std::max(hi[a], Dot(p, axes[a]));
      }
    }
  }
  // Room around the surfaces: 4% of the larger extent on each side, and a
  // band for the direction letters.
  const double pad = 0.04 * std::max(hi[0] - lo[0], hi[1] - lo[1]);
  for (int a = 0; a < 2; ++a) {
    lo[a] -= pad;
    hi[a] += pad;
  }
  const double extent = std::max({hi[0] - lo[0], hi[1] - lo[1], 1e-3});
  double mm = mm_per_pixel;
  if (extent / mm > options.max_size) mm = extent / options.max_size;
  if (extent / mm < options.min_size) mm = extent / options.min_size;
  const int width =
      std::max(1, static_cast<int>(std::ceil((hi[0] - lo[0]) / mm - 1e-9))) +
      2 * kLetterRoom;
  const int height =
      std::max(1, static_cast<int>(std::ceil((hi[1] - lo[1]) / mm - 1e-9))) +
      2 * kLetterRoom;
  // The picture's top-left corner, centred on the surfaces, in front of
  // them (1 mm before the nearest).
  const double centre_r = (lo[0] + hi[0]) / 2, centre_d = (lo[1] + hi[1]) / 2;
  const double front = lo[2] - 1.0;
  Vec3 corner{};
  for (int c = 0; c < 3; ++c) {
    corner[c] = (centre_r - width * mm / 2) * kRight[c] +
                (centre_d - height * mm / 2) * kDown[c] +
                front * kViewDirection[c];
  }

  legend.lines.push_back(absl::StrFormat(
      "3D: %s seen from the front (anterior), orthographic, %.3g mm per "
      "pixel",
      surfaces.size() > 1 ? "surfaces" : "surface", mm));

  const Vec3 light =
      Normalised({-kViewDirection[0] - 0.35 * kRight[0] - 0.55 * kDown[0],
                  -kViewDirection[1] - 0.35 * kRight[1] - 0.55 * kDown[1],
                  -kViewDirection[2] - 0.35 * kRight[2] - 0.55 * kDown[2]});
  // One ray per pixel centre; pixels whose neighbours see another surface
  // (or none) are then traced again at 2 x 2 subsamples, which smooths the
  // silhouettes at little cost.
  struct Sample {
    double rgb[3];
    int surface;  // -1: background
  };
  auto trace = [&](std::vector<Intersector>& local, double u,
                   double v) -> Sample {
    Vec3 eye{};
    for (int c = 0; c < 3; ++c) {
      eye[c] = corner[c] + u * kRight[c] + v * kDown[c];
    }
    double best = std::numeric_limits<double>::infinity();
    Vec3 normal{};
    int seen = -1;
    for (size_t s = 0; s < surfaces.size(); ++s) {
      const Surface& surface = surfaces[s];
      Ray ray(ToLevelSet(surface, eye), surface.direction);
      VdbVec3 hit, gradient;
      double t = 0;
      if (!local[s].intersectsWS(ray, hit, gradient, t)) continue;
      const double depth = t / surface.units_per_mm;
      if (!(depth < best)) continue;
      best = depth;
      seen = static_cast<int>(s);
      // The gradient is in index space; in LPS a normal maps by the
      // inverse transpose: R * diag(1 / h).
      const Grid& g = *surface.grid;
      Vec3 n{};
      for (int c = 0; c < 3; ++c) {
        n[c] = g.direction[3 * c] * gradient[0] / g.spacing[0] +
               g.direction[3 * c + 1] * gradient[1] / g.spacing[1] +
               g.direction[3 * c + 2] * gradient[2] / g.spacing[2];
      }
      normal = Normalised(n);
    }
    Sample sample{{0, 0, 0}, seen};
    if (seen < 0) {
      for (int c = 0; c < 3; ++c) sample.rgb[c] = kBackground[c];
      return sample;
    }
    // The level set is negative inside: its gradient points out of the
    // object, towards the viewer on a front face.
    const double lambert = std::max(0.0, Dot(normal, light));
    const double shade = kAmbient + (1 - kAmbient) * lambert;
    for (int c = 0; c < 3; ++c) {
      sample.rgb[c] = surfaces[seen].rgb[c] * shade;
    }
    return sample;
  };
  std::vector<Sample> samples(static_cast<size_t>(width) * height);
  std::atomic<bool> cancelled{false};
  std::string failure;
  std::atomic<bool> failed{false};
  // Runs `pass` on every row, each task with its own intersectors (they
  // keep per-ray state).
  auto for_rows = [&](const auto& pass) {
    tbb::parallel_for(tbb::blocked_range<int>(0, height, 4),
                      [&](const tbb::blocked_range<int>& rows) {
                        if (cancelled.load() || failed.load()) return;
                        if (!context.CheckCancelled().ok()) {
                          cancelled = true;
                          return;
                        }
                        try {
                          std::vector<Intersector> local;
                          local.reserve(surfaces.size());
                          for (const Surface& s : surfaces)
                            local.push_back(*s.intersector);
                          for (int y = rows.begin(); y != rows.end(); ++y)
                            pass(local, y);
                        } catch (const std::exception& e) {
                          if (!failed.exchange(true)) failure = e.what();
                        }
                      });
  };
  if (!empty) {
    for_rows([&](std::vector<Intersector>& local, int y) {
      for (int x = 0; x < width; ++x) {
        samples[static_cast<size_t>(y) * width + x] =
            trace(local, (x + 0.5) * mm, (y + 0.5) * mm);
      }
    });
    std::vector<Sample> smoothed = samples;
    for_rows([&](std::vector<Intersector>& local, int y) {
      for (int x = 0; x < width; ++x) {
        const int id = samples[static_cast<size_t>(y) * width + x].surface;
        bool edge = false;
        for (const auto [dx, dy] : {std::pair{-1, 0}, std::pair{1, 0},
                                    std::pair{0, -1}, std::pair{0, 1}}) {
          const int nx = x + dx, ny = y + dy;
          if (nx < 0 || ny < 0 || nx >= width || ny >= height) continue;
          edge |= samples[static_cast<size_t>(ny) * width + nx].surface != id;
        }
        if (!edge) continue;
        Sample& out = smoothed[static_cast<size_t>(y) * width + x];
        for (int c = 0; c < 3; ++c) out.rgb[c] = 0;
        for (int sy = 0; sy < kSubsamples; ++sy) {
          for (int sx = 0; sx < kSubsamples; ++sx) {
            const Sample sub = trace(local, (x + (sx + 0.5) / kSubsamples) * mm,
                                     (y + (sy + 0.5) / kSubsamples) * mm);
            for (int c = 0; c < 3; ++c) {
              out.rgb[c] += sub.rgb[c] / (kSubsamples * kSubsamples);
            }
          }
        }
      }
    });
    samples = std::move(smoothed);
  }
  std::vector<uint8_t> picture(static_cast<size_t>(width) * height * 3);
  for (size_t n = 0; n < samples.size(); ++n) {
    for (int c = 0; c < 3; ++c) {
      picture[3 * n + c] = empty ? kBackground[c]
                                 : static_cast<uint8_t>(std::lround(std::clamp(
                                       samples[n].rgb[c], 0.0, 255.0)));
    }
  }
  if (cancelled) {
    if (absl::Status s = context.CheckCancelled(); !s.ok()) return s;
    return absl::CancelledError("previews cancelled");
  }
  if (failed) {
    return absl::InternalError(
        absl::StrCat("previews: ray tracing failed: ", failure));
  }

  const Layout layout = LayOut(font, width, height, legend);
  SurfacePtr canvas = NewCanvas(layout);
  {
    cairo_surface_flush(canvas.get());
    unsigned char* data = cairo_image_surface_get_data(canvas.get());
    const int stride = cairo_image_surface_get_stride(canvas.get());
    for (int y = 0; y < height; ++y) {
      uint32_t* row =
          reinterpret_cast<uint32_t*>(data + (layout.y0 + y) * stride) +
          layout.x0;
      const uint8_t* in = picture.data() + static_cast<size_t>(y) * width * 3;
      for (int x = 0; x < width; ++x) {
        row[x] = (uint32_t{in[3 * x]} << 16) | (uint32_t{in[3 * x + 1]} << 8) |
                 uint32_t{in[3 * x + 2]};
      }
    }
    cairo_surface_mark_dirty(canvas.get());
  }
  ContextPtr cr(cairo_create(canvas.get()));
  if (empty)
    DrawCentredNote(cr.get(), font, layout, "no surface: the object is empty");
  DrawEdgeLetters(cr.get(), font, layout,
                  {DisplayDirectionLetter({-kRight[0], -kRight[1], -kRight[2]}),
                   DisplayDirectionLetter(kRight),
                   DisplayDirectionLetter({-kDown[0], -kDown[1], -kDown[2]}),
                   DisplayDirectionLetter(kDown)});
  DrawLegend(cr.get(), font, layout, legend);

  PreviewImage image;
  image.name = "3d-front";
  image.width = layout.width;
  image.height = layout.height;
  image.rgb = SurfaceToRgb(canvas.get());
  image.description = empty ? "3D view from the front: no surface"
                            : "3D view of the surface from the front";
  image.legend = legend.lines;
  image.patient_orientation = absl::StrCat(DicomDirectionLetters(kRight), "\\",
                                           DicomDirectionLetters(kDown));
  image.x0 = layout.x0;
  image.y0 = layout.y0;
  image.x1 = layout.x0 + width;
  image.y1 = layout.y0 + height;
  for (int c = 0; c < 3; ++c) {
    image.per_x[c] = mm * kRight[c];
    image.per_y[c] = mm * kDown[c];
    image.origin[c] =
        corner[c] - layout.x0 * image.per_x[c] - layout.y0 * image.per_y[c];
    image.view_direction[c] = kViewDirection[c];
  }
  return image;
}

}  // namespace interslice::preview_internal

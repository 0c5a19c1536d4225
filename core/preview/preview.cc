// RenderPreviews: checks the scene, names the grid's axes, chooses the
// planes, the scale and the window, and renders the views in parallel
// (view_2d.cc, view_3d.cc).
#include "core/preview/preview.h"

#include <tbb/parallel_for.h>
#include <tbb/task_arena.h>
#include <tbb/task_group.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <optional>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/preview/preview_internal.h"

namespace interslice {
namespace {

using preview_internal::AxisPixels;
using preview_internal::Legend;
using preview_internal::LegendFont;
using preview_internal::PlaneView;

// Spacings within this ratio of the finest are drawn one pixel per sample.
constexpr double kSameSpacing = 1.05;

absl::Status CheckScene(const PreviewScene& scene,
                        const PreviewOptions& options) {
  if (absl::Status s = scene.grid.Validate(); !s.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat("previews: the grid: ", s.message()));
  }
  for (int a = 0; a < 3; ++a) {
    if (scene.grid.size[a] > (1 << 20)) {
      return absl::InvalidArgumentError(
          "previews: the grid is too large to draw");
    }
  }
  if ((scene.field == nullptr) == (scene.labels == nullptr)) {
    return absl::InvalidArgumentError(
        "previews: give exactly one of a field and a label map");
  }
  const size_t voxels = static_cast<size_t>(scene.grid.VoxelCount());
  if (scene.field != nullptr && scene.field->data.size() != voxels) {
    return absl::InvalidArgumentError(
        "previews: the field does not hold one value per voxel of the grid");
  }
  if (scene.labels != nullptr && scene.labels->data.size() != voxels) {
    return absl::InvalidArgumentError(
        "previews: the label map does not hold one value per voxel of the "
        "grid");
  }
  if (scene.field != nullptr && scene.objects.size() != 1) {
    return absl::InvalidArgumentError(
        "previews: a field is one object: give exactly one");
  }
  for (double k : scene.marked_slices) {
    if (!std::isfinite(k)) {
      return absl::InvalidArgumentError(
          "previews: a marked slice position is not finite");
    }
  }
  if (scene.window.has_value() &&
      !(scene.window->width > 0 && std::isfinite(scene.window->width) &&
        std::isfinite(scene.window->center))) {
    return absl::InvalidArgumentError(
        "previews: the window's width must be positive");
  }
  if (!(options.min_size >= 16 && options.min_size <= options.max_size &&
        options.max_size <= 8192)) {
    return absl::InvalidArgumentError(
        "previews: sizes must satisfy 16 <= min_size <= max_size <= 8192");
  }
  return absl::OkStatus();
}

// The patient axis (0 = L, 1 = P, 2 = S) of each grid axis: the assignment
// with the largest sum of |cosines| (ties: the first permutation).
std::array<int, 3> PatientAxes(const Grid& grid) {
  std::array<int, 3> perm = {0, 1, 2}, best = perm;
  double best_score = -1;
  do {
    double score = 0;
    for (int a = 0; a < 3; ++a) score += std::abs(grid.Axis(a)[perm[a]]);
    if (score > best_score + 1e-12) {
      best_score = score;
      best = perm;
    }
  } while (std::next_permutation(perm.begin(), perm.end()));
  return best;
}

// How many object voxels lie in each plane along each axis.
struct ObjectCounts {
  std::array<std::vector<int64_t>, 3> per_plane;
  int64_t total = 0;
};

ObjectCounts CountObject(const PreviewScene& scene) {
  const Grid& g = scene.grid;
  const int64_t nx = g.size[0], ny = g.size[1], nz = g.size[2];
  std::vector<bool> wanted;
  if (scene.labels != nullptr) {
    wanted.assign(65536, false);
    for (const PreviewObject& o : scene.objects) {
      if (o.label >= 1 && o.label <= 65535) wanted[o.label] = true;
    }
  }
  // Per slice, its own counts along i and j: integer sums, so the totals
  // do not depend on how the slices are shared among threads.
  std::vector<std::vector<int64_t>> along_i(nz), along_j(nz);
  tbb::parallel_for(int64_t{0}, nz, [&](int64_t k) {
    std::vector<int64_t> ci(nx, 0), cj(ny, 0);
    for (int64_t j = 0; j < ny; ++j) {
      const int64_t row = g.LinearIndex(0, j, k);
      for (int64_t i = 0; i < nx; ++i) {
        const bool in =
            scene.field != nullptr
                ? scene.field->data[row + i] >= 0
                : static_cast<bool>(wanted[scene.labels->data[row + i]]);
        if (in) {
          ++ci[i];
          ++cj[j];
        }
      }
    }
    along_i[k] = std::move(ci);
    along_j[k] = std::move(cj);
  });
  ObjectCounts counts;
  counts.per_plane[0].assign(nx, 0);
  counts.per_plane[1].assign(ny, 0);
  counts.per_plane[2].assign(nz, 0);
  for (int64_t k = 0; k < nz; ++k) {
    for (int64_t i = 0; i < nx; ++i) {
      counts.per_plane[0][i] += along_i[k][i];
      counts.per_plane[2][k] += along_i[k][i];
    }
    for (int64_t j = 0; j < ny; ++j) counts.per_plane[1][j] += along_j[k][j];
    counts.total += counts.per_plane[2][k];
  }
  return counts;
}

// The plane along `axis` through the object's centroid, or the nearest that
// holds some of it; the grid's middle without an object.
int64_t ChoosePlane(const ObjectCounts& counts, int axis, int64_t size) {
  if (counts.total == 0) return size / 2;
  const std::vector<int64_t>& c = counts.per_plane[axis];
  // sum(index * count) fits: at most 2^20 planes of 2^40 voxels.
  __int128 moment = 0;
  for (int64_t n = 0; n < size; ++n) moment += static_cast<__int128>(n) * c[n];
  const int64_t centre = static_cast<int64_t>(
      (2 * moment + counts.total) / (2 * static_cast<__int128>(counts.total)));
  const int64_t start = std::clamp<int64_t>(centre, 0, size - 1);
  for (int64_t d = 0; d < size; ++d) {
    if (start - d >= 0 && c[start - d] > 0) return start - d;
    if (start + d < size && c[start + d] > 0) return start + d;
  }
  return start;
}

DisplayWindow ChooseWindow(const PreviewScene& scene,
                           const std::vector<const Volume<float>*>& planes) {
  if (scene.window.has_value()) {
    const double lo = scene.window->center - scene.window->width / 2;
    const double hi = scene.window->center + scene.window->width / 2;
    bool shows_all = true;
    for (double v : scene.window_must_show) {
      if (!(v > lo && v < hi)) shows_all = false;
    }
    if (shows_all) return *scene.window;
  }
  std::vector<float> values;
  for (const Volume<float>* p : planes) {
    for (float v : p->data) {
      if (std::isfinite(v)) values.push_back(v);
    }
  }
  double lo = 0, hi = 1;
  if (!values.empty()) {
    const size_t a = values.size() / 100;
    const size_t b = values.size() - 1 - values.size() / 100;
    std::nth_element(values.begin(), values.begin() + a, values.end());
    lo = values[a];
    std::nth_element(values.begin(), values.begin() + b, values.end());
    hi = values[b];
  }
  for (double v : scene.window_must_show) {
    if (std::isfinite(v)) {
      lo = std::min(lo, v);
      hi = std::max(hi, v);
    }
  }
  const double margin = 0.05 * (hi - lo);
  lo -= margin;
  hi += margin;
  if (!(hi > lo)) hi = lo + 1;
  return {(lo + hi) / 2, hi - lo};
}

}  // namespace

absl::StatusOr<PreviewSet> RenderPreviews(const PreviewScene& scene,
                                          const PreviewOptions& options,
                                          const ComputeContext& context) {
  INTERSLICE_RETURN_IF_ERROR(CheckScene(scene, options));
  INTERSLICE_ASSIGN_OR_RETURN(const LegendFont* font,
                              LegendFont::Get(options.font_path));
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  const Grid& grid = scene.grid;
  PreviewSet set;

  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  ObjectCounts counts;
  arena.execute([&] { counts = CountObject(scene); });
  if (counts.total == 0) {
    set.notes.push_back(
        "the object is empty: the previews show no outline and no surface");
  } else if (scene.labels != nullptr) {
    std::vector<bool> present(65536, false);
    for (uint16_t v : scene.labels->data) present[v] = true;
    for (const PreviewObject& o : scene.objects) {
      if (o.label < 1 || o.label > 65535 || !present[o.label]) {
        set.notes.push_back(absl::StrFormat(
            "label %d is empty: the previews show no outline of it", o.label));
      }
    }
  }

  // The views: axial, coronal, sagittal (normals: the grid axes closest to
  // S, P and L), each oriented as a radiologist reads it.
  const std::array<int, 3> patient = PatientAxes(grid);
  struct Convention {
    const char* name;
    int normal_patient_axis;
    int right_axis, right_sign, down_axis, down_sign;
  };
  constexpr Convention kConventions[] = {
      {"axial", 2, 0, +1, 1, +1},     // from the feet: L right, P down
      {"coronal", 1, 0, +1, 2, -1},   // from the front: L right, I down
      {"sagittal", 0, 1, +1, 2, -1},  // from the left: P right, I down
  };
  std::vector<PlaneView> views;
  for (const Convention& c : kConventions) {
    PlaneView view;
    view.name = c.name;
    for (int a = 0; a < 3; ++a) {
      if (patient[a] == c.normal_patient_axis) view.normal = a;
    }
    for (int a = 0; a < 3; ++a) {
      if (a == view.normal) continue;
      if (patient[a] == c.right_axis) {
        view.h = a;
        view.flip_h = grid.Axis(a)[c.right_axis] * c.right_sign < 0;
      } else {
        view.v = a;
        view.flip_v = grid.Axis(a)[c.down_axis] * c.down_sign < 0;
      }
    }
    view.index = ChoosePlane(counts, view.normal, grid.size[view.normal]);
    views.push_back(view);
  }

  // One scale for every view (preview.h, "Display scale").
  const double finest =
      std::min({grid.spacing[0], grid.spacing[1], grid.spacing[2]});
  double length[3];
  double longest = 0;
  for (int a = 0; a < 3; ++a) {
    double stretch = grid.spacing[a] / finest;
    if (stretch < kSameSpacing) stretch = 1;
    length[a] = grid.size[a] * stretch;
    longest = std::max(longest, length[a]);
  }
  double zoom = 1;
  if (longest > options.max_size) zoom = options.max_size / longest;
  if (longest < options.min_size) zoom = options.min_size / longest;
  AxisPixels pixels;
  for (int a = 0; a < 3; ++a) {
    pixels[a] = std::max(1, static_cast<int>(std::lround(length[a] * zoom)));
  }
  const double mm_per_pixel = finest / zoom;

  // The planes' grey values, then the window they share.
  std::vector<Volume<float>> planes(views.size());
  std::vector<absl::Status> status(views.size() + 1);
  if (scene.intensity) {
    arena.execute([&] {
      tbb::parallel_for(size_t{0}, views.size(), [&](size_t n) {
        VoxelBox box{{0, 0, 0}, grid.size};
        box.begin[views[n].normal] = views[n].index;
        box.end[views[n].normal] = views[n].index + 1;
        absl::StatusOr<Volume<float>> plane = scene.intensity(box);
        if (!plane.ok()) {
          status[n] = plane.status();
          return;
        }
        const Grid expected = CropGrid(grid, box);
        if (plane->grid.size != expected.size ||
            static_cast<int64_t>(plane->data.size()) != expected.VoxelCount()) {
          status[n] = absl::InternalError(
              "previews: the intensity sampler returned a plane of another "
              "size");
          return;
        }
        planes[n] = *std::move(plane);
      });
    });
    for (const absl::Status& s : status) INTERSLICE_RETURN_IF_ERROR(s);
  }
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  std::vector<const Volume<float>*> plane_pointers;
  for (const Volume<float>& p : planes) plane_pointers.push_back(&p);
  const DisplayWindow window = ChooseWindow(scene, plane_pointers);

  Legend common;
  common.lines = scene.legend;
  bool any_surface = false;
  for (const PreviewObject& o : scene.objects) {
    if (o.surface != nullptr) any_surface = true;
  }
  std::vector<std::optional<PreviewImage>> images(views.size() + 1);
  arena.execute([&] {
    tbb::task_group group;
    for (size_t n = 0; n < views.size(); ++n) {
      group.run([&, n] {
        if (absl::Status s = context.CheckCancelled(); !s.ok()) {
          status[n] = s;
          return;
        }
        absl::StatusOr<PreviewImage> image = preview_internal::RenderPlaneView(
            scene, views[n], pixels, planes[n], window, common, *font);
        if (image.ok()) {
          images[n] = *std::move(image);
        } else {
          status[n] = image.status();
        }
      });
    }
    if (any_surface) {
      group.run([&] {
        absl::StatusOr<PreviewImage> image = preview_internal::RenderFrontView(
            scene, mm_per_pixel, options, common, *font, context);
        if (image.ok()) {
          images.back() = *std::move(image);
        } else {
          status.back() = image.status();
        }
      });
    }
    group.wait();
  });
  // A cancellation wins over any other failure it caused.
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  for (const absl::Status& s : status) INTERSLICE_RETURN_IF_ERROR(s);
  for (std::optional<PreviewImage>& image : images) {
    if (image.has_value()) set.images.push_back(*std::move(image));
  }
  return set;
}

}  // namespace interslice

// Previews (issue 28): what a job made, as pictures a person reads at a
// glance in any image viewer or PACS. Three views through the object on the
// job's output grid and one of its surface, each with a legend burned in:
//
// - Three orthogonal planes of the output grid (multi-planar reformats of
//   the grey values, e.g. the intensity series), each through the object's
//   centre: the object's outline drawn on them in colour, and the original
//   (or key) slices marked by ticks beside every view that cuts across them.
//   The planes are index planes of the grid, so the original slices (planes
//   of constant slice index) are straight rows or columns and nothing is
//   resampled but the display scale.
// - A shaded 3D view of the surfaces, seen from the front (from anterior,
//   the patient's right on the image's left, head up), orthographic.
//
// Rendering: Cairo (image surfaces, anti-aliased lines, text through
// FreeType with one font file, PNG) for the 2D views and the legends;
// OpenVDB's LevelSetRayIntersector on the same narrow-band level set the
// mesher builds (core/surface) for the 3D view, shaded by Lambert's cosine
// law. No display, no GPU, no fontconfig lookup. docs/DESIGN.md says why.
//
// Conventions (core/geometry/volume.h): grid index (i, j, k), LPS mm.
//
// Which plane is which: each grid axis is named by the patient axis it is
// closest to (the assignment of grid axes to L, P, S that maximises the sum
// of |cosines|). The plane normal to the axis closest to S is "axial", to P
// "coronal", to L "sagittal". Each is shown as a radiologist expects:
// axial from the feet (patient's left on the image's right, anterior up),
// coronal from the front (left on the right, head up), sagittal from the
// patient's left (anterior on the left, head up), as far as the grid's
// axes allow (each image axis is a grid axis, flipped as needed).
//
// Display scale: one scale for all views, in mm per pixel; each grid axis
// whose spacing is within 5% of the finest one is shown at one pixel per
// sample (no resampling blur on a nearly isotropic grid), coarser axes
// stretched to their true length (bilinear, Cairo's GOOD filter). The
// longest side of a view is then scaled into [min_size, max_size].
//
// Plane positions: each plane goes through the object's centroid (rounded
// to a grid index); if that plane holds none of the object, the nearest
// plane that does. No object at all: the grid's centre.
//
// Window (grey levels): the source's window when every value in
// window_must_show (e.g. the threshold) lies inside it; otherwise the 1st to
// 99th percentile of the three planes' values, widened to include those
// values. The legend says which window was used.
//
// Determinism: the same scene and options give the same pixels whatever
// context.threads (each pixel is computed by one task; reductions are
// integer sums). The font (DejaVu Sans from fonts-dejavu-core) is rendered
// without hinting, so text does not depend on fontconfig's configuration.
// Pixels depend on the Cairo, pixman, FreeType and OpenVDB builds, so pin
// pixel hashes only within one machine's build.
//
// No patient data is ever drawn: the legend holds what the caller gives
// (the job's method, thresholds, grid) and what this module computes.
#ifndef INTERSLICE_CORE_PREVIEW_PREVIEW_H_
#define INTERSLICE_CORE_PREVIEW_PREVIEW_H_

#include <array>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "core/common/compute.h"
#include "core/geometry/volume.h"

namespace interslice {

// The grey values of the scene's grid on `box` (one voxel thick along one
// axis: a plane), as a volume on CropGrid(grid, box), modality units (HU for
// CT). Called once per 2D view, possibly from several threads at once.
using PreviewPlaneSampler =
    std::function<absl::StatusOr<Volume<float>>(const VoxelBox& box)>;

// An object of the previews: its outline on the planes and its surface in
// the 3D view, in one colour.
struct PreviewObject {
  // Its value in PreviewScene::labels (ignored with PreviewScene::field).
  int label = 0;
  std::array<uint8_t, 3> rgb = {60, 230, 60};
  // Its surface for the 3D view: a field, positive inside (the zero level is
  // the surface), on a box of the scene's grid (same spacing and direction,
  // origin on a grid node, any size within the grid), e.g. the job's field
  // or a fill's per-label field. Null: not in the 3D view. Not owned.
  const Volume<float>* surface = nullptr;
  // Legend text beside its colour, e.g. ">= 300 HU" or "label 3" (no
  // patient data: segment names typed by a person are not drawn).
  std::string name;
};

struct DisplayWindow {
  double center = 0;
  double width = 0;  // > 0
};

struct PreviewScene {
  // The output grid; the planes are its index planes.
  Grid grid;
  // Grey values on a plane of `grid`; empty = black planes.
  PreviewPlaneSampler intensity;
  // The source's window, if it has one (see "Window" above).
  std::optional<DisplayWindow> window;
  std::vector<double> window_must_show;
  // The objects on the planes: exactly one of `field` (one object, inside
  // where field >= 0, as the job's mask; objects[0] gives its colour) and
  // `labels` (inside object n where labels == objects[n].label; labels not
  // in `objects` are not drawn). Either must be on `grid`. Not owned.
  const Volume<float>* field = nullptr;
  const Volume<uint16_t>* labels = nullptr;
  std::vector<PreviewObject> objects;
  // Positions of the original slices (or a fill's key slices) as continuous
  // slice indices of `grid` (k, along grid axis 2), each marked by a tick in
  // the margins of every view whose plane contains axis 2, on the image row
  // (or column) whose pixel holds that position. `marked_slices_name` is
  // their legend text.
  std::vector<double> marked_slices;
  std::string marked_slices_name = "original slices";
  // Legend lines common to every view, the first one its title (e.g.
  // "interslice: interpolated between 28 original slices, not acquired").
  // Printable ASCII; the views add their own lines.
  std::vector<std::string> legend;
};

struct PreviewOptions {
  // The longest side of a view's picture is scaled into [min_size,
  // max_size] pixels (margins and legend come on top).
  int min_size = 384;
  int max_size = 1024;
  // The legend's TrueType font.
  std::string font_path = "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf";
};

// One rendered view.
struct PreviewImage {
  // "axial", "coronal", "sagittal" (the 2D views, named as above) or
  // "3d-front".
  std::string name;
  int width = 0, height = 0;
  // 8-bit RGB, rows from the top, 3 bytes per pixel, no padding.
  std::vector<uint8_t> rgb;
  // What it shows, one line (e.g. "axial plane: grid slice 150 of 298"),
  // and the legend lines burned into it.
  std::string description;
  std::vector<std::string> legend;
  // DICOM PatientOrientation (0020,0020) of the picture: the patient
  // directions of its rows (left to right) and columns (top to bottom),
  // e.g. "L\P" for an axial view; oblique axes give up to three letters.
  std::string patient_orientation;
  // The picture: pixels [x0, x1) x [y0, y1); the rest is margins and legend.
  int x0 = 0, y0 = 0, x1 = 0, y1 = 0;
  // What the pixel (x, y) of the picture shows, its centre at (x + 0.5,
  // y + 0.5): at = origin + (x + 0.5) * per_x + (y + 0.5) * per_y. 2D
  // views: a continuous grid index (i, j, k) (one component constant: the
  // plane). 3D view: a point in LPS mm on the view plane, which the view
  // sees along `view_direction` (unit, LPS).
  Vec3 origin = {0, 0, 0}, per_x = {0, 0, 0}, per_y = {0, 0, 0};
  Vec3 view_direction = {0, 0, 0};
  // 2D views: the grid axis normal to the plane and the plane's index; -1
  // for the 3D view.
  int plane_axis = -1;
  int64_t plane_index = 0;
};

struct PreviewSet {
  // axial, coronal, sagittal, 3d-front (the 3D view only when an object
  // has a surface field).
  std::vector<PreviewImage> images;
  // Things a person should know, one sentence each (e.g. "the object is
  // empty: the previews show no outline and no surface"). No patient data.
  std::vector<std::string> notes;
};

// Renders the previews. Errors: INVALID_ARGUMENT for an invalid grid, no or
// both of field/labels, a field or label map not on the grid, a surface
// field not on a box of the grid, bad options; FAILED_PRECONDITION when the
// font cannot be loaded; errors of the intensity sampler as they come;
// CANCELLED / DEADLINE_EXCEEDED from context (polled between views and
// rows). Threads: context.threads (0 = all); the pixels do not depend on
// them. Memory: the planes, the pictures, and one narrow-band level set per
// surface (the mesher's, core/surface).
absl::StatusOr<PreviewSet> RenderPreviews(const PreviewScene& scene,
                                          const PreviewOptions& options,
                                          const ComputeContext& context);

// The picture as PNG bytes (8-bit RGB, Cairo's encoder; no time stamp, so
// the same pixels give the same bytes). INTERNAL if encoding fails.
absl::StatusOr<std::string> EncodePng(const PreviewImage& image);

// Writes each image as `<folder>/<name>.png`, replacing an older folder only
// once the new one is complete (written into a sibling temporary folder,
// synced, then renamed into place). Returns the paths, in image order.
// INTERNAL naming the path on failure.
absl::StatusOr<std::vector<std::string>> WritePreviewPngs(
    const std::vector<PreviewImage>& images, const std::string& folder);

}  // namespace interslice

#endif  // INTERSLICE_CORE_PREVIEW_PREVIEW_H_

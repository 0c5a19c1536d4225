// Private to core/preview: the parts of RenderPreviews (preview.cc) shared
// by its 2D views (view_2d.cc), its 3D view (view_3d.cc) and the canvas with
// its legend (canvas.cc). Includes Cairo: include it only from core/preview.
#ifndef INTERSLICE_CORE_PREVIEW_PREVIEW_INTERNAL_H_
#define INTERSLICE_CORE_PREVIEW_PREVIEW_INTERNAL_H_

#include <cairo.h>

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "core/preview/preview.h"

namespace interslice::preview_internal {

using Rgb = std::array<uint8_t, 3>;

// Colours every view uses.
inline constexpr Rgb kBackground = {16, 16, 16};
inline constexpr Rgb kText = {235, 235, 235};
inline constexpr Rgb kTick = {255, 200, 0};

// Margin around every picture, pixels: the ticks of marked slices are drawn
// in it (kTickInset pixels from each side of it).
inline constexpr int kMargin = 12;
inline constexpr int kTickInset = 2;

// A legend entry with a colour: a small filled square (an object's outline
// or surface colour) or a short horizontal tick (marked slices).
struct Swatch {
  Rgb rgb;
  std::string text;
  bool tick = false;
};

struct Legend {
  std::vector<std::string> lines;
  std::vector<Swatch> swatches;
};

// The legend's font: DejaVu Sans (or options.font_path) loaded through
// FreeType, unhinted, as a Cairo font face. Loaded once per path and kept
// for the process (Cairo caches scaled fonts beyond any one call and locks
// the face itself, so views on several threads share it).
class LegendFont {
 public:
  // FAILED_PRECONDITION naming the file when it cannot be loaded (a failed
  // load is not remembered: the next call tries again).
  static absl::StatusOr<const LegendFont*> Get(const std::string& path);
  LegendFont(const LegendFont&) = delete;
  LegendFont& operator=(const LegendFont&) = delete;

  // Selects the font at `pixels` size on `cr`, unhinted and grey
  // anti-aliased (not the screen's settings: the same pixels everywhere).
  void Use(cairo_t* cr, double pixels) const;

 private:
  LegendFont() = default;
  cairo_font_face_t* face_ = nullptr;
};

// Where a picture of `picture_w` x `picture_h` pixels, its margins and the
// legend go on the canvas: the picture centred horizontally, the legend
// below it; the canvas is at least as wide as the legend's longest line.
struct Layout {
  int width = 0, height = 0;  // the canvas
  int x0 = 0, y0 = 0;         // the picture's top-left pixel
  int picture_w = 0, picture_h = 0;
  int legend_y = 0;  // the legend's first baseline area
};
Layout LayOut(const LegendFont& font, int picture_w, int picture_h,
              const Legend& legend);

// A canvas of layout.width x layout.height filled with kBackground.
struct CairoSurfaceDeleter {
  void operator()(cairo_surface_t* s) const { cairo_surface_destroy(s); }
};
struct CairoDeleter {
  void operator()(cairo_t* cr) const { cairo_destroy(cr); }
};
using SurfacePtr = std::unique_ptr<cairo_surface_t, CairoSurfaceDeleter>;
using ContextPtr = std::unique_ptr<cairo_t, CairoDeleter>;
SurfacePtr NewCanvas(const Layout& layout);

// Draws the legend below the picture (lines, then the swatches flowing left
// to right, wrapping at the canvas width).
void DrawLegend(cairo_t* cr, const LegendFont& font, const Layout& layout,
                const Legend& legend);

// Draws the patient-direction letters (e.g. "R", "A") at the middle of the
// picture's left, right, top and bottom edges, inside it.
void DrawEdgeLetters(cairo_t* cr, const LegendFont& font, const Layout& layout,
                     const std::array<std::string, 4>& left_right_top_bottom);

// A small note centred on the picture (e.g. "no surface").
void DrawCentredNote(cairo_t* cr, const LegendFont& font, const Layout& layout,
                     const std::string& text);

void SetColour(cairo_t* cr, const Rgb& rgb, double alpha = 1.0);

// The canvas's pixels as 8-bit RGB rows (PreviewImage::rgb).
std::vector<uint8_t> SurfaceToRgb(cairo_surface_t* surface);

// The patient direction letters of a unit LPS vector: DICOM's (L/R, P/A,
// H/F) of its components above 1% in order of magnitude (at most three;
// PatientOrientation), or the burned-in letter of its largest component
// (L/R, P/A, S/I).
std::string DicomDirectionLetters(const Vec3& direction);
std::string DisplayDirectionLetter(const Vec3& direction);

// A 2D view: the plane of grid index `index` along grid axis `normal`,
// grid axis `h` along the picture's x (left to right), `v` along its y (top
// to bottom), each flipped as needed to follow the radiological convention
// (preview.h).
struct PlaneView {
  std::string name;  // "axial", "coronal", "sagittal"
  int normal = 2;
  int h = 0, v = 1;
  bool flip_h = false, flip_v = false;
  int64_t index = 0;
};

// The picture's length in pixels along each grid axis (the same in every
// view, so the views share one scale).
using AxisPixels = std::array<int, 3>;

// Renders `view`: `plane` holds the grey values (CropGrid of the scene's
// grid at the plane; empty data = black), `window` maps them to grey,
// `common` is the legend every view shares.
absl::StatusOr<PreviewImage> RenderPlaneView(
    const PreviewScene& scene, const PlaneView& view, const AxisPixels& pixels,
    const Volume<float>& plane, const DisplayWindow& window,
    const Legend& common, const LegendFont& font);

// Renders the surfaces of scene.objects seen from the front (preview.h),
// at `mm_per_pixel` unless that puts the longer side outside [min_size,
// max_size]. Threads: the caller's arena.
absl::StatusOr<PreviewImage> RenderFrontView(const PreviewScene& scene,
                                             double mm_per_pixel,
                                             const PreviewOptions& options,
                                             const Legend& common,
                                             const LegendFont& font,
                                             const ComputeContext& context);

}  // namespace interslice::preview_internal

#endif  // INTERSLICE_CORE_PREVIEW_PREVIEW_INTERNAL_H_

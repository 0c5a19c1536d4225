// The 2D views: a plane of the output grid in grey, the objects' outlines
// (ITK's marching squares on the plane, stroked by Cairo with anti-aliased
// lines at sub-pixel positions), the marked slices as ticks in the margins,
// the patient directions at the edges and the legend.
#include <cairo.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <optional>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/preview/preview_internal.h"
#include "itkContourExtractor2DImageFilter.h"
#include "itkImage.h"

namespace interslice::preview_internal {
namespace {

using PlaneImage = itk::Image<float, 2>;
using ContourFilter = itk::ContourExtractor2DImageFilter<PlaneImage>;

constexpr double kOutlineWidth = 1.5;  // pixels

const char* AxisIndexName(int axis) {
  return axis == 0 ? "column i" : axis == 1 ? "row j" : "slice k";
}

// The plane in picture order: sample (p, q), p along the picture's x and q
// along its y, is grid index g with g[view.normal] = `fixed`.
struct PlaneSampling {
  const PlaneView& view;
  const Grid& grid;
  int64_t nh, nv;
  Index3 Index(int64_t p, int64_t q, int64_t fixed) const {
    Index3 g{};
    g[view.normal] = fixed;
    g[view.h] = view.flip_h ? nh - 1 - p : p;
    g[view.v] = view.flip_v ? nv - 1 - q : q;
    return g;
  }
};

// One object on the plane in picture order: values whose contour at `level`
// is its outline (inside where value > level).
struct ObjectPlane {
  std::vector<float> values;  // nh * nv
  double level = 0;
  // Beyond the plane's edge: the mirror of the inside value (so the outline
  // closes halfway between the last sample and the edge, as the picture
  // ends there), or `outside` for an indicator.
  bool mirror_at_edge = false;
  float outside = 0;
};

// Outlines of `object` as polylines in picture-sample coordinates.
absl::StatusOr<std::vector<std::vector<std::array<double, 2>>>> Outline(
    const ObjectPlane& object, int64_t nh, int64_t nv) {
  std::vector<std::vector<std::array<double, 2>>> lines;
  int64_t p0 = nh, p1 = -1, q0 = nv, q1 = -1;
  for (int64_t q = 0; q < nv; ++q) {
    for (int64_t p = 0; p < nh; ++p) {
      if (object.values[q * nh + p] > object.level) {
        p0 = std::min(p0, p);
        p1 = std::max(p1, p);
        q0 = std::min(q0, q);
        q1 = std::max(q1, q);
      }
    }
  }
  if (p1 < 0) return lines;
  // The box of inside samples grown by one sample; samples beyond the plane
  // are padding.
  const int64_t b0 = p0 - 1, c0 = q0 - 1;
  const int64_t w = p1 - p0 + 3, h = q1 - q0 + 3;
  auto image = PlaneImage::New();
  PlaneImage::RegionType region;
  region.SetSize(
      {static_cast<itk::SizeValueType>(w), static_cast<itk::SizeValueType>(h)});
  image->SetRegions(region);
  image->Allocate();
  float* buffer = image->GetBufferPointer();
  for (int64_t y = 0; y < h; ++y) {
    for (int64_t x = 0; x < w; ++x) {
      const int64_t p = b0 + x, q = c0 + y;
      float value;
      if (p >= 0 && p < nh && q >= 0 && q < nv) {
        value = object.values[q * nh + p];
      } else if (object.mirror_at_edge) {
        const int64_t pe = std::clamp<int64_t>(p, 0, nh - 1);
        const int64_t qe = std::clamp<int64_t>(q, 0, nv - 1);
        const float inner = object.values[qe * nh + pe];
        value = -std::max(std::abs(inner), 1e-6f);
      } else {
        value = object.outside;
      }
      buffer[y * w + x] = value;
    }
  }
  auto filter = ContourFilter::New();
  filter->SetInput(image);
  filter->SetContourValue(object.level);
  filter->VertexConnectHighPixelsOn();
  try {
    filter->Update();
  } catch (const itk::ExceptionObject& e) {
    return absl::InternalError(
        absl::StrCat("previews: outline failed: ", e.GetDescription()));
  }
  for (unsigned n = 0; n < filter->GetNumberOfIndexedOutputs(); ++n) {
    const auto* vertices = filter->GetOutput(n)->GetVertexList();
    std::vector<std::array<double, 2>> line;
    line.reserve(vertices->Size());
    for (unsigned k = 0; k < vertices->Size(); ++k) {
      const auto& v = vertices->ElementAt(k);
      line.push_back(
          {v[0] + static_cast<double>(b0), v[1] + static_cast<double>(c0)});
    }
    if (line.size() >= 2) lines.push_back(std::move(line));
  }
  return lines;
}

uint8_t Grey(float value, const DisplayWindow& window) {
  const double low = window.center - window.width / 2;
  const double t = (value - low) / window.width;
  return static_cast<uint8_t>(std::lround(std::clamp(t, 0.0, 1.0) * 255.0));
}

}  // namespace

absl::StatusOr<PreviewImage> RenderPlaneView(
    const PreviewScene& scene, const PlaneView& view, const AxisPixels& pixels,
    const Volume<float>& plane, const DisplayWindow& window,
    const Legend& common, const LegendFont& font) {
  const Grid& grid = scene.grid;
  const int64_t nh = grid.size[view.h], nv = grid.size[view.v];
  const int wh = pixels[view.h], wv = pixels[view.v];
  const PlaneSampling sampling{view, grid, nh, nv};

  // The legend: what every view says, then this view's plane and window,
  // then the colours.
  Legend legend = common;
  std::string where = absl::StrFormat("%s: %s = %d of %d", view.name,
                                      AxisIndexName(view.normal), view.index,
                                      grid.size[view.normal]);
  if (view.normal == 2 && !scene.marked_slices.empty()) {
    double nearest = std::numeric_limits<double>::infinity();
    for (double k : scene.marked_slices) {
      nearest = std::min(nearest, std::abs(k - view.index) * grid.spacing[2]);
    }
    if (nearest < 1e-3) {
      absl::StrAppend(&where, ", on one of the ", scene.marked_slices_name);
    } else {
      absl::StrAppend(&where,
                      absl::StrFormat(", %.3g mm from the nearest of the %s",
                                      nearest, scene.marked_slices_name));
    }
  }
  absl::StrAppend(&where, absl::StrFormat("; window %.4g / %.4g", window.center,
                                          window.width));
  legend.lines.push_back(where);
  for (const PreviewObject& object : scene.objects) {
    legend.swatches.push_back({object.rgb, object.name, false});
  }
  const bool shows_slices =
      (view.h == 2 || view.v == 2) && !scene.marked_slices.empty();
  if (shows_slices) {
    legend.swatches.push_back({kTick,
                               absl::StrCat(scene.marked_slices_name, " (",
                                            scene.marked_slices.size(), ")"),
                               true});
  }

  const Layout layout = LayOut(font, wh, wv, legend);
  SurfacePtr canvas = NewCanvas(layout);
  ContextPtr cr(cairo_create(canvas.get()));

  // Grey values, in picture order, scaled to the picture.
  {
    SurfacePtr grey(cairo_image_surface_create(
        CAIRO_FORMAT_RGB24, static_cast<int>(nh), static_cast<int>(nv)));
    cairo_surface_flush(grey.get());
    unsigned char* data = cairo_image_surface_get_data(grey.get());
    const int stride = cairo_image_surface_get_stride(grey.get());
    const bool has_values = !plane.data.empty();
    for (int64_t q = 0; q < nv; ++q) {
      uint32_t* row = reinterpret_cast<uint32_t*>(data + q * stride);
      for (int64_t p = 0; p < nh; ++p) {
        Index3 g = sampling.Index(p, q, 0);
        const uint8_t v =
            has_values ? Grey(plane.at(g[0], g[1], g[2]), window) : uint8_t{0};
        row[p] = (uint32_t{v} << 16) | (uint32_t{v} << 8) | v;
      }
    }
    cairo_surface_mark_dirty(grey.get());
    cairo_save(cr.get());
    cairo_rectangle(cr.get(), layout.x0, layout.y0, wh, wv);
    cairo_clip(cr.get());
    cairo_translate(cr.get(), layout.x0, layout.y0);
    cairo_scale(cr.get(), static_cast<double>(wh) / nh,
                static_cast<double>(wv) / nv);
    cairo_set_source_surface(cr.get(), grey.get(), 0, 0);
    cairo_pattern_t* pattern = cairo_get_source(cr.get());
    cairo_pattern_set_filter(pattern, CAIRO_FILTER_GOOD);
    cairo_pattern_set_extend(pattern, CAIRO_EXTEND_PAD);
    cairo_paint(cr.get());
    cairo_restore(cr.get());
  }

  // Outlines, clipped to the picture.
  cairo_save(cr.get());
  cairo_rectangle(cr.get(), layout.x0, layout.y0, wh, wv);
  cairo_clip(cr.get());
  cairo_set_line_width(cr.get(), kOutlineWidth);
  cairo_set_line_join(cr.get(), CAIRO_LINE_JOIN_ROUND);
  cairo_set_line_cap(cr.get(), CAIRO_LINE_CAP_ROUND);
  const double sx = static_cast<double>(wh) / nh;
  const double sy = static_cast<double>(wv) / nv;
  for (const PreviewObject& object : scene.objects) {
    ObjectPlane values;
    values.values.resize(static_cast<size_t>(nh * nv));
    for (int64_t q = 0; q < nv; ++q) {
      for (int64_t p = 0; p < nh; ++p) {
        const Index3 g = sampling.Index(p, q, view.index);
        const int64_t n = grid.LinearIndex(g[0], g[1], g[2]);
        values.values[q * nh + p] =
            scene.field != nullptr
                ? scene.field->data[n]
                : (scene.labels->data[n] == object.label ? 1.0f : 0.0f);
      }
    }
    if (scene.field != nullptr) {
      // Inside is field >= 0 (as the job's mask): contour just below zero
      // so that samples exactly at zero count as inside.
      values.level = std::nextafter(0.0, -1.0);
      values.mirror_at_edge = true;
    } else {
      values.level = 0.5;
      values.outside = 0;
    }
    absl::StatusOr<std::vector<std::vector<std::array<double, 2>>>> lines =
        Outline(values, nh, nv);
    if (!lines.ok()) return lines.status();
    SetColour(cr.get(), object.rgb);
    for (const auto& line : *lines) {
      for (size_t n = 0; n < line.size(); ++n) {
        const double x = layout.x0 + (line[n][0] + 0.5) * sx;
        const double y = layout.y0 + (line[n][1] + 0.5) * sy;
        if (n == 0) {
          cairo_move_to(cr.get(), x, y);
        } else {
          cairo_line_to(cr.get(), x, y);
        }
      }
      if (line.size() > 2 && line.front() == line.back()) {
        cairo_close_path(cr.get());
      }
      cairo_stroke(cr.get());
    }
    if (scene.field != nullptr) break;  // one object
  }
  cairo_restore(cr.get());

  // Marked slices: a crisp tick on each side of the picture, in the margin,
  // on the row (or column) whose pixel holds the slice's position.
  if (shows_slices) {
    cairo_save(cr.get());
    cairo_set_antialias(cr.get(), CAIRO_ANTIALIAS_NONE);
    SetColour(cr.get(), kTick);
    const bool vertical = view.v == 2;
    const int64_t n = vertical ? nv : nh;
    const bool flip = vertical ? view.flip_v : view.flip_h;
    const double scale = vertical ? sy : sx;
    const int length = kMargin - 2 * kTickInset;
    for (double k : scene.marked_slices) {
      if (k < -0.5 || k > n - 0.5) continue;
      const double c = flip ? n - 1 - k : k;
      const int pixel = static_cast<int>(std::floor((c + 0.5) * scale));
      if (pixel < 0 || pixel >= (vertical ? wv : wh)) continue;
      if (vertical) {
        const int y = layout.y0 + pixel;
        cairo_rectangle(cr.get(), layout.x0 - kMargin + kTickInset, y, length,
                        1);
        cairo_rectangle(cr.get(), layout.x0 + wh + kTickInset, y, length, 1);
      } else {
        const int x = layout.x0 + pixel;
        cairo_rectangle(cr.get(), x, layout.y0 - kMargin + kTickInset, 1,
                        length);
        cairo_rectangle(cr.get(), x, layout.y0 + wv + kTickInset, 1, length);
      }
    }
    cairo_fill(cr.get());
    cairo_restore(cr.get());
  }

  // Patient directions: the picture's x runs along +/- grid axis h.
  Vec3 right = grid.Axis(view.h), down = grid.Axis(view.v);
  for (int c = 0; c < 3; ++c) {
    if (view.flip_h) right[c] = -right[c];
    if (view.flip_v) down[c] = -down[c];
  }
  const Vec3 left = {-right[0], -right[1], -right[2]};
  const Vec3 up = {-down[0], -down[1], -down[2]};
  DrawEdgeLetters(cr.get(), font, layout,
                  {DisplayDirectionLetter(left), DisplayDirectionLetter(right),
                   DisplayDirectionLetter(up), DisplayDirectionLetter(down)});
  DrawLegend(cr.get(), font, layout, legend);

  PreviewImage image;
  image.name = view.name;
  image.width = layout.width;
  image.height = layout.height;
  image.rgb = SurfaceToRgb(canvas.get());
  image.description = absl::StrFormat(
      "%s plane of the output grid, %s = %d of %d", view.name,
      AxisIndexName(view.normal), view.index, grid.size[view.normal]);
  image.legend = legend.lines;
  image.patient_orientation = absl::StrCat(DicomDirectionLetters(right), "\\",
                                           DicomDirectionLetters(down));
  image.x0 = layout.x0;
  image.y0 = layout.y0;
  image.x1 = layout.x0 + wh;
  image.y1 = layout.y0 + wv;
  // index along h at picture x: p = (x + 0.5 - x0) / sx - 0.5, flipped as
  // the view is.
  const double ph = static_cast<double>(nh) / wh;
  const double pv = static_cast<double>(nv) / wv;
  image.origin[view.normal] = static_cast<double>(view.index);
  if (view.flip_h) {
    image.origin[view.h] = nh - 0.5 + layout.x0 * ph;
    image.per_x[view.h] = -ph;
  } else {
    image.origin[view.h] = -layout.x0 * ph - 0.5;
    image.per_x[view.h] = ph;
  }
  if (view.flip_v) {
    image.origin[view.v] = nv - 0.5 + layout.y0 * pv;
    image.per_y[view.v] = -pv;
  } else {
    image.origin[view.v] = -layout.y0 * pv - 0.5;
    image.per_y[view.v] = pv;
  }
  image.plane_axis = view.normal;
  image.plane_index = view.index;
  return image;
}

}  // namespace interslice::preview_internal

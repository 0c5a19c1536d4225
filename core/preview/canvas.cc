// The canvas of a preview: Cairo image surfaces, the legend's text (one
// TrueType file through FreeType, unhinted), PNG encoding and the preview
// folder.
#include <cairo-ft.h>
#include <cairo.h>
#include <fcntl.h>
#include <ft2build.h>
#include <unistd.h>
#include FT_FREETYPE_H

#include <algorithm>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <map>
#include <random>
#include <system_error>

#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "core/preview/preview.h"
#include "core/preview/preview_internal.h"

namespace interslice {
namespace preview_internal {
namespace {

constexpr double kFontPixels = 13;
constexpr int kLineHeight = 18;
constexpr int kLegendPadding = 8;
constexpr int kSwatchSize = 10;
constexpr int kSwatchGap = 16;  // between swatch entries

double TextWidth(cairo_t* cr, const std::string& text) {
  cairo_text_extents_t extents;
  cairo_text_extents(cr, text.c_str(), &extents);
  return extents.x_advance;
}

// One scratch context to measure text.
struct Measurer {
  SurfacePtr surface{cairo_image_surface_create(CAIRO_FORMAT_RGB24, 1, 1)};
  ContextPtr cr{cairo_create(surface.get())};
};

// Swatch entries laid out in rows within `width`: the x of each entry and the
// number of rows.
struct SwatchFlow {
  std::vector<std::pair<double, int>> positions;  // x, row
  int rows = 0;
};
SwatchFlow FlowSwatches(cairo_t* cr, const std::vector<Swatch>& swatches,
                        double width) {
  SwatchFlow flow;
  double x = kLegendPadding;
  int row = 0;
  for (const Swatch& s : swatches) {
    const double w = kSwatchSize + 5 + TextWidth(cr, s.text);
    if (x > kLegendPadding && x + w > width - kLegendPadding) {
      x = kLegendPadding;
      ++row;
    }
    flow.positions.emplace_back(x, row);
    x += w + kSwatchGap;
  }
  flow.rows = swatches.empty() ? 0 : row + 1;
  return flow;
}

}  // namespace

absl::StatusOr<const LegendFont*> LegendFont::Get(const std::string& path) {
  static absl::Mutex mutex(absl::kConstInit);
  // Never freed: Cairo's font caches may refer to the faces until exit.
  static auto* fonts = new std::map<std::string, const LegendFont*>();
  absl::MutexLock lock(&mutex);
  if (auto it = fonts->find(path); it != fonts->end()) return it->second;
  static FT_Library library = nullptr;
  if (library == nullptr && FT_Init_FreeType(&library) != 0) {
    library = nullptr;
    return absl::FailedPreconditionError("previews: FreeType did not start");
  }
  FT_Face face = nullptr;
  if (FT_New_Face(library, path.c_str(), 0, &face) != 0) {
    return absl::FailedPreconditionError(
        absl::StrCat("previews: cannot load the legend font ", path,
                     " (Debian package fonts-dejavu-core)"));
  }
  auto* font = new LegendFont();
  font->face_ = cairo_ft_font_face_create_for_ft_face(face, FT_LOAD_NO_HINTING);
  if (cairo_font_face_status(font->face_) != CAIRO_STATUS_SUCCESS) {
    cairo_font_face_destroy(font->face_);
    FT_Done_Face(face);
    delete font;
    return absl::FailedPreconditionError(
        "previews: Cairo cannot use the legend font");
  }
  fonts->emplace(path, font);
  return font;
}

void LegendFont::Use(cairo_t* cr, double pixels) const {
  cairo_set_font_face(cr, face_);
  cairo_set_font_size(cr, pixels);
  cairo_font_options_t* options = cairo_font_options_create();
  cairo_font_options_set_antialias(options, CAIRO_ANTIALIAS_GRAY);
  cairo_font_options_set_hint_style(options, CAIRO_HINT_STYLE_NONE);
  cairo_font_options_set_hint_metrics(options, CAIRO_HINT_METRICS_OFF);
  cairo_set_font_options(cr, options);
  cairo_font_options_destroy(options);
}

Layout LayOut(const LegendFont& font, int picture_w, int picture_h,
              const Legend& legend) {
  Measurer m;
  font.Use(m.cr.get(), kFontPixels);
  double widest = 0;
  for (const std::string& line : legend.lines) {
    widest = std::max(widest, TextWidth(m.cr.get(), line));
  }
  Layout layout;
  layout.picture_w = picture_w;
  layout.picture_h = picture_h;
  layout.width =
      std::max(picture_w + 2 * kMargin,
               static_cast<int>(std::ceil(widest)) + 2 * kLegendPadding);
  const SwatchFlow flow =
      FlowSwatches(m.cr.get(), legend.swatches, layout.width);
  const int legend_rows = static_cast<int>(legend.lines.size()) + flow.rows;
  layout.x0 = (layout.width - picture_w) / 2;
  layout.y0 = kMargin;
  layout.legend_y = kMargin + picture_h + kMargin;
  layout.height = layout.legend_y + legend_rows * kLineHeight + kLegendPadding;
  return layout;
}

SurfacePtr NewCanvas(const Layout& layout) {
  SurfacePtr surface(cairo_image_surface_create(CAIRO_FORMAT_RGB24,
                                                layout.width, layout.height));
  ContextPtr cr(cairo_create(surface.get()));
  SetColour(cr.get(), kBackground);
  cairo_paint(cr.get());
  return surface;
}

void SetColour(cairo_t* cr, const Rgb& rgb, double alpha) {
  cairo_set_source_rgba(cr, rgb[0] / 255.0, rgb[1] / 255.0, rgb[2] / 255.0,
                        alpha);
}

void DrawLegend(cairo_t* cr, const LegendFont& font, const Layout& layout,
                const Legend& legend) {
  cairo_save(cr);
  font.Use(cr, kFontPixels);
  // Baselines sit 4 pixels above each row's bottom.
  double y = layout.legend_y + kLineHeight - 5;
  for (const std::string& line : legend.lines) {
    SetColour(cr, kText);
    cairo_move_to(cr, kLegendPadding, y);
    cairo_show_text(cr, line.c_str());
    y += kLineHeight;
  }
  const SwatchFlow flow = FlowSwatches(cr, legend.swatches, layout.width);
  for (size_t n = 0; n < legend.swatches.size(); ++n) {
    const Swatch& s = legend.swatches[n];
    const double x = flow.positions[n].first;
    const double row_y = y + flow.positions[n].second * kLineHeight;
    SetColour(cr, s.rgb);
    if (s.tick) {
      cairo_rectangle(cr, x, std::floor(row_y - 4), kSwatchSize, 1);
    } else {
      cairo_rectangle(cr, x, row_y - kSwatchSize + 1, kSwatchSize, kSwatchSize);
    }
    cairo_fill(cr);
    SetColour(cr, kText);
    cairo_move_to(cr, x + kSwatchSize + 5, row_y);
    cairo_show_text(cr, s.text.c_str());
  }
  cairo_restore(cr);
}

void DrawEdgeLetters(cairo_t* cr, const LegendFont& font, const Layout& layout,
                     const std::array<std::string, 4>& letters) {
  cairo_save(cr);
  font.Use(cr, kFontPixels);
  const double cx = layout.x0 + layout.picture_w / 2.0;
  const double cy = layout.y0 + layout.picture_h / 2.0;
  const double places[4][2] = {{static_cast<double>(layout.x0 + 3), cy + 5},
                               {layout.x0 + layout.picture_w - 3.0, cy + 5},
                               {cx, layout.y0 + 15.0},
                               {cx, layout.y0 + layout.picture_h - 4.0}};
  for (int n = 0; n < 4; ++n) {
    if (letters[n].empty()) continue;
    const double w = TextWidth(cr, letters[n]);
    double x = places[n][0];
    if (n == 1) x -= w;
    if (n >= 2) x -= w / 2;
    // A dark outline keeps the letter readable on bright anatomy.
    cairo_move_to(cr, x, places[n][1]);
    cairo_text_path(cr, letters[n].c_str());
    SetColour(cr, kBackground);
    cairo_set_line_width(cr, 2.5);
    cairo_stroke_preserve(cr);
    SetColour(cr, kText);
    cairo_fill(cr);
  }
  cairo_restore(cr);
}

void DrawCentredNote(cairo_t* cr, const LegendFont& font, const Layout& layout,
                     const std::string& text) {
  cairo_save(cr);
  font.Use(cr, kFontPixels);
  SetColour(cr, kText);
  const double w = TextWidth(cr, text);
  cairo_move_to(cr, layout.x0 + (layout.picture_w - w) / 2.0,
                layout.y0 + layout.picture_h / 2.0);
  cairo_show_text(cr, text.c_str());
  cairo_restore(cr);
}

std::vector<uint8_t> SurfaceToRgb(cairo_surface_t* surface) {
  cairo_surface_flush(surface);
  const int w = cairo_image_surface_get_width(surface);
  const int h = cairo_image_surface_get_height(surface);
  const int stride = cairo_image_surface_get_stride(surface);
  const unsigned char* data = cairo_image_surface_get_data(surface);
  std::vector<uint8_t> rgb(static_cast<size_t>(w) * h * 3);
  for (int y = 0; y < h; ++y) {
    const uint32_t* row = reinterpret_cast<const uint32_t*>(data + y * stride);
    uint8_t* out = rgb.data() + static_cast<size_t>(y) * w * 3;
    for (int x = 0; x < w; ++x) {
      // CAIRO_FORMAT_RGB24: native-endian 0xXXRRGGBB.
      out[3 * x] = static_cast<uint8_t>(row[x] >> 16);
      out[3 * x + 1] = static_cast<uint8_t>(row[x] >> 8);
      out[3 * x + 2] = static_cast<uint8_t>(row[x]);
    }
  }
  return rgb;
}

std::string DicomDirectionLetters(const Vec3& d) {
  const char positive[3] = {'L', 'P', 'H'};
  const char negative[3] = {'R', 'A', 'F'};
  int order[3] = {0, 1, 2};
  std::stable_sort(order, order + 3, [&](int a, int b) {
    return std::abs(d[a]) > std::abs(d[b]);
  });
  std::string letters;
  for (int a : order) {
    if (std::abs(d[a]) > 0.01) letters += d[a] > 0 ? positive[a] : negative[a];
  }
  return letters;
}

std::string DisplayDirectionLetter(const Vec3& d) {
  const char positive[3] = {'L', 'P', 'S'};
  const char negative[3] = {'R', 'A', 'I'};
  int best = 0;
  for (int a = 1; a < 3; ++a) {
    if (std::abs(d[a]) > std::abs(d[best])) best = a;
  }
  return std::string(1, d[best] > 0 ? positive[best] : negative[best]);
}

}  // namespace preview_internal

namespace {

using preview_internal::SurfacePtr;

cairo_status_t AppendToString(void* closure, const unsigned char* data,
                              unsigned int length) {
  static_cast<std::string*>(closure)->append(
      reinterpret_cast<const char*>(data), length);
  return CAIRO_STATUS_SUCCESS;
}

absl::Status WriteFileSynced(const std::filesystem::path& path,
                             const std::string& bytes) {
  const int fd = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  if (fd < 0) {
    return absl::InternalError(absl::StrCat("cannot create ", path.string(),
                                            ": ", std::strerror(errno)));
  }
  size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + done, bytes.size() - done);
    if (n < 0) {
      if (errno == EINTR) continue;
      const int error = errno;
      ::close(fd);
      return absl::InternalError(absl::StrCat("cannot write ", path.string(),
                                              ": ", std::strerror(error)));
    }
    done += static_cast<size_t>(n);
  }
  const bool synced = ::fsync(fd) == 0;
  const int error = errno;
  if (::close(fd) != 0 || !synced) {
    return absl::InternalError(absl::StrCat("cannot write ", path.string(),
                                            ": ", std::strerror(error)));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::string> EncodePng(const PreviewImage& image) {
  if (image.width <= 0 || image.height <= 0 ||
      image.rgb.size() != static_cast<size_t>(image.width) * image.height * 3) {
    return absl::InvalidArgumentError(
        absl::StrCat("preview ", image.name, ": no pixels or a wrong size"));
  }
  SurfacePtr surface(cairo_image_surface_create(CAIRO_FORMAT_RGB24, image.width,
                                                image.height));
  if (cairo_surface_status(surface.get()) != CAIRO_STATUS_SUCCESS) {
    return absl::InternalError(
        absl::StrCat("preview ", image.name, ": cannot allocate its image"));
  }
  cairo_surface_flush(surface.get());
  unsigned char* data = cairo_image_surface_get_data(surface.get());
  const int stride = cairo_image_surface_get_stride(surface.get());
  for (int y = 0; y < image.height; ++y) {
    uint32_t* row = reinterpret_cast<uint32_t*>(data + y * stride);
    const uint8_t* in =
        image.rgb.data() + static_cast<size_t>(y) * image.width * 3;
    for (int x = 0; x < image.width; ++x) {
      row[x] = (uint32_t{in[3 * x]} << 16) | (uint32_t{in[3 * x + 1]} << 8) |
               uint32_t{in[3 * x + 2]};
    }
  }
  cairo_surface_mark_dirty(surface.get());
  std::string png;
  if (cairo_surface_write_to_png_stream(surface.get(), AppendToString, &png) !=
      CAIRO_STATUS_SUCCESS) {
    return absl::InternalError(
        absl::StrCat("preview ", image.name, ": PNG encoding failed"));
  }
  return png;
}

absl::StatusOr<std::vector<std::string>> WritePreviewPngs(
    const std::vector<PreviewImage>& images, const std::string& folder) {
  namespace fs = std::filesystem;
  const fs::path target(folder);
  std::random_device random;
  const fs::path temp =
      target.parent_path() /
      absl::StrCat(".", target.filename().string(), ".tmp-", random());
  std::error_code ec;
  fs::create_directories(temp, ec);
  if (ec) {
    return absl::InternalError(
        absl::StrCat("cannot create ", temp.string(), ": ", ec.message()));
  }
  std::vector<std::string> paths;
  absl::Status status;
  for (const PreviewImage& image : images) {
    absl::StatusOr<std::string> png = EncodePng(image);
    if (!png.ok()) {
      status = png.status();
      break;
    }
    status = WriteFileSynced(temp / (image.name + ".png"), *png);
    if (!status.ok()) break;
    paths.push_back((target / (image.name + ".png")).string());
  }
  if (status.ok()) {
    fs::remove_all(target, ec);
    fs::rename(temp, target, ec);
    if (ec) {
      status = absl::InternalError(absl::StrCat(
          "cannot move the previews into ", folder, ": ", ec.message()));
    }
  }
  if (!status.ok()) {
    fs::remove_all(temp, ec);
    return status;
  }
  // The rename itself is durable once the parent folder is synced.
  const int dir =
      ::open(target.parent_path().empty() ? "." : target.parent_path().c_str(),
             O_RDONLY | O_DIRECTORY);
  if (dir >= 0) {
    ::fsync(dir);
    ::close(dir);
  }
  return paths;
}

}  // namespace interslice

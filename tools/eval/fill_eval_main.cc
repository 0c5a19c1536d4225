// interslice_fill_eval: drop-k on multi-label segmentations.
//
// A fully drawn label map (given, or made from the series by HU bands and
// connected components) keeps every k-th slice as key slices; the slices in
// between are filled by nearest-slice copy, linear stacking (core/labels with
// method linear) and the paper's refinement (cg, direct), and compared per
// label with the withheld slices between the first and last key slice:
// Dice, HD95 and MSD (tools/eval/metrics.h, 3D surface distances in mm), the
// number of "gap" voxels (background on a withheld slice at a pixel labelled
// on both bracketing key slices) and the time of the whole fill.
//
// Output in --out: fill_metrics.csv (one row per k, method, label),
// fill_summary.csv (per k and method: mean Dice/HD95/MSD over labels, gap
// voxels, seconds) and labels.json (the labels made: band, voxels).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "CLI/CLI.hpp"
#include "absl/strings/numbers.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"
#include "core/dicom/series_reader.h"
#include "core/labels/label_fill.h"
#include "core/labels/label_map_io.h"
#include "core/labels/segmentation_reader.h"
#include "core/volume_io/volume_io.h"
#include "itkConnectedComponentImageFilter.h"
#include "itkImage.h"
#include "itkImportImageFilter.h"
#include "itkMedianImageFilter.h"
#include "itkRelabelComponentImageFilter.h"
#include "nlohmann/json.hpp"
#include "tools/eval/metrics.h"

namespace interslice::eval {
namespace {

using Image3f = itk::Image<float, 3>;
using Image3u = itk::Image<uint32_t, 3>;

Image3f::Pointer ToItk(const Volume<float>& v) {
  auto image = Image3f::New();
  Image3f::SizeType size;
  for (int a = 0; a < 3; ++a) size[a] = v.grid.size[a];
  image->SetRegions(Image3f::RegionType(size));
  image->Allocate();
  std::copy(v.data.begin(), v.data.end(), image->GetBufferPointer());
  return image;
}

struct MadeLabel {
  int label;
  float lower, upper;
  int64_t voxels;
};

// Labels from HU bands: each band (after a 3x3 in-plane median, so that a
// band is not speckle) split into 3D face-connected components; the largest
// components of all bands become labels 1..max_labels in order of size.
// Neighbouring bands touch, so many labels share boundaries.
LabelVolume MakeLabels(const Volume<float>& image,
                       const std::vector<float>& edges, int max_labels,
                       int64_t min_voxels, std::vector<MadeLabel>& made) {
  auto median = itk::MedianImageFilter<Image3f, Image3f>::New();
  median->SetInput(ToItk(image));
  itk::Size<3> radius = {{1, 1, 0}};
  median->SetRadius(radius);
  median->Update();
  const float* smooth = median->GetOutput()->GetBufferPointer();
  struct Component {
    int band;
    uint32_t id;
    int64_t voxels;
  };
  std::vector<Component> components;
  std::vector<std::vector<uint32_t>> ids(edges.size() - 1);
  const int64_t n = image.grid.VoxelCount();
  for (size_t b = 0; b + 1 < edges.size(); ++b) {
    auto mask = itk::Image<uint8_t, 3>::New();
    itk::Size<3> size;
    for (int a = 0; a < 3; ++a) size[a] = image.grid.size[a];
    mask->SetRegions(itk::ImageRegion<3>(size));
    mask->Allocate();
    uint8_t* m = mask->GetBufferPointer();
    for (int64_t v = 0; v < n; ++v) {
      m[v] = smooth[v] >= edges[b] && smooth[v] < edges[b + 1];
    }
    auto cc = itk::ConnectedComponentImageFilter<itk::Image<uint8_t, 3>,
                                                 Image3u>::New();
    cc->SetInput(mask);
    cc->FullyConnectedOff();
    auto relabel = itk::RelabelComponentImageFilter<Image3u, Image3u>::New();
    relabel->SetInput(cc->GetOutput());
    relabel->SetMinimumObjectSize(min_voxels);
    relabel->Update();
    const uint32_t* r = relabel->GetOutput()->GetBufferPointer();
    ids[b].assign(r, r + n);
    const auto& sizes = relabel->GetSizeOfObjectsInPixels();
    for (size_t c = 0; c < sizes.size(); ++c) {
      components.push_back({static_cast<int>(b), static_cast<uint32_t>(c + 1),
                            static_cast<int64_t>(sizes[c])});
    }
  }
  std::sort(components.begin(), components.end(),
            [](const Component& a, const Component& b) {
              return a.voxels > b.voxels;
            });
  if (static_cast<int>(components.size()) > max_labels) {
    components.resize(max_labels);
  }
  LabelVolume labels;
  labels.grid = image.grid;
  labels.data.assign(n, 0);
  for (size_t l = 0; l < components.size(); ++l) {
    const Component& c = components[l];
    for (int64_t v = 0; v < n; ++v) {
      if (ids[c.band][v] == c.id) labels.data[v] = l + 1;
    }
    made.push_back(
        {static_cast<int>(l + 1), edges[c.band], edges[c.band + 1], c.voxels});
  }
  return labels;
}

// Nearest key slice copied onto each slice (ties: the lower key).
LabelVolume NearestCopy(const LabelVolume& truth,
                        const std::vector<int64_t>& keys) {
  LabelVolume out = truth;
  const int64_t plane = truth.grid.SliceVoxelCount();
  for (int64_t k = 0; k < truth.grid.size[2]; ++k) {
    int64_t best = keys.front();
    for (int64_t key : keys) {
      if (std::abs(key - k) < std::abs(best - k)) best = key;
    }
    std::copy(truth.data.begin() + best * plane,
              truth.data.begin() + (best + 1) * plane,
              out.data.begin() + k * plane);
  }
  return out;
}

struct LabelScore {
  double dice = 0, hd95 = -1, msd = -1;
};

// Scores of `label` on the slices marked in `withheld`, computed on the
// bounding box of the label in both volumes grown by 8 voxels (distances
// are to surfaces inside that box, which holds both surfaces).
LabelScore Score(const LabelVolume& out, const LabelVolume& truth, int label,
                 const std::vector<uint8_t>& withheld) {
  const Grid& g = truth.grid;
  VoxelBox box{{g.size[0], g.size[1], g.size[2]}, {0, 0, 0}};
  for (int64_t k = 0; k < g.size[2]; ++k) {
    for (int64_t j = 0; j < g.size[1]; ++j) {
      for (int64_t i = 0; i < g.size[0]; ++i) {
        const int64_t v = g.LinearIndex(i, j, k);
        if (out.data[v] != label && truth.data[v] != label) continue;
        const int64_t idx[3] = {i, j, k};
        for (int a = 0; a < 3; ++a) {
          box.begin[a] = std::min(box.begin[a], idx[a]);
          box.end[a] = std::max(box.end[a], idx[a] + 1);
        }
      }
    }
  }
  LabelScore score;
  if (box.end[0] == 0) return score;
  for (int a = 0; a < 3; ++a) {
    box.begin[a] = std::max<int64_t>(0, box.begin[a] - 8);
    box.end[a] = std::min(g.size[a], box.end[a] + 8);
  }
  Mask a, b;
  a.grid = b.grid = CropGrid(g, box);
  a.data.resize(a.grid.VoxelCount());
  b.data.resize(a.grid.VoxelCount());
  std::vector<uint8_t> slices(a.grid.size[2]);
  for (int64_t k = 0; k < a.grid.size[2]; ++k) {
    slices[k] = withheld[box.begin[2] + k];
    for (int64_t j = 0; j < a.grid.size[1]; ++j) {
      for (int64_t i = 0; i < a.grid.size[0]; ++i) {
        const int64_t v =
            g.LinearIndex(box.begin[0] + i, box.begin[1] + j, box.begin[2] + k);
        a.at(i, j, k) = out.data[v] == label;
        b.at(i, j, k) = truth.data[v] == label;
      }
    }
  }
  int64_t in_truth = 0;
  for (int64_t k = 0; k < a.grid.size[2]; ++k) {
    if (!slices[k]) continue;
    for (int64_t p = 0; p < a.grid.SliceVoxelCount(); ++p) {
      in_truth += b.data[k * a.grid.SliceVoxelCount() + p];
    }
  }
  if (in_truth == 0) {
    score.dice = -1;  // not on the withheld slices: not scored
    return score;
  }
  score.dice = DiceOnSlices(a, b, slices);
  const SurfaceDistances d = SurfaceDistancesOnSlices(a, b, slices);
  score.hd95 = d.hd95;
  score.msd = d.msd;
  return score;
}

int64_t CountGaps(const LabelVolume& out, const LabelVolume& truth,
                  const std::vector<int64_t>& keys) {
  const int64_t plane = truth.grid.SliceVoxelCount();
  int64_t gaps = 0;
  for (size_t s = 0; s + 1 < keys.size(); ++s) {
    const uint16_t* a = truth.data.data() + keys[s] * plane;
    const uint16_t* b = truth.data.data() + keys[s + 1] * plane;
    for (int64_t k = keys[s] + 1; k < keys[s + 1]; ++k) {
      const uint16_t* o = out.data.data() + k * plane;
      for (int64_t p = 0; p < plane; ++p) {
        gaps += a[p] != 0 && b[p] != 0 && o[p] == 0;
      }
    }
  }
  return gaps;
}

int Main(int argc, char** argv) {
  CLI::App app{"drop-k evaluation of interslice fill on label maps"};
  std::string series_dir, labels_path, out_dir,
      ks_text = "2,3,5,8", methods_text = "copy,linear,cg,direct,auto";
  std::string bands_text = "-200,0,40,100,300,3000";
  int max_labels = 20, threads = 0, margin = FillOptions().margin_pixels;
  int64_t min_voxels = 2000;
  app.add_option("--series", series_dir,
                 "Reference DICOM series (without it, --labels is a label "
                 "map on its own grid)");
  app.add_option("--labels", labels_path,
                 "Fully drawn label map on the series' voxels (any layout), "
                 "or an RTSTRUCT / SEG drawn on the series (default: made "
                 "from HU bands)");
  std::string rois_text;
  app.add_option("--rois", rois_text,
                 "RTSTRUCT ROI / SEG segment numbers to read (comma "
                 "separated; default all)");
  app.add_option("--bands", bands_text, "HU band edges for made labels");
  app.add_option("--max-labels", max_labels, "At most this many made labels");
  app.add_option("--min-voxels", min_voxels, "Smallest made label, voxels");
  app.add_option("--ks", ks_text, "Key slice steps");
  app.add_option("--methods", methods_text,
                 "copy,linear,cg,direct,morph,auto,auto-trend,"
                 "auto-doubled,auto-nomorph");
  int64_t slices = 0;
  app.add_option("--slices", slices,
                 "Resample the truth labels to this many slices (nearest "
                 "slice, z spacing scaled): e.g. 150 for the issue's timing "
                 "grid; 0 = as read");
  app.add_option("--threads", threads, "Threads (0 = all)");
  app.add_option("--margin", margin, "In-plane margin of each label's box");
  app.add_option("--out", out_dir, "Output folder")->required();
  bool no_score = false;
  app.add_flag("--no-score", no_score,
               "Time the fills only (no Dice/HD95/MSD: for profiling)");
  bool save_fills = false;
  app.add_flag("--save-fills", save_fills,
               "Write each fill's label map (fill-k<K>-<method>.nii.gz): to "
               "compare two builds' fills voxel for voxel");
  int repeat = 1;
  app.add_option("--repeat", repeat,
                 "Run each fill this many times; seconds = the fastest");
  CLI11_PARSE(app, argc, argv);
  SetItkThreads(threads);
  QuietDicomToolkitLogging();
  std::filesystem::create_directories(out_dir);

  if (series_dir.empty() && labels_path.empty()) {
    std::fprintf(stderr, "give --series, --labels or both\n");
    return 1;
  }
  std::optional<DicomSeries> series;
  if (!series_dir.empty()) {
    absl::StatusOr<DicomSeries> read =
        ReadDicomSeries({series_dir}, {}, ComputeContext{.threads = threads});
    if (!read.ok()) {
      std::fprintf(stderr, "%s\n",
                   std::string(read.status().message()).c_str());
      return 1;
    }
    series = *std::move(read);
  }
  LabelVolume truth;
  LabelContours contours;
  std::vector<MadeLabel> made;
  if (!labels_path.empty() && series.has_value() &&
      LooksLikeDicomFile(labels_path)) {
    // An RTSTRUCT (its polygons give the key slices' exact distance, as
    // `interslice fill` uses them) or a SEG drawn on the series.
    std::vector<int> only;
    for (absl::string_view r : absl::StrSplit(rois_text, ',')) {
      int v;
      if (!r.empty() && absl::SimpleAtoi(r, &v)) only.push_back(v);
    }
    const ReferenceSeries reference{series->image.grid,
                                    series->series_instance_uid,
                                    series->frame_of_reference_uid};
    absl::StatusOr<SegmentationInput> seg =
        ReadDicomLabels(labels_path, reference, only);
    if (!seg.ok()) {
      std::fprintf(stderr, "%s\n", std::string(seg.status().message()).c_str());
      return 1;
    }
    truth = std::move(seg->labels);
    contours = std::move(seg->contours);
  } else if (!labels_path.empty()) {
    // Any layout of the series' voxels (core/labels/label_map_io.h); no
    // series: the map's own grid.
    absl::StatusOr<Volume<float>> own;
    Grid grid;
    if (series.has_value()) {
      grid = series->image.grid;
    } else {
      absl::StatusOr<VolumeFileHeader> header =
          ReadVolumeFileHeader(labels_path);
      if (!header.ok()) {
        std::fprintf(stderr, "%s\n",
                     std::string(header.status().message()).c_str());
        return 1;
      }
      grid = header->grid;
    }
    absl::StatusOr<LabelMapOnReference> l =
        ReadLabelMapOnReference(labels_path, grid);
    if (!l.ok()) {
      std::fprintf(stderr, "%s\n", std::string(l.status().message()).c_str());
      return 1;
    }
    truth = std::move(l->labels);
  } else {
    std::vector<float> edges;
    for (absl::string_view e : absl::StrSplit(bands_text, ',')) {
      float v;
      if (!absl::SimpleAtof(e, &v)) return 1;
      edges.push_back(v);
    }
    truth = MakeLabels(series->image, edges, max_labels, min_voxels, made);
    (void)WriteVolume(truth, out_dir + "/truth-labels.nii.gz");
  }
  if (slices > 0 && slices != truth.grid.size[2]) {
    // Nearest-slice resampling: output slice k' takes input slice
    // round(k' (Z - 1) / (Z' - 1)); the extent in mm is kept.
    const int64_t nz_in = truth.grid.size[2];
    const int64_t plane = truth.grid.SliceVoxelCount();
    LabelVolume resampled;
    resampled.grid = truth.grid;
    resampled.grid.size[2] = slices;
    resampled.grid.spacing[2] =
        truth.grid.spacing[2] * (nz_in - 1) / std::max<int64_t>(1, slices - 1);
    resampled.data.resize(resampled.grid.VoxelCount());
    for (int64_t k = 0; k < slices; ++k) {
      const int64_t from = std::llround(static_cast<double>(k) * (nz_in - 1) /
                                        std::max<int64_t>(1, slices - 1));
      std::copy(truth.data.begin() + from * plane,
                truth.data.begin() + (from + 1) * plane,
                resampled.data.begin() + k * plane);
    }
    truth = std::move(resampled);
  }
  const std::vector<int> labels = LabelsPresent(truth);
  nlohmann::ordered_json made_json = nlohmann::ordered_json::array();
  for (const MadeLabel& m : made) {
    made_json.push_back({{"label", m.label},
                         {"hu_from", m.lower},
                         {"hu_to", m.upper},
                         {"voxels", m.voxels}});
  }
  std::ofstream(out_dir + "/labels.json")
      << nlohmann::ordered_json{{"grid", truth.grid.size},
                                {"labels", made_json}}
             .dump(2)
      << "\n";
  std::printf("%zu labels on %lld x %lld x %lld\n", labels.size(),
              static_cast<long long>(truth.grid.size[0]),
              static_cast<long long>(truth.grid.size[1]),
              static_cast<long long>(truth.grid.size[2]));

  std::ofstream metrics(out_dir + "/fill_metrics.csv");
  metrics << "k,method,label,dice,hd95_mm,msd_mm\n";
  std::ofstream summary(out_dir + "/fill_summary.csv");
  std::ofstream timing;
  if (no_score) {
    timing.open(out_dir + "/fill_timing.csv");
    timing << "grid,labels,k,method,threads,seconds,cpu_seconds\n";
  }
  std::ofstream choices(out_dir + "/fill_choices.csv");
  choices << "k,method,label,chosen";
  for (const char* what : {"d2", "d4", "score"}) {
    for (const char* c : {"copy", "linear", "blend", "direct", "morph"}) {
      choices << "," << what << "_" << c;
    }
  }
  choices << "\n";
  // Each scored held-out key slice's own validation Dice per candidate
  // (LabelFillInfo::validation_slice_dice): how much the ranking varies from
  // slice to slice, for studying selection rules (issue 24).
  std::ofstream slice_rows(out_dir + "/fill_validation_slices.csv");
  slice_rows << "k,method,label,gap,slice,copy,linear,blend,direct,morph\n";
  summary << "k,method,labels_scored,mean_dice,mean_hd95_mm,mean_msd_mm,"
             "gap_voxels,seconds,cpu_seconds\n";
  const int64_t nz = truth.grid.size[2];
  for (absl::string_view kt : absl::StrSplit(ks_text, ',')) {
    int64_t step;
    if (!absl::SimpleAtoi(kt, &step) || step < 1) return 1;
    std::vector<int64_t> keys;
    for (int64_t k = 0; k < nz; k += step) keys.push_back(k);
    std::vector<uint8_t> withheld(nz, 0);
    for (int64_t k = 0; k < keys.back(); ++k) withheld[k] = k % step != 0;
    for (absl::string_view mt : absl::StrSplit(methods_text, ',')) {
      const std::string method(mt);
      LabelVolume out;
      // Wall clock and process CPU time (all threads) of the fill, the
      // fastest of --repeat runs: on a shared machine the CPU time says
      // what the fill costs, the wall clock what the load left of it.
      double seconds = 1e300, cpu_seconds = 1e300;
      for (int rep = 0; rep < std::max(1, repeat); ++rep) {
        const auto start = std::chrono::steady_clock::now();
        const std::clock_t cpu_start = std::clock();
        if (method == "copy") {
          out = NearestCopy(truth, keys);
        } else {
          FillOptions options;
          options.key_slices = keys;
          options.margin_pixels = margin;
          // auto: the default (the selection at the doubled gap);
          // auto-trend: the gap-trend rule (AutoSelection::kGapTrend);
          // auto-doubled: the doubled gap whatever the default;
          // auto-nomorph: without the morph among the candidates.
          const bool is_auto = method.rfind("auto", 0) == 0;
          options.method = is_auto ? FillMethod::kAuto : FillMethod::kSolver;
          if (method == "auto-doubled") {
            options.selection = AutoSelection::kDoubledGap;
          }
          if (method == "auto-trend") {
            options.selection = AutoSelection::kGapTrend;
          }
          if (method == "auto-nomorph") options.auto_morph = false;
          options.solver.method = method == "linear" ? SolverMethod::kLinear
                                  : method == "cg"
                                      ? SolverMethod::kConjugateGradient
                                  : method == "morph" ? SolverMethod::kMorph
                                                      : SolverMethod::kDirect;
          if (!contours.polygons.empty()) options.contours = &contours;
          absl::StatusOr<FillResult> r = FillBetweenSlices(
              truth, options, ComputeContext{.threads = threads});
          if (!r.ok()) {
            std::fprintf(stderr, "%s\n",
                         std::string(r.status().message()).c_str());
            return 1;
          }
          out = std::move(r->labels);
          if (is_auto && rep == 0) {
            // The candidate chosen per label, its validation Dice on the
            // label's own held-out key slices at the doubled and quadrupled
            // gap and the score (no truth involved).
            for (const LabelFillInfo& info : r->per_label) {
              choices << step << "," << method << "," << info.label << ","
                      << info.method;
              for (const auto* list :
                   {&info.validation_dice, &info.validation_dice_4g,
                    &info.validation_score}) {
                for (const auto& [name, dice] : *list) {
                  choices << absl::StrFormat(",%.4f", dice);
                }
                if (list->empty()) choices << ",,,,,";
              }
              choices << "\n";
              for (const auto& [gap, rows] :
                   {std::pair{"2g", &info.validation_slice_dice},
                    std::pair{"4g", &info.validation_slice_dice_4g}}) {
                for (size_t n = 0; n < rows->size(); ++n) {
                  slice_rows << step << "," << method << "," << info.label
                             << "," << gap << "," << n;
                  for (double dice : (*rows)[n]) {
                    slice_rows << absl::StrFormat(",%.4f", dice);
                  }
                  slice_rows << "\n";
                }
              }
            }
            choices.flush();
            slice_rows.flush();
          }
        }
        seconds =
            std::min(seconds, std::chrono::duration<double>(
                                  std::chrono::steady_clock::now() - start)
                                  .count());
        cpu_seconds = std::min(
            cpu_seconds,
            static_cast<double>(std::clock() - cpu_start) / CLOCKS_PER_SEC);
      }
      if (save_fills) {
        const std::string path =
            absl::StrFormat("%s/fill-k%d-%s.nii.gz", out_dir, step, method);
        if (absl::Status written = WriteVolume(out, path); !written.ok()) {
          std::fprintf(stderr, "%s\n", std::string(written.message()).c_str());
          return 1;
        }
      }
      if (no_score) {
        std::printf("%lld,%s,seconds %.2f,cpu_seconds %.2f\n",
                    static_cast<long long>(step), method.c_str(), seconds,
                    cpu_seconds);
        std::fflush(stdout);
        timing << absl::StrFormat("%dx%dx%d,%d,%d,%s,%d,%.2f,%.2f\n",
                                  truth.grid.size[0], truth.grid.size[1],
                                  truth.grid.size[2], labels.size(), step,
                                  method, threads, seconds, cpu_seconds);
        timing.flush();
        continue;
      }
      double sum_dice = 0, sum_hd = 0, sum_msd = 0;
      int scored = 0;
      for (int label : labels) {
        const LabelScore s = Score(out, truth, label, withheld);
        if (s.dice < 0) continue;
        metrics << absl::StrFormat("%d,%s,%d,%.4f,%.3f,%.3f\n", step, method,
                                   label, s.dice, s.hd95, s.msd);
        sum_dice += s.dice;
        sum_hd += s.hd95;
        sum_msd += s.msd;
        ++scored;
      }
      const int64_t gaps = CountGaps(out, truth, keys);
      const std::string line = absl::StrFormat(
          "%d,%s,%d,%.4f,%.3f,%.3f,%d,%.2f,%.2f\n", step, method, scored,
          sum_dice / std::max(1, scored), sum_hd / std::max(1, scored),
          sum_msd / std::max(1, scored), gaps, seconds, cpu_seconds);
      summary << line;
      summary.flush();
      std::printf("%s", line.c_str());
      std::fflush(stdout);
    }
  }
  return 0;
}

}  // namespace
}  // namespace interslice::eval

int main(int argc, char** argv) { return interslice::eval::Main(argc, argv); }

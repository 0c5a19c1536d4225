// The experiments of the quality harness. Each appends rows to a Recorder,
// which writes metrics.csv, convergence.csv, planes.json + raw/ and
// results.json into the output folder.
#ifndef INTERSLICE_TOOLS_EVAL_EXPERIMENTS_H_
#define INTERSLICE_TOOLS_EVAL_EXPERIMENTS_H_

#include <string>
#include <vector>

#include "absl/status/status.h"
#include "nlohmann/json.hpp"

namespace interslice::eval {

struct EvalOptions {
  std::string thin_dir;   // thin real series (drop-k ground truth)
  std::string thick_dir;  // thick series, same frame of reference ("" = skip)
  std::string out_dir;
  float threshold = 300;  // HU; object = value >= threshold
  std::vector<int> ks = {2, 4, 8};
  // "auto": bounding box of the thresholded thin series + roi_margin voxels
  // in-plane (all slices kept); "full": whole slices; or "i0,i1,j0,j1".
  std::string roi = "auto";
  int roi_margin = 8;
  int cg_iterations = 15;       // "cg15"
  double cg_tolerance = 1e-4;   // "cgtol": relative residual target...
  int cg_max_iterations = 300;  // ...capped at this many iterations
  double top_slab_mm = 24;      // skull-top slab for the failure mode
  int threads = 0;              // 0 = all hardware threads
  std::vector<std::string> methods = {"nearest",   "linear", "cg15",
                                      "cgtol",     "direct", "direct-mm",
                                      "morph-raw", "morph"};
};

// Collects every number and writes the output folder.
class Recorder {
 public:
  explicit Recorder(std::string out_dir);
  nlohmann::json& meta() { return meta_; }
  void AddRow(nlohmann::json row) { rows_.push_back(std::move(row)); }
  void AddConvergence(nlohmann::json point) {
    convergence_.push_back(std::move(point));
  }
  // A float32 plane (rows x cols, row-major) under raw/, indexed in
  // planes.json with its tags and pixel spacings (mm).
  absl::Status WritePlane(const std::string& name, const nlohmann::json& tags,
                          const std::vector<float>& data, int64_t rows,
                          int64_t cols, double row_mm, double col_mm);
  // metrics.csv, convergence.csv, planes.json, results.json.
  absl::Status Finish();

 private:
  std::string out_dir_;
  nlohmann::json meta_ = nlohmann::json::object();
  nlohmann::json rows_ = nlohmann::json::array();
  nlohmann::json convergence_ = nlohmann::json::array();
  nlohmann::json planes_ = nlohmann::json::array();
};

absl::Status RunDropK(const EvalOptions& options, Recorder& recorder);
absl::Status RunThickToThin(const EvalOptions& options, Recorder& recorder);
absl::Status RunArtificial(const EvalOptions& options, Recorder& recorder);
absl::Status RunConvergence(const EvalOptions& options, Recorder& recorder);

}  // namespace interslice::eval

#endif  // INTERSLICE_TOOLS_EVAL_EXPERIMENTS_H_

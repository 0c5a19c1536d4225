// interslice_eval: the quality harness (DESIGN.md section 5). See
// scripts/eval.sh for the one documented command and docs/eval/ for the
// latest report.
//
//   interslice_eval --thin DIR [--thick DIR] --threshold 300 --out DIR
//       [--experiments dropk,thick,artificial,convergence] [--ks 2,4,8]
//       [--methods nearest,linear,cg15,cgtol,direct,direct-mm]
//       [--roi auto|full|i0,i1,j0,j1] [--cg-tolerance 1e-4]
//       [--cg-max-iterations 300] [--threads N]
#include <chrono>
#include <cstdio>
#include <ctime>
#include <string>
#include <vector>

#include "CLI/CLI.hpp"
#include "core/dicom/series_reader.h"
#include "tools/eval/experiments.h"
#include "tools/eval/metrics.h"

int main(int argc, char** argv) {
  using namespace interslice::eval;
  EvalOptions o;
  std::vector<std::string> experiments = {"dropk", "thick", "artificial",
                                          "convergence"};
  CLI::App app{"interslice quality harness"};
  app.add_option("--thin", o.thin_dir, "thin series folder (ground truth)");
  app.add_option("--thick", o.thick_dir,
                 "thick series folder, same frame of reference");
  app.add_option("--out", o.out_dir, "output folder")->required();
  app.add_option("--threshold", o.threshold, "object: value >= threshold (HU)");
  app.add_option("--experiments", experiments,
                 "dropk, thick, artificial, convergence")
      ->delimiter(',');
  app.add_option("--ks", o.ks, "drop-k factors")->delimiter(',');
  app.add_option("--methods", o.methods,
                 "nearest, linear, cg15, cgtol, direct (+ -mm variants)")
      ->delimiter(',');
  app.add_option("--roi", o.roi, "auto | full | i0,i1,j0,j1");
  app.add_option("--roi-margin", o.roi_margin, "auto ROI margin, voxels");
  app.add_option("--cg-iterations", o.cg_iterations, "iterations of cg15");
  app.add_option("--cg-tolerance", o.cg_tolerance,
                 "relative residual target of cgtol");
  app.add_option("--cg-max-iterations", o.cg_max_iterations,
                 "iteration cap of cgtol");
  app.add_option("--top-slab-mm", o.top_slab_mm,
                 "height of the skull-top slab for topology");
  app.add_option("--threads", o.threads, "threads (0 = all)");
  CLI11_PARSE(app, argc, argv);

  interslice::QuietDicomToolkitLogging();
  SetItkThreads(o.threads);
  Recorder recorder(o.out_dir);
  const auto start = std::chrono::steady_clock::now();
  recorder.meta()["threshold"] = o.threshold;
  recorder.meta()["ks"] = o.ks;
  recorder.meta()["methods"] = o.methods;
  recorder.meta()["cg_iterations"] = o.cg_iterations;
  recorder.meta()["cg_tolerance"] = o.cg_tolerance;
  recorder.meta()["cg_max_iterations"] = o.cg_max_iterations;
  recorder.meta()["threads"] = o.threads;
  recorder.meta()["experiments"] = experiments;
  recorder.meta()["top_slab_mm"] = o.top_slab_mm;
  int failures = 0;
  for (const std::string& e : experiments) {
    const auto t0 = std::chrono::steady_clock::now();
    absl::Status status;
    if (e == "dropk") {
      status = o.thin_dir.empty() ? absl::InvalidArgumentError("no --thin")
                                  : RunDropK(o, recorder);
    } else if (e == "thick") {
      status = o.thick_dir.empty() || o.thin_dir.empty()
                   ? absl::InvalidArgumentError("no --thick/--thin")
                   : RunThickToThin(o, recorder);
    } else if (e == "artificial") {
      status = RunArtificial(o, recorder);
    } else if (e == "convergence") {
      status = RunConvergence(o, recorder);
    } else {
      status = absl::InvalidArgumentError("unknown experiment " + e);
    }
    const double s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0)
            .count();
    recorder.meta()["seconds"][e] = s;
    if (!status.ok()) {
      ++failures;
      recorder.meta()["errors"][e] = status.ToString();
      std::fprintf(stderr, "%s FAILED: %s\n", e.c_str(),
                   status.ToString().c_str());
    } else {
      std::fprintf(stderr, "%s done in %.1f s\n", e.c_str(), s);
    }
    // Write after every experiment so a long run leaves partial results.
    (void)recorder.Finish();
  }
  recorder.meta()["seconds"]["total"] =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count();
  const absl::Status status = recorder.Finish();
  if (!status.ok()) {
    std::fprintf(stderr, "%s\n", status.ToString().c_str());
    return 1;
  }
  return failures == 0 ? 0 : 2;
}

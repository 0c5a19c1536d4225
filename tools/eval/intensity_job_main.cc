// interslice_intensity_job: one pipeline job (RunJob, core/pipeline) with the
// intensity method chosen, for timing and peak memory of the intensity series
// (issue 23) before the option reaches the CLI. Not a product command.
//
//   interslice_intensity_job --input DIR --out DIR --threshold HU
//       [--method morph|direct|cg|linear] [--intensity none|linear|morph]
//       [--threads N] [--report FILE]
//
// --intensity none writes no intensity series (the mask job alone); linear
// and morph write series-intensity/ with that JobSpec::intensity_method. The
// job writes the mask and distance as NIfTI and the STL mesh, as `interslice
// run` does by default.
#include <cstdio>
#include <fstream>
#include <string>

#include "CLI/CLI.hpp"
#include "core/dicom/series_reader.h"
#include "core/pipeline/pipeline.h"

int main(int argc, char** argv) {
  std::string input, out, method = "morph", intensity = "morph", report_path;
  float threshold = 300;
  int threads = 0;
  CLI::App app{"one interslice job with a chosen intensity method"};
  app.add_option("--input", input, "DICOM series folder")->required();
  app.add_option("--out", out, "output folder")->required();
  app.add_option("--threshold", threshold, "object threshold (HU)");
  app.add_option("--method", method, "mask method: morph, direct, cg, linear");
  app.add_option("--intensity", intensity, "none, linear or morph");
  app.add_option("--threads", threads, "threads (0 = all)");
  app.add_option("--report", report_path, "report JSON file");
  CLI11_PARSE(app, argc, argv);
  interslice::QuietDicomToolkitLogging();
  interslice::JobSpec spec;
  spec.inputs = {input};
  spec.output_dir = out;
  spec.lower_threshold = threshold;
  if (method == "morph") {
    spec.solver.method = interslice::SolverMethod::kMorph;
  } else if (method == "direct") {
    spec.solver.method = interslice::SolverMethod::kDirect;
  } else if (method == "linear") {
    spec.solver.method = interslice::SolverMethod::kLinear;
  } else if (method != "cg") {
    std::fprintf(stderr, "unknown method %s\n", method.c_str());
    return 1;
  }
  if (intensity != "none") {
    spec.output_series = {"intensity"};
    spec.intensity_method = intensity;
  }
  interslice::ComputeContext context;
  context.threads = threads;
  auto report = interslice::RunJob(spec, context);
  if (!report.ok()) {
    std::fprintf(stderr, "%s\n", report.status().ToString().c_str());
    return 1;
  }
  report->peak_rss_bytes = interslice::PeakRssBytes();
  const std::string json = interslice::JobReportToJson(*report);
  if (!report_path.empty()) std::ofstream(report_path) << json << "\n";
  return 0;
}

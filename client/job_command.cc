#include "client/job_command.h"

#include <cstdio>
#include <fstream>
#include <variant>

#include "CLI/CLI.hpp"
#include "client/progress_display.h"
#include "job/options.h"

namespace interslice::client {
namespace {

template <typename Options>
void Add(CLI::App& app, Options& options,
         std::span<const job::OptionDef<Options>> table) {
  for (const job::OptionDef<Options>& def : table) {
    if ((def.doors & job::kCommandLine) == 0) continue;
    const std::string name = job::CommandLineName(def.key);
    const std::string help(def.help);
    CLI::Option* option = nullptr;
    std::visit(
        [&](auto member) {
          using T = std::remove_reference_t<decltype(options.*member)>;
          if constexpr (std::is_same_v<T, bool>) {
            option = app.add_flag(name, options.*member, help);
          } else if constexpr (std::is_same_v<T, std::optional<bool>>) {
            // --name and --no-name; neither keeps the default.
            std::optional<bool>* value = &(options.*member);
            CLI::Option* yes = app.add_flag_callback(
                name, [value] { *value = true; }, help);
            CLI::Option* no = app.add_flag_callback(
                "--no-" + name.substr(2), [value] { *value = false; },
                "The opposite of " + name);
            yes->excludes(no);
            option = yes;
          } else if constexpr (std::is_same_v<T, std::string> ||
                               std::is_same_v<T, double>) {
            option = app.add_option(name, options.*member, help);
            // Show the default where there is one.
            if (!CLI::detail::to_string(options.*member).empty()) {
              option->capture_default_str();
            }
          } else {
            option = app.add_option(name, options.*member, help);
          }
        },
        def.member);
    if (def.required) option->required();
  }
}

}  // namespace

void AddJobOptions(CLI::App& app, job::InterpolationOptions& options) {
  app.add_option("inputs", options.inputs,
                 "DICOM folder(s) or file(s); folders are searched recursively")
      ->required();
  Add(app, options, job::InterpolationOptionTable());
  app.add_option("--out", options.out, "Output folder (created if missing)")
      ->required();
}

void AddJobOptions(CLI::App& app, job::FillJobOptions& options) {
  app.add_option("segmentation", options.segmentation,
                 "Label map (.nii, .nii.gz, .nrrd; integer labels, 0 = "
                 "background) on the reference series' grid, or a DICOM SEG "
                 "(label = segment number) or RTSTRUCT (label = ROI number) "
                 "drawn on the reference series")
      ->required();
  app.add_option("--reference", options.reference,
                 "The DICOM series the segmentation was drawn on (folders "
                 "or files)")
      ->required();
  Add(app, options, job::FillOptionTable());
  app.add_option("--out", options.out, "Output folder (created if missing)")
      ->required();
}

void AddLocalRunOptions(CLI::App& app, LocalRunArguments& args) {
  app.add_option("--report", args.report, "Write a JSON report to this file");
  app.add_option("--threads", args.threads, "Worker threads (0 = all cores)")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  app.add_flag("--quiet", args.quiet, "No progress display or summary");
}

int FailWith(const absl::Status& status) {
  std::fprintf(stderr, "interslice: error: %s\n",
               std::string(status.message()).c_str());
  return 1;
}

int ExecuteJob(const job::JobKind& job, const LocalRunArguments& args) {
  ProgressDisplay display(stderr, !args.quiet);
  ComputeContext context;
  context.threads = args.threads;
  context.progress = [&display](const ProgressEvent& e) { display.Update(e); };
  absl::StatusOr<job::JobResult> result = job.Run(context);
  display.Finish();
  if (!result.ok()) return FailWith(result.status());
  for (const std::string& w : result->warnings) {
    std::fprintf(stderr, "interslice: warning: %s\n", w.c_str());
  }
  if (!args.report.empty()) {
    std::ofstream file(args.report);
    file << result->report_json << "\n";
    file.close();
    if (!file) {
      std::fprintf(stderr, "interslice: error: cannot write report %s\n",
                   args.report.c_str());
      return 1;
    }
  }
  if (!args.quiet) {
    for (const std::string& line : result->summary) {
      std::printf("%s\n", line.c_str());
    }
  }
  return 0;
}

}  // namespace interslice::client

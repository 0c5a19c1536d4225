#include "client/cli.h"

#include <cstdio>
#include <cstdlib>
#include <string>

#include "CLI/CLI.hpp"
#include "client/fill_command.h"
#include "client/run_command.h"
#ifdef INTERSLICE_WITH_SERVER
#include "client/remote_commands.h"
#endif
#include "core/dicom/series_reader.h"

namespace interslice::client {

int RunCli(int argc, char** argv) {
  CLI::App app{
      "interslice: smooth shape-based interpolation of DICOM series "
      "(Csebfalvi et al. 2001) into isotropic volumes and surface meshes"};
  app.require_subcommand(1);
  app.set_version_flag("--version", "interslice 0.1.0");

  RunArguments run_args;
  CLI::App* run = app.add_subcommand(
      "run", "Run the whole pipeline in this process (no server)");
  AddRunOptions(*run, run_args);
  FillArguments fill_args;
  CLI::App* fill = app.add_subcommand(
      "fill",
      "Fill a segmentation (label map, DICOM SEG or RTSTRUCT) between its "
      "key slices for every label, in this process (or on a server with "
      "--server)");
  AddFillOptions(*fill, fill_args);
#ifdef INTERSLICE_WITH_SERVER
  RemoteCommands remote;
  remote.Register(app);
  remote.RegisterFill(*fill, fill_args);
#endif

  // CLI11 reports an unknown command only as "a subcommand is required".
  const auto is_command = [&app](const std::string& name) {
    for (const CLI::App* sub : app.get_subcommands({})) {
      if (sub->check_name(name)) return true;
    }
    return false;
  };
  if (argc > 1 && argv[1][0] != '-' && !is_command(argv[1])) {
    std::fprintf(stderr,
                 "interslice: error: unknown command '%s' (see --help)\n",
                 argv[1]);
    return 1;
  }
  if (std::getenv("INTERSLICE_DCMTK_LOG") == nullptr)
    QuietDicomToolkitLogging();
  try {
    app.parse(argc, argv);
  } catch (const CLI::CallForHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForAllHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForVersion& e) {
    return app.exit(e);
  } catch (const CLI::ParseError& e) {
    // One line and exit code 1, whatever CLI11's own code would be.
    std::fprintf(stderr, "interslice: error: %s (see --help)\n", e.what());
    return 1;
  }
  if (run->parsed()) return ExecuteRun(run_args);
#ifdef INTERSLICE_WITH_SERVER
  if (const int rc = remote.ExecuteFill(); rc >= 0) return rc;
#endif
  if (fill->parsed()) return ExecuteFill(fill_args);
#ifdef INTERSLICE_WITH_SERVER
  if (const int rc = remote.Execute(); rc >= 0) return rc;
#endif
  return 1;
}

}  // namespace interslice::client

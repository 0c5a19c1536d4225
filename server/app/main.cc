// interslice-server: the gRPC daemon. Its flags are a table
// (server/app/flags.h); everything else lives in server/app/server.cc.
#include <cstdio>
#include <string>

#include "CLI/CLI.hpp"
#include "server/app/flags.h"
#include "server/app/server.h"
#include "server/engine/job_worker.h"
#include "server/net/dimse/scu.h"

int main(int argc, char** argv) {
  // Before any thread starts (it sets an environment variable that DCMTK
  // reads at each outgoing connection): see server/net/dimse/scu.h.
  interslice::server::dimse::DisableNagleOnOutgoingAssociations();
  // A job's worker process (server/engine/job_worker.h): the server starts
  // this executable again with this one argument.
  if (argc == 2 && std::string(argv[1]) == "--job-worker") {
    return interslice::server::RunJobWorker(0, 1);
  }
  interslice::server::ServerOptions options;
  CLI::App app{"interslice-server: the interslice gRPC daemon"};
  app.set_version_flag("--version", "interslice-server 0.1.0");
  interslice::server::AddServerFlags(app, options);
  bool check_config = false;
  app.add_flag("--check-config", check_config,
               "Check the DICOM configuration and exit: load the peers and "
               "rules files as a start would, C-ECHO every peer, print what "
               "each rule matches; exit code 0, or 1 with one line per "
               "problem");
  try {
    app.parse(argc, argv);
  } catch (const CLI::CallForHelp& e) {
    return app.exit(e);
  } catch (const CLI::CallForVersion& e) {
    return app.exit(e);
  } catch (const CLI::ParseError& e) {
    std::fprintf(stderr, "interslice-server: error: %s (see --help)\n",
                 e.what());
    return 1;
  }
  if (check_config) return interslice::server::CheckConfig(options);
  return interslice::server::RunServer(options);
}

// The `interslice` command line: parses arguments, dispatches subcommands,
// and turns every failure into a one-line reason on stderr with exit code 1.
#ifndef INTERSLICE_CLIENT_CLI_H_
#define INTERSLICE_CLIENT_CLI_H_

namespace interslice::client {

// Exit codes: 0 success (or --help), 1 bad input or failure.
int RunCli(int argc, char** argv);

}  // namespace interslice::client

#endif  // INTERSLICE_CLIENT_CLI_H_

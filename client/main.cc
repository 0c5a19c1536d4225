// `interslice`: the command line client. All logic lives in cli.cc.
#include "client/cli.h"

int main(int argc, char** argv) {
  return interslice::client::RunCli(argc, argv);
}

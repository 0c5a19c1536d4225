// interslice-server's command line: every flag of ServerOptions as one row
// of a table (its names, the field it sets, its help text and its checks),
// registered with CLI11 by one loop. A new option is a field in
// ServerOptions (server.h) and a row here.
#ifndef INTERSLICE_SERVER_APP_FLAGS_H_
#define INTERSLICE_SERVER_APP_FLAGS_H_

#include <array>
#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <utility>
#include <variant>
#include <vector>

#include "CLI/CLI.hpp"
#include "server/app/server.h"

namespace interslice::server {

// The ServerOptions field a flag sets; a bool field is a flag without a
// value, a vector a repeatable option.
using ServerOptionField =
    std::variant<std::string ServerOptions::*, int ServerOptions::*,
                 int64_t ServerOptions::*, double ServerOptions::*,
                 bool ServerOptions::*,
                 std::vector<std::string> ServerOptions::*>;

// One row of the table: plain data (a constant table, nothing to destroy).
struct ServerFlag {
  const char* names;  // "--listen", or aliases "--status-listen,--http-listen"
  ServerOptionField field;
  const char* help;
  bool show_default = false;  // the help shows the field's default
  bool required = false;
  // Accepted values: a range (of ints or of numbers), or one of a list
  // (up to four values; the rest null).
  std::optional<std::pair<int, int>> int_range;
  std::optional<std::pair<double, double>> float_range;
  std::array<const char*, 4> one_of = {};
};

// Every flag, in the order --help lists them.
std::span<const ServerFlag> ServerFlags();

// Registers every row of ServerFlags() on `app`, setting `options`.
void AddServerFlags(CLI::App& app, ServerOptions& options);

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_APP_FLAGS_H_

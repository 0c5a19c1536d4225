// The daemon's log: spdlog on stderr, as text or JSON lines, every message
// one line (LogSafe is the backstop for what the call sites escape).
#ifndef INTERSLICE_SERVER_APP_LOGGING_H_
#define INTERSLICE_SERVER_APP_LOGGING_H_

#include "absl/status/status.h"
#include "server/app/server.h"

namespace interslice::server {

// The default logger by --log-format (text | json) and --log-level;
// INVALID_ARGUMENT naming the flag for any other value.
absl::Status SetUpLogging(const ServerOptions& options);

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_APP_LOGGING_H_

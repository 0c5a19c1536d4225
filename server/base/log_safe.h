// Text from clients (labels, spec strings, file names, identities) and text
// derived from it (error messages that quote it) is escaped before it reaches
// a log line or an error message, so that it can never start a line of its
// own (a forged log entry) or carry terminal escape sequences.
#ifndef INTERSLICE_SERVER_BASE_LOG_SAFE_H_
#define INTERSLICE_SERVER_BASE_LOG_SAFE_H_

#include <string>

#include "absl/strings/string_view.h"

namespace interslice::server {

// `text` with '\n', '\r' and '\t' written as \n, \r and \t, every other
// byte below 0x20, 0x7f and every byte that is not part of a well-formed
// UTF-8 sequence written as \xHH. Printable ASCII (backslashes included) and
// valid UTF-8 pass unchanged, so LogSafe(LogSafe(x)) == LogSafe(x) and
// layers may each apply it. Pure; the result is one line.
std::string LogSafe(absl::string_view text);

// Whether LogSafe(text) == text: printable ASCII and valid UTF-8 only.
bool IsLogSafe(absl::string_view text);

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_BASE_LOG_SAFE_H_

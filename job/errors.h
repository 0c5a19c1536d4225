// Errors that name the option they are about. The job layer makes them with
// the option's key ("energy_units"); each door says the key in its own words
// before the error reaches a person:
//   command line: "--energy-units: unknown units 'inch' (choose from voxel,
//   mm)" rules file:   "job.energy_units: unknown units 'inch' (...)" (or
//   "fill.") wire:         "spec.energy_units: unknown units 'inch' (...)"
// The key travels as a payload of the absl::Status; the message alone reads
// "energy_units: unknown units ..." wherever an error is shown unrendered.
#ifndef INTERSLICE_JOB_ERRORS_H_
#define INTERSLICE_JOB_ERRORS_H_

#include <optional>
#include <string>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"

namespace interslice::job {

// INVALID_ARGUMENT "<key>: <message>" carrying `key`.
absl::Status OptionError(absl::string_view key, absl::string_view message);

// The key an error names, if OptionError made it.
std::optional<std::string> ErrorOptionKey(const absl::Status& status);

// The message without its "<key>: " prefix (the whole message for other
// errors).
std::string ErrorMessageWithoutKey(const absl::Status& status);

// How each door names an option's key.
enum class ErrorDoor { kCommandLine, kRulesJob, kRulesFill, kWire };

// `status` with its key named for `door`: the same code, the message
// "<field>: <message>"; errors without a key unchanged. kWire names the
// field of interslice.v1.JobSpec from the option tables (fill options first
// when `fill` is true).
absl::Status ForDoor(const absl::Status& status, ErrorDoor door,
                     bool fill = false);

}  // namespace interslice::job

#endif  // INTERSLICE_JOB_ERRORS_H_

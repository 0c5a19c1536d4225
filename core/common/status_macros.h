// Helpers for propagating absl::Status through module boundaries.
#ifndef INTERSLICE_CORE_COMMON_STATUS_MACROS_H_
#define INTERSLICE_CORE_COMMON_STATUS_MACROS_H_

#include "absl/status/status.h"
#include "absl/status/statusor.h"

#define INTERSLICE_STATUS_CONCAT_INNER_(a, b) a##b
#define INTERSLICE_STATUS_CONCAT_(a, b) INTERSLICE_STATUS_CONCAT_INNER_(a, b)

// Returns from the enclosing function when `expr` (an absl::Status) is not OK.
#define INTERSLICE_RETURN_IF_ERROR(expr)                                      \
  do {                                                                        \
    if (absl::Status interslice_status_ = (expr); !interslice_status_.ok()) { \
      return interslice_status_;                                              \
    }                                                                         \
  } while (false)

// `lhs = value of rexpr` when `rexpr` (an absl::StatusOr) holds a value;
// otherwise returns its status from the enclosing function.
#define INTERSLICE_ASSIGN_OR_RETURN(lhs, rexpr) \
  INTERSLICE_ASSIGN_OR_RETURN_IMPL_(            \
      INTERSLICE_STATUS_CONCAT_(interslice_statusor_, __LINE__), lhs, rexpr)

#define INTERSLICE_ASSIGN_OR_RETURN_IMPL_(statusor, lhs, rexpr) \
  auto statusor = (rexpr);                                      \
  if (!statusor.ok()) return std::move(statusor).status();      \
  lhs = std::move(statusor).value()

#endif  // INTERSLICE_CORE_COMMON_STATUS_MACROS_H_

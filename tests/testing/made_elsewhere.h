// Test inputs made with interslice's own writers (a SEG of `interslice run
// --seg`, an RTSTRUCT of `interslice fill --rtstruct`) stand for objects a
// person or another system made. The DICOM node never takes its own
// results as input unless a rule asks (server/node/config.h, own_results),
// so such fixtures get another Manufacturer and Manufacturer's Model Name
// first, as they would have had.
#ifndef INTERSLICE_TESTS_TESTING_MADE_ELSEWHERE_H_
#define INTERSLICE_TESTS_TESTING_MADE_ELSEWHERE_H_

#include <string>

#include "absl/status/status.h"

namespace interslice::testing {

// Rewrites the DICOM file at `path` in place with Manufacturer "a
// contouring workstation" and Manufacturer's Model Name "test"; nothing
// else changes (UIDs, pixel data).
absl::Status MarkAsMadeElsewhere(const std::string& path);

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_MADE_ELSEWHERE_H_

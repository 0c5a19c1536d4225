// Comparing result folders: a job through the server (or a replica, or a
// DICOM rule) must write the same bytes as the in-process run.
#ifndef INTERSLICE_TESTS_TESTING_FILES_H_
#define INTERSLICE_TESTS_TESTING_FILES_H_

#include <set>
#include <string>

namespace interslice::testing {

// EXPECTs that every file of `expected_dir` (but those named in `except`)
// is in `actual_dir` with the same bytes, and that there are at least
// `min_files` of them (so an empty reference cannot pass).
void ExpectSameFiles(const std::string& expected_dir,
                     const std::string& actual_dir, int min_files,
                     const std::set<std::string>& except = {});

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_FILES_H_

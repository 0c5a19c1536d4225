// Comparing result folders: a job through the server (or a replica, or a
// DICOM rule) must write the same bytes as the in-process run.
#ifndef INTERSLICE_TESTS_TESTING_FILES_H_
#define INTERSLICE_TESTS_TESTING_FILES_H_

#include <set>
#include <string>

namespace interslice::testing {

// How DICOM files (*.dcm) are compared: byte for byte, or by size only
// (files written at another time: their creation date and time differ,
// nothing else may; the DICOM tests compare pixels and UIDs themselves).
enum class DicomComparison { kSameBytes, kSameSize };

// EXPECTs that every file of `expected_dir` and of its folders (a derived
// series, the previews), but those whose path relative to it is named in
// `except`, is in `actual_dir` at the same relative path with the same
// bytes, and that there are at least `min_files` of them (so an empty
// reference cannot pass).
void ExpectSameFiles(const std::string& expected_dir,
                     const std::string& actual_dir, int min_files,
                     const std::set<std::string>& except = {},
                     DicomComparison dicom = DicomComparison::kSameBytes);

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_FILES_H_

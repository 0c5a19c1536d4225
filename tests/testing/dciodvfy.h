// dciodvfy (David Clunie's dicom3tools), the validator of every DICOM output
// test: a file is valid when dciodvfy exits 0 AND prints no "Error" line.
// Both are checked, so a dciodvfy that cannot run at all (missing, crashed,
// "Abort" on an unreadable file) can never pass as "no errors counted".
#ifndef INTERSLICE_TESTS_TESTING_DCIODVFY_H_
#define INTERSLICE_TESTS_TESTING_DCIODVFY_H_

#include <string>
#include <vector>

namespace interslice::testing {

struct DciodvfyReport {
  // dciodvfy's exit status (0: it found no error); -1 when it did not run.
  int exit_code = -1;
  std::vector<std::string> errors;    // its "Error" and "Abort" lines
  std::vector<std::string> warnings;  // its "Warning" lines
};

// Runs dciodvfy on one file. A missing dciodvfy fails the current test
// (tools.h: RequireTool) and gives exit_code -1 with one error naming it.
DciodvfyReport Dciodvfy(const std::string& path);

// The number of problems over `paths`: every error line, plus one for each
// file whose exit status is not 0 although it printed no error line. Each
// is appended to `details` (when given) as "<file name>: <line>" and
// printed.
int DciodvfyErrors(const std::vector<std::string>& paths,
                   std::string* details = nullptr);

// EXPECTs that every file is valid; prints each distinct warning once.
void ExpectValidIod(const std::vector<std::string>& paths);

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_DCIODVFY_H_

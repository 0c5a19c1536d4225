// A bounded structural scan of an encoded DICOM data set, run on every
// received instance before any DICOM parser of the server process reads it.
//
// Why: DCMTK's parser recurses once per nested sequence and has no depth
// limit, so one instance with 10,000 nested sequences (360 KB) overflows the
// stack of the thread that parses it (issue 22). The listener therefore
// stores what it receives bit for bit (DCMTK writes the data set's bytes to
// a file without parsing them), scans that file here, and only a file that
// passes is parsed by DCMTK (for its UIDs and the rules' facts). The scan
// itself never recurses: it walks the encoding with an explicit stack, reads
// only tags, VRs and lengths (values are skipped, never loaded), and stops
// at the first violation.
//
// What passes (PS3.5 section 7): elements in the file's transfer syntax
// (implicit or explicit VR, little or big endian, deflated; encapsulated
// pixel data as a sequence of fragments); the VR of an implicit-VR element
// from DCMTK's data dictionary (unknown tags are UN); undefined lengths only
// on sequences, on UN (whose content is then implicit VR little endian,
// PS3.5 6.2.2) and on encapsulated pixel data; every defined length within
// its enclosing item, sequence and the file; items only inside sequences and
// delimiters where they belong. Limits: nesting depth (sequences inside
// sequences), elements in all (items and fragments count), inflated bytes of
// a deflated data set.
//
// Errors: INVALID_ARGUMENT with the offset and what is wrong ("nesting
// deeper than 32 sequences at byte 1234"); never data-set values, so the
// message is free of patient data. NOT_FOUND / INTERNAL when the file cannot
// be opened or read.
#ifndef INTERSLICE_SERVER_NODE_DATASET_SCAN_H_
#define INTERSLICE_SERVER_NODE_DATASET_SCAN_H_

#include <cstdint>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"

namespace interslice::server::node {

struct DatasetScanLimits {
  // Sequences nested inside sequences. The deepest standard IODs the node
  // accepts nest about 5 (RTSTRUCT contour references). DCMTK 3.6.7's
  // parser needs about 1.5 KiB of stack per level (measured: 700 levels
  // fill a 1 MiB thread stack; 10,000 overflow the 8 MiB default), so 32
  // levels cost it about 48 KiB.
  int max_depth = 32;
  // Elements, items and pixel-data fragments in all. An enhanced multi-frame
  // CT of 2,000 frames has about 60,000; DCMTK holds ~200 bytes per element
  // in memory when it parses the header.
  int64_t max_elements = 250000;
  // A deflated data set may inflate to at most this many bytes.
  int64_t max_inflated_bytes = int64_t{1} << 30;
  // In a deflated data set, a value other than the pixel data may hold at
  // most this many bytes: DCMTK cannot come back to a value in a
  // compressed stream, so it loads each one into memory as it parses.
  int64_t max_deflated_value_bytes = int64_t{64} << 20;
};

struct DatasetScanResult {
  // Where the data set starts in the file (after preamble and meta group).
  int64_t dataset_offset = 0;
  std::string transfer_syntax_uid;
  int64_t elements = 0;
  int deepest = 0;  // the deepest sequence nesting seen
};

// Where the data set of a Part 10 file starts and its transfer syntax, from
// its file meta group (explicit VR little endian, group 0002, every value at
// most 64 KiB, at most 64 elements). INVALID_ARGUMENT when the file is not
// Part 10.
struct Part10Meta {
  int64_t dataset_offset = 0;
  std::string transfer_syntax_uid;
};
absl::StatusOr<Part10Meta> ReadPart10Meta(const std::string& path);

// Scans a DICOM Part 10 file: 128-byte preamble, "DICM", the file meta
// group (explicit VR little endian), then the data set in the meta group's
// transfer syntax.
absl::StatusOr<DatasetScanResult> ScanPart10File(
    const std::string& path, const DatasetScanLimits& limits = {});

// Scans a data set given as bytes (no preamble or meta group) in the
// transfer syntax `transfer_syntax_uid` (for tests and the fuzzer).
absl::StatusOr<DatasetScanResult> ScanDatasetBytes(
    std::string_view bytes, const std::string& transfer_syntax_uid,
    const DatasetScanLimits& limits = {});

}  // namespace interslice::server::node

#endif  // INTERSLICE_SERVER_NODE_DATASET_SCAN_H_

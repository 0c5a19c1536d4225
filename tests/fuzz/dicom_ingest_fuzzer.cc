// libFuzzer target: untrusted bytes as DICOM input. The bytes become one or
// more files in a private temporary folder (split at kFileSeparator, so that
// a corpus entry can hold a small series and reach the stack checks), which
// are read (ReadDicomSeries, header scan included) with a small voxel limit;
// when they hold several series, listed (ListDicomSeries) and read again
// choosing one. Every outcome must be a status: no crash, hang, leak or
// unbounded allocation.
#include <stdlib.h>
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <string>
#include <string_view>
#include <system_error>
#include <vector>

#include "absl/status/status.h"
#include "core/common/compute.h"
#include "core/dicom/series_reader.h"

namespace {

namespace fs = std::filesystem;

// Between files of one input. Eight bytes that do not occur in the seed
// files; scripts/fuzz.sh builds multi-file seeds with it.
constexpr std::string_view kFileSeparator = "\xffIS-NEXT";
constexpr int kMaxFiles = 8;
// Small enough that a header claiming a large image is refused quickly,
// large enough for the 512 x 512 x 4 seed series.
constexpr int64_t kMaxVoxels = int64_t{1} << 22;

fs::path& Folder() {
  static fs::path folder;
  return folder;
}

void RemoveFolder() {
  std::error_code ec;
  if (!Folder().empty()) fs::remove_all(Folder(), ec);
}

}  // namespace

extern "C" int LLVMFuzzerInitialize(int* argc, char*** argv) {
  interslice::QuietDicomToolkitLogging();
  interslice::RegisterDicomDecoders();
  std::string pattern =
      (fs::temp_directory_path() / "interslice_fuzz_XXXXXX").string();
  if (mkdtemp(pattern.data()) == nullptr) {
    std::perror("dicom_ingest_fuzzer: mkdtemp");
    std::abort();
  }
  Folder() = pattern;
  std::atexit(RemoveFolder);
  return 0;
}

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const fs::path& folder = Folder();
  std::error_code ec;
  for (const fs::directory_entry& entry : fs::directory_iterator(folder, ec)) {
    fs::remove(entry.path(), ec);
  }
  std::string_view rest(reinterpret_cast<const char*>(data), size);
  for (int i = 0; i < kMaxFiles && (i == 0 || !rest.empty()); ++i) {
    size_t end = rest.find(kFileSeparator);
    if (i == kMaxFiles - 1) end = std::string_view::npos;
    const std::string_view part = rest.substr(0, end);
    std::ofstream(folder / ("IM" + std::to_string(i) + ".dcm"),
                  std::ios::binary)
        .write(part.data(), static_cast<std::streamsize>(part.size()));
    rest = end == std::string_view::npos
               ? std::string_view()
               : rest.substr(end + kFileSeparator.size());
  }

  const std::vector<std::string> inputs = {folder.string()};
  interslice::DicomReadOptions options;
  options.max_voxels = kMaxVoxels;
  interslice::ComputeContext context;
  context.threads = 1;
  auto series = interslice::ReadDicomSeries(inputs, options, context);
  // Several series: list them (the header scan on its own) and read one by
  // its name (the selection path). Listing every input would only scan the
  // same headers twice.
  if (series.status().code() == absl::StatusCode::kFailedPrecondition) {
    auto listed = interslice::ListDicomSeries(inputs);
    if (listed.ok() && !listed->empty()) {
      options.series_instance_uid = listed->back().series_instance_uid;
      series = interslice::ReadDicomSeries(inputs, options, context);
    }
  }
  if (series.ok() && series->image.data.size() !=
                         static_cast<size_t>(series->image.grid.VoxelCount())) {
    std::abort();  // the reader's contract: one value per voxel
  }
  return 0;
}

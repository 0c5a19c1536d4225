// The repository root for the benchmarks' data (data/...): a value from a
// file CMake generates in the build folder (bench/CMakeLists.txt), not a
// compile definition, so that benchmark objects do not depend on where the
// checkout is (tests/testing/paths.h says why).
#ifndef INTERSLICE_BENCH_BENCH_PATHS_H_
#define INTERSLICE_BENCH_BENCH_PATHS_H_

namespace interslice {

// Absolute, without a trailing slash.
const char* BenchSourceDir();

}  // namespace interslice

#endif  // INTERSLICE_BENCH_BENCH_PATHS_H_

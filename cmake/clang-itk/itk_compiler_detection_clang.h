// Clang builds only (the fuzz build, INTERSLICE_BUILD_FUZZERS), included
// before every source that uses ITK (-include, InterSliceDependencies.cmake):
// Debian's ITK 5.2 ships compiler feature tables for GCC alone, and its
// itk_compiler_detection.h stops with "Unsupported compiler" under clang.
// Clang implements every feature that table tests for, so the header is read
// here once as if by GCC 12 (its include guard makes ITK's own later include
// a no-op), and the compiler macros are restored right after. ITK's
// libraries are GCC-built against the same libstdc++: the ABI is the same.
#pragma push_macro("__clang__")
#pragma push_macro("__GNUC__")
#pragma push_macro("__GNUC_MINOR__")
#undef __clang__
#undef __GNUC__
#undef __GNUC_MINOR__
#define __GNUC__ 12
#define __GNUC_MINOR__ 2
#include <itk_compiler_detection.h>
#pragma pop_macro("__GNUC_MINOR__")
#pragma pop_macro("__GNUC__")
#pragma pop_macro("__clang__")

# Finds every third-party dependency once (all Debian bookworm packages; see
# scripts/install-deps.sh). Notes on the Debian packaging are in docs/DESIGN.md.
find_package(PkgConfig REQUIRED)
find_package(Threads REQUIRED)
find_package(absl CONFIG REQUIRED)
find_package(TBB CONFIG REQUIRED)
find_package(DCMTK CONFIG REQUIRED)
find_package(ZLIB REQUIRED)
# GDCM decodes JPEG 2000, which DCMTK's free edition cannot (core/dicom). Its
# config warns about command-line tools that are not installed; harmless.
find_package(GDCM CONFIG REQUIRED)
find_package(nlohmann_json CONFIG REQUIRED)
# libcurl: the DICOMweb client (server/dicomweb/) and the test fixtures.
find_package(CURL REQUIRED)
find_package(CLI11 CONFIG REQUIRED)
find_package(spdlog CONFIG REQUIRED)
# SHA-1 for name-based UIDs (core/dicom_out); SHA-256 of uploads (server).
find_package(OpenSSL REQUIRED)

# FFTW ships no usable CMake config for the float library: use pkg-config.
pkg_check_modules(FFTW3F REQUIRED IMPORTED_TARGET fftw3f)
pkg_check_modules(FFTW3 REQUIRED IMPORTED_TARGET fftw3)
# libdeflate: parallel block compression of .nii.gz / .nrrd (core/volume_io).
pkg_check_modules(LIBDEFLATE REQUIRED IMPORTED_TARGET libdeflate)
# Cairo with its FreeType font backend: the previews (core/preview).
pkg_check_modules(CAIRO REQUIRED IMPORTED_TARGET cairo cairo-ft freetype2)

# OpenVDB ships only FindOpenVDB.cmake in the multiarch cmake folder.
if(CMAKE_LIBRARY_ARCHITECTURE)
  list(APPEND CMAKE_MODULE_PATH
       /usr/lib/${CMAKE_LIBRARY_ARCHITECTURE}/cmake/OpenVDB)
endif()
find_package(OpenVDB REQUIRED COMPONENTS openvdb)
# meshoptimizer: the Encapsulated STL's size cap (core/surface SimplifyMesh).
find_package(meshoptimizer CONFIG REQUIRED)

# Only the ITK modules we use, which keeps include paths and link lines short.
find_package(ITK REQUIRED COMPONENTS
  ITKCommon ITKPath ITKDistanceMap ITKImageGrid ITKImageIntensity
  ITKThresholding ITKIOImageBase ITKIONIFTI ITKIONRRD
  # tools/eval (quality harness): LabelOverlapMeasures, connected components
  ITKImageStatistics ITKConnectedComponents
  # tests: ITK's GDCM series reader as an independent consumer of our DICOM
  ITKIOGDCM)

# ITK's include directories and libraries as one imported interface target,
# so that only the modules that use ITK see its (large) include path.
add_library(interslice_itk INTERFACE)
target_include_directories(interslice_itk SYSTEM INTERFACE ${ITK_INCLUDE_DIRS})
if(CMAKE_CXX_COMPILER_ID STREQUAL "Clang")
  # Debian's ITK headers know only GCC (see the header).
  target_compile_options(interslice_itk INTERFACE
    "SHELL:-include ${CMAKE_CURRENT_LIST_DIR}/clang-itk/itk_compiler_detection_clang.h")
endif()
target_link_libraries(interslice_itk INTERFACE ${ITK_LIBRARIES})

if(INTERSLICE_BUILD_TESTS)
  find_package(GTest CONFIG REQUIRED)
endif()
if(INTERSLICE_BUILD_BENCHMARKS)
  find_package(benchmark CONFIG REQUIRED)
endif()

# The gRPC daemon and the client commands that talk to it. Debian ships no
# protobuf CMake config (only CMake's FindProtobuf module) but does ship
# gRPC's config (gRPC::grpc++, gRPC::grpc_cpp_plugin).
if(INTERSLICE_BUILD_SERVER)
  find_package(Protobuf REQUIRED)
  find_package(gRPC CONFIG REQUIRED)
  find_package(prometheus-cpp CONFIG REQUIRED)
  # The status page's HTTP listener (server/net/http/status_page.cc): the civetweb
  # prometheus-cpp's /metrics already runs on (docs/DESIGN.md).
  find_package(civetweb CONFIG REQUIRED)
  # The DICOM node's peers and rules files (server/node/peers_config.cc, rules.cc).
  find_package(yaml-cpp CONFIG REQUIRED)
  pkg_check_modules(RE2 REQUIRED IMPORTED_TARGET re2)
endif()

#!/usr/bin/env bash
# Installs the Debian bookworm packages interslice needs to build, test and run.
# Idempotent: exits quickly when everything is already present.
set -euo pipefail

packages=(
  build-essential cmake ninja-build pkg-config ccache git
  # the linker (CMakeLists.txt, INTERSLICE_USE_LLD): several times faster than
  # GNU ld on the test binaries
  lld
  libdcmtk-dev dcmtk
  libinsighttoolkit5-dev
  libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler
  libspdlog-dev libfmt-dev
  libgtest-dev libgmock-dev libbenchmark-dev
  libfftw3-dev libtbb-dev
  libopenvdb-dev libboost-iostreams-dev
  # the Encapsulated STL's size cap (core/surface SimplifyMesh): quadric edge
  # collapse; its shared library reaches the image through stage-image.sh's ldd
  libmeshoptimizer-dev
  libcli11-dev prometheus-cpp-dev libcivetweb-dev libabsl-dev nlohmann-json3-dev
  zlib1g-dev libdeflate-dev libgdcm-dev libssl-dev
  # previews (core/preview): Cairo draws the 2D views and writes PNG; the
  # legend's font is DejaVu Sans, loaded from its file (no fontconfig lookup)
  libcairo2-dev fonts-dejavu-core
  dicom3tools
  # the DICOM node (server/dicom): configuration files; a real PACS for its
  # end-to-end tests (Orthanc, started by the tests, never as a service)
  libyaml-cpp-dev libre2-dev orthanc orthanc-dicomweb
  # the Orthanc test fixture talks to its REST API with libcurl
  libcurl4-openssl-dev
  # deploy/ manifests are linted in CI
  yamllint
  # the instrumented build (scripts/build-instrumented.sh: the sanitized suite
  # and the libFuzzer targets): clang with its sanitizer and libFuzzer runtimes
  clang libclang-rt-14-dev
  # a user's tools reading our label maps back (tests/core/labels: nibabel)
  python3-nibabel
  # the OHIF viewer test (tests/viewer/ohif_test.mjs) drives Debian's chromium
  # headless (puppeteer-core, no browser download); the status page test
  # (tests/server/app/server_test.cc) renders in it and checks codes with curl
  chromium curl
  # the HTTPS deployment test (tests/server/net/dicomweb/https_proxy_test.sh):
  # stunnel terminates TLS in front of the loopback HTTP listener
  # (docs/dicomweb.md, "HTTPS"); operators install their own proxy
  stunnel4
)
# Node.js for the viewer test (tests/viewer: a DICOM SEG loaded as OHIF v3
# loads it): Debian's nodejs + npm unless node and npm are already there (a
# NodeSource nodejs bundles npm and conflicts with Debian's npm package).
if ! command -v node >/dev/null || ! command -v npm >/dev/null; then
  packages+=(nodejs npm)
fi
# The viewer test's npm packages, pinned by tests/viewer/package-lock.json;
# installed again when the lockfile is newer than what is installed.
viewer_npm() {
  local dir
  dir="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)/tests/viewer"
  if [ -f "$dir/package-lock.json" ] &&
     { [ ! -f "$dir/node_modules/.package-lock.json" ] ||
       [ "$dir/package-lock.json" -nt "$dir/node_modules/.package-lock.json" ]; }; then
    echo "install-deps: npm ci in tests/viewer"
    npm ci --prefix "$dir" --no-audit --no-fund --ignore-scripts
  fi
  # the prebuilt OHIF viewer, pinned by tests/viewer/ohif/ohif-app.pin
  bash "$dir/ohif/fetch_ohif.sh" >/dev/null
}
# --image: only what building the server and the client needs (the
# container image's build stage, deploy/Dockerfile): no test, lint, fuzzing,
# PACS or viewer tools.
if [ "${1:-}" = "--image" ]; then
  not_for_image=" libgtest-dev libgmock-dev libbenchmark-dev dicom3tools "
  not_for_image+=" git orthanc orthanc-dicomweb yamllint clang "
  not_for_image+=" libclang-rt-14-dev nodejs npm python3-nibabel chromium curl "
  not_for_image+=" stunnel4 "
  kept=()
  for p in "${packages[@]}"; do
    [[ $not_for_image == *" $p "* ]] || kept+=("$p")
  done
  packages=("${kept[@]}")
  viewer_npm() { :; }
fi
# Extra packages for the evaluation report (scripts/eval.sh): plots.
if [ "${1:-}" = "--eval" ]; then
  packages+=(python3-matplotlib python3-numpy)
fi

missing=()
for p in "${packages[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done

if [ ${#missing[@]} -eq 0 ]; then
  echo "install-deps: all ${#packages[@]} packages present"
  viewer_npm
  exit 0
fi

echo "install-deps: installing ${missing[*]}"
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -q
$SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"
viewer_npm

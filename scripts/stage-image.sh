#!/usr/bin/env bash
# Collects what the interslice-server image holds, from built binaries:
#   OUT_DIR/bin/interslice-server, OUT_DIR/bin/interslice   (stripped)
#   OUT_DIR/lib/   every shared library the two load (ldd), but glibc's own,
#                  and gRPC's reflection library (the server dlopen()s it
#                  only with --reflection), stripped
#   OUT_DIR/share/libdcmtk17/   DCMTK's data dictionaries: without them every
#                  implicit-VR data set (what PACS send by default) is
#                  unreadable and the DICOM listener aborts each association
#   OUT_DIR/share/fonts/truetype/dejavu/DejaVuSans.ttf   the previews' legend
#                  font (core/preview/preview.h)
#
#   bash scripts/stage-image.sh SERVER_BINARY CLIENT_BINARY OUT_DIR
#
# One copy of this step for both images: deploy/Dockerfile runs it in its
# build stage on the binaries it compiles; scripts/test-deploy.sh runs it on
# build/'s binaries for deploy/Dockerfile.prebuilt. Both runtime stages copy
# OUT_DIR the same way, so the two images differ only in where the binaries
# were compiled. Runs on Debian bookworm (the libraries are this system's:
# the same packages as the image's debian:bookworm-slim base expects).
set -euo pipefail
if (($# != 3)); then
  echo "usage: $0 SERVER_BINARY CLIENT_BINARY OUT_DIR" >&2
  exit 2
fi
server="$1" client="$2" out="$3"
reflection=/usr/lib/x86_64-linux-gnu/libgrpc++_reflection.so.1.51
for f in "$server" "$client" "$reflection"; do
  [[ -f $f ]] || { echo "stage-image: $f does not exist" >&2; exit 1; }
done
rm -rf "$out"
mkdir -p "$out/bin" "$out/lib" "$out/share/libdcmtk17"
cp "$server" "$out/bin/interslice-server"
cp "$client" "$out/bin/interslice"
strip --strip-unneeded "$out/bin/"*
libs="$({ ldd "$out/bin/interslice-server" "$out/bin/interslice" "$reflection"; } |
  awk '/=> \// {print $3}' | sort -u |
  grep -v -E '/(libc|libm|libdl|libpthread|librt|ld-linux[^/]*)\.so' || true)"
if grep -q 'not found' <<<"$(ldd "$out/bin/interslice-server" "$out/bin/interslice")"; then
  ldd "$out/bin/interslice-server" "$out/bin/interslice" | grep 'not found' >&2
  echo "stage-image: a library the binaries need is missing" >&2
  exit 1
fi
[[ -n $libs ]] || { echo "stage-image: ldd found no libraries" >&2; exit 1; }
while IFS= read -r lib; do cp -L "$lib" "$out/lib/"; done <<<"$libs"
cp -L "$reflection" "$out/lib/"
strip --strip-unneeded "$out/lib/"*
cp /usr/share/libdcmtk17/dicom.dic /usr/share/libdcmtk17/private.dic \
  "$out/share/libdcmtk17/"
mkdir -p "$out/share/fonts/truetype/dejavu"
cp /usr/share/fonts/truetype/dejavu/DejaVuSans.ttf "$out/share/fonts/truetype/dejavu/"
echo "stage-image: $(ls "$out/lib" | wc -l) libraries, $(du -sm "$out" | cut -f1) MB in $out"

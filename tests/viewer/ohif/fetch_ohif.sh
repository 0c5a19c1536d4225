#!/usr/bin/env bash
# Installs the pinned prebuilt OHIF viewer (ohif-app.pin) into tests/viewer/ohif/dist-<version>/
# unless it is already there: `npm pack` of the pinned version, its sha512 checked against the pin,
# and only the package's dist/ folder kept. Prints the dist folder's path on the last line.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
pin="$here/ohif-app.pin"
field() { awk -v k="$1" '$1 == k { print $2 }' "$pin"; }
package="$(field package)" version="$(field version)" integrity="$(field integrity)"
dest="$here/dist-$version"
if [ -f "$dest/.integrity" ] && [ "$(cat "$dest/.integrity")" = "$integrity" ]; then
  echo "$dest"
  exit 0
fi
command -v npm >/dev/null || { echo "fetch_ohif: npm not found" >&2; exit 1; }
work="$(mktemp -d "${TMPDIR:-/tmp}/ohif-fetch.XXXXXX")"
trap 'rm -rf "$work"' EXIT
echo "fetch_ohif: npm pack $package@$version" >&2
(cd "$work" && npm pack --silent "$package@$version" >/dev/null)
tarball="$(ls "$work"/*.tgz)"
actual="sha512-$(openssl dgst -sha512 -binary "$tarball" | base64 -w0)"
if [ "$actual" != "$integrity" ]; then
  echo "fetch_ohif: $package@$version tarball has $actual, the pin says $integrity" >&2
  exit 1
fi
tar -xzf "$tarball" -C "$work" package/dist
rm -rf "$dest"
mv "$work/package/dist" "$dest"
echo "$integrity" >"$dest/.integrity"
echo "$dest"

#!/usr/bin/env bash
# The outputs of four doors on the shipped phantom (data/ct-head-phantom-thick),
# as a manifest of SHA-256 sums, so that a refactoring can be shown to change
# no output byte:
#   run          `interslice run` in process (direct, every output kind)
#   interpolate  the same job through `interslice-server` (gRPC upload)
#   fill         `interslice fill` of a label map kept on every 3rd slice
#   node         a DICOM node rule: storescu of the phantom into the server's
#                listener, the rule's job, its results fetched
#
#   tools/regression/phantom-outputs.sh BUILD_DIR OUT_DIR
#   tools/regression/phantom-outputs.sh --hash OUT_DIR   (the manifest again)
#
# Writes OUT_DIR/manifest.txt ("<sha256>  <door>/<file>", sorted). What
# changes from run to run is left out of the hashes: DICOM files carry the
# times they were written (InstanceCreation, Content, Series and Secondary
# Capture date and time), hashed after those elements are set to fixed
# values (dcmodify on a copy); a report.json is hashed without its timings,
# memory and thread figures, and with its paths relative to the output
# folder. Everything else byte for byte. Compare two manifests with diff.
set -euo pipefail
root="$(cd "$(dirname "$0")/../.." && pwd)"
mode=run
if [[ ${1:-} == --hash ]]; then
  mode=hash
  out="$(cd "${2:?usage: $0 --hash OUT_DIR}" && pwd)"
else
  build="$(cd "${1:?usage: $0 BUILD_DIR OUT_DIR}" && pwd)"
  out="${2:?usage: $0 BUILD_DIR OUT_DIR}"
fi
phantom="$root/data/ct-head-phantom-thick"
work="$(mktemp -d)"
server_pid=""
cleanup() {
  [[ -z $server_pid ]] || kill "$server_pid" 2>/dev/null || true
  rm -rf "$work"
}
trap cleanup EXIT

hash_outputs() {  # hash_outputs OUT_DIR: writes OUT_DIR/manifest.txt
  local out="$1"
  local stamp=(-m "(0008,0012)=20000101" -m "(0008,0013)=000000"
               -m "(0008,0023)=20000101" -m "(0008,0033)=000000"
               -m "(0008,0021)=20000101" -m "(0008,0031)=000000"
               -m "(0018,1012)=20000101" -m "(0018,1014)=000000")
  (
    cd "$out"
    find . -type f ! -name manifest.txt | sort | while IFS= read -r f; do
      f="${f#./}"
      if [[ $(head -c 132 "$f" | tail -c 4) == DICM ]]; then
        cp "$f" "$work/normalised.dcm"
        dcmodify -q -nb -imt "${stamp[@]}" "$work/normalised.dcm"
        echo "$(sha256sum <"$work/normalised.dcm" | cut -c1-64)  $f"
      elif [[ $f == */report.json ]]; then
        echo "$(python3 - "$f" "$out/$(dirname "$f")" <<'PY'
import hashlib, json, sys
folder = sys.argv[2].rstrip("/") + "/"
def strip(v, key=""):
    if isinstance(v, dict):
        return {k: strip(x, k) for k, x in v.items()
                if key != "stages" and
                not any(w in k for w in ("seconds", "time", "rss", "threads"))}
    if isinstance(v, list):
        return [strip(x) for x in v]
    if isinstance(v, str) and v.startswith(folder):
        return v[len(folder):]
    return v
print(hashlib.sha256(json.dumps(strip(json.load(open(sys.argv[1]))),
                                sort_keys=True).encode()).hexdigest())
PY
)  $f"
      else
        echo "$(sha256sum <"$f" | cut -c1-64)  $f"
      fi
    done
  ) >"$work/manifest.txt"
  mv "$work/manifest.txt" "$out/manifest.txt"
  echo "phantom-outputs: $(wc -l <"$out/manifest.txt") files in $out/manifest.txt"
}

if [[ $mode == hash ]]; then
  hash_outputs "$out"
  exit 0
fi
cli="$build/client/interslice"
server_bin="$build/server/interslice-server"
rm -rf "$out"
mkdir -p "$out"
out="$(cd "$out" && pwd)"

job=("$phantom" --threshold 300 --method direct --mesh stl,ply --volume nii,nrrd
     --output-series intensity,distance,mask --previews png,dicom --quiet)

echo "phantom-outputs: run"
"$cli" run "${job[@]}" --out "$out/run" --report "$out/run/report.json"

start_server() {  # start_server SPOOL [FLAGS...]: sets port, dicom_port
  local spool="$1"
  shift
  "$server_bin" --listen 127.0.0.1:0 --spool "$spool" --port-file "$work/ports" \
    --log-level warn "$@" >"$work/server.log" 2>&1 &
  server_pid=$!
  for _ in $(seq 1 200); do [[ -s $work/ports ]] && break; sleep 0.1; done
  port="$(sed -n 1p "$work/ports")"
  dicom_port="$(sed -n 3p "$work/ports")"
}
stop_server() {
  kill -TERM "$server_pid"
  wait "$server_pid" || true
  server_pid=""
  rm -f "$work/ports"
}

echo "phantom-outputs: interpolate"
start_server "$work/spool-grpc"
"$cli" interpolate --server "127.0.0.1:$port" "${job[@]}" --out "$out/interpolate" \
  --report "$out/interpolate/report.json" --deadline 900
stop_server

echo "phantom-outputs: fill"
# A label map on the phantom's own grid (factor 1: no slice inserted), kept on
# every 3rd slice by --key-slices.
"$cli" run "$phantom" --threshold 300 --method linear --factor 1 --volume nii \
  --mesh none --previews none --out "$work/labels" --quiet
"$cli" fill "$work/labels/mask.nii.gz" --reference "$phantom" --key-slices 0-27:3 \
  --method auto --seg --volume nii,nrrd --mesh stl --previews png --quiet \
  --out "$out/fill" --report "$out/fill/report.json"

echo "phantom-outputs: node"
cat >"$work/peers.yaml" <<YAML
accept_unknown_callers: true
peers: []
YAML
cat >"$work/rules.yaml" <<YAML
stable_seconds: 1
rules:
  - name: ct-bone
    match: {modality: CT}
    job: {threshold: 300, method: direct, output_series: [intensity, mask], mesh: [stl]}
YAML
start_server "$work/spool-node" --dicom-listen 127.0.0.1:0 --dicom-peers "$work/peers.yaml" \
  --rules "$work/rules.yaml"
storescu -aec INTERSLICE 127.0.0.1 "$dicom_port" "$phantom"/*.dcm
id=""
for _ in $(seq 1 600); do
  id="$("$cli" list --all --server "127.0.0.1:$port" 2>/dev/null | awk '$2 == "succeeded" {print $1; exit}')"
  [[ -n $id ]] && break
  sleep 0.5
done
[[ -n $id ]] || { cat "$work/server.log"; echo "phantom-outputs: the node made no job" >&2; exit 1; }
"$cli" fetch "$id" --server "127.0.0.1:$port" --out "$out/node" >/dev/null
stop_server

hash_outputs "$out"

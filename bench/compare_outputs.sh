#!/usr/bin/env bash
# Are two builds' outputs the same bytes? Runs `run`, `fill` and `interpolate`
# (each build's own server) on the shipped phantom with both builds and
# compares every file. DICOM objects are compared after removing the
# attributes that hold the time of writing (creation, content, series date
# and time), which differ between any two runs of the same build.
#
#   bash bench/compare_outputs.sh OLD_BUILD_DIR NEW_BUILD_DIR [WORK_DIR]
#
# e.g. a build of main in ../main/build against this checkout's build/. Exit
# 0 when everything is identical; each difference is printed.
set -euo pipefail
root="$(cd "$(dirname "$0")/.." && pwd)"
old_build=$(cd "$1" && pwd) new_build=$(cd "$2" && pwd)
work=${3:-$(mktemp -d "${TMPDIR:-/tmp}/compare-outputs.XXXXXX")}
data="$root/data/ct-head-phantom-thick"
mkdir -p "$work"

same() {  # folder a, folder b
  local a=$1 b=$2 bad=0 f
  if [[ $(cd "$a" && find . -type f | sort) != $(cd "$b" && find . -type f | sort) ]]; then
    echo "DIFF: different files in $a and $b"
    return 1
  fi
  while IFS= read -r f; do
    [[ $f == ./report.json ]] && continue  # timings and memory
    if [[ $f == *.dcm ]]; then
      local ta tb
      ta=$(mktemp); tb=$(mktemp)
      cp "$a/$f" "$ta"; cp "$b/$f" "$tb"
      dcmodify -q -nb -ie -ea "(0008,0012)" -ea "(0008,0013)" -ea "(0008,0021)" \
        -ea "(0008,0023)" -ea "(0008,002a)" -ea "(0008,0031)" -ea "(0008,0033)" \
        "$ta" "$tb"
      cmp -s "$ta" "$tb" || { echo "DIFF: $f"; bad=1; }
      rm -f "$ta" "$tb"
    else
      cmp -s "$a/$f" "$b/$f" || { echo "DIFF: $f"; bad=1; }
    fi
  done < <(cd "$a" && find . -type f | sort)
  return $bad
}

status=0
for v in old new; do
  build_var=${v}_build
  bin="${!build_var}/client/interslice"
  "$bin" run "$data" --threshold 300 --method direct --volume nii,nrrd --mesh stl,ply \
    --output-series intensity,distance --seg --out "$work/$v-run" --quiet --threads 2
  # A label map on the reference grid to fill: the old build's mask at factor 1.
  [[ $v == old ]] && "$bin" run "$data" --threshold 300 --factor 1 --method linear \
    --volume nii --mesh none --out "$work/mask" --quiet
  "$bin" fill "$work/mask/mask.nii.gz" --reference "$data" --key-slices 0-27:3 --mesh stl \
    --seg --volume nii,nrrd --out "$work/$v-fill" --quiet
  server="${!build_var}/server/interslice-server"
  port=$((40000 + RANDOM % 20000))
  "$server" --listen "127.0.0.1:$port" --spool "$work/$v-spool" --log-level warn \
    >"$work/$v-server.log" 2>&1 &
  pid=$!
  for _ in $(seq 150); do "$bin" health --server "127.0.0.1:$port" >/dev/null 2>&1 && break; sleep 0.2; done
  "$bin" interpolate "$data" --threshold 300 --method direct --volume nii,nrrd --mesh stl \
    --output-series intensity --seg --server "127.0.0.1:$port" --out "$work/$v-remote" --quiet
  kill "$pid"; wait "$pid" || true
done
for job in run fill remote; do
  if same "$work/old-$job" "$work/new-$job"; then echo "$job: identical"; else status=1; fi
done
echo "outputs in $work"
exit $status

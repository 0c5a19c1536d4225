#!/usr/bin/env bash
# Whole-job benchmark: the three jobs of the speed table on the
# shipped thick CT phantom to 0.45 mm, and a large synthetic thick series,
# each run as its own `interslice run` process so that its peak memory
# (/usr/bin/time's maximum resident set size) is its own. With --before, a
# second binary runs the same jobs interleaved with the first (before,
# after, before, after, ...), so both see the same machine load; medians
# of --repeat runs are reported, with the load average around each run.
#
#   bench/whole_jobs.sh --after BIN [--before BIN] [--repeat N] [--large]
#                       [--out FILE.md] [--work DIR]
#
# Writes a markdown section (FILE.md, default stdout). Timings are what the
# job's --report says (per stage) and the wall time of the process.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
after="" before="" repeat=3 large=0 out=/dev/stdout
work="${TMPDIR:-/tmp}/interslice-whole-jobs"
while [ $# -gt 0 ]; do
  case "$1" in
    --after) after="$2"; shift 2 ;;
    --before) before="$2"; shift 2 ;;
    --repeat) repeat="$2"; shift 2 ;;
    --large) large=1; shift ;;
    --out) out="$2"; shift 2 ;;
    --work) work="$2"; shift 2 ;;
    *) echo "whole_jobs.sh: unknown option $1" >&2; exit 2 ;;
  esac
done
[ -n "$after" ] || { echo "whole_jobs.sh: --after BIN is required" >&2; exit 2; }
[ -x /usr/bin/time ] || { echo "whole_jobs.sh: needs /usr/bin/time (apt-get install time)" >&2; exit 2; }
phantom="$repo/data/ct-head-phantom-thick"
rm -rf "$work"; mkdir -p "$work"
results="$work/results.tsv"
: > "$results"

# A large thick series like a body CT: 100 slices x 5 mm, 512x512, made from
# the phantom's 28 slices in a back-and-forth order (no jumps between
# neighbours) with new positions and instance UIDs (DCMTK's dcmodify). Not
# committed: generated here.
make_large() {
  local dir="$work/large-series"
  mkdir -p "$dir"
  mapfile -t files < <(cd "$phantom" && ls I*.dcm | sort -t I -k2 -n)
  local n=${#files[@]} k
  for k in $(seq 0 99); do
    local cycle=$((k / (n - 1))) step=$((k % (n - 1))) index
    if [ $((cycle % 2)) -eq 0 ]; then index=$step; else index=$((n - 1 - step)); fi
    local file="$dir/IM$(printf %03d "$k").dcm"
    cp "$phantom/${files[$index]}" "$file"
    dcmodify -q -nb -gin -m "(0020,0032)=-115.5\\-1.85\\$(awk -v k="$k" 'BEGIN{printf "%.2f", 200 + 5 * k}')" \
      -m "(0020,0013)=$((k + 1))" -m "(0020,1041)=$((200 + 5 * k))" "$file"
  done
  echo "$dir"
}

# job name, then the arguments after `run SERIES`.
declare -A job_args
job_names=(direct default dicom)
job_args[direct]="--threshold 300 --spacing 0.45 --method direct --volume nii,nrrd --mesh stl,ply"
job_args[default]="--threshold 300 --spacing 0.45"
job_args[dicom]="--threshold 300 --spacing 0.45 --method direct --output-series mask,distance,intensity --seg --mesh stl,ply,obj"
# Options older binaries lack run with the --after binary only.
declare -A after_only=([default-raw]=1 [dicom-rle]=1)
job_names+=(default-raw dicom-rle)
job_args[default-raw]="--threshold 300 --spacing 0.45 --volume nii-uncompressed"
job_args[dicom-rle]="${job_args[dicom]} --dicom-compression rle"
declare -A job_series
for j in "${job_names[@]}"; do job_series[$j]="$phantom"; done
if [ "$large" = 1 ]; then
  job_names+=(large)
  job_series[large]="$(make_large)"
  job_args[large]="--threshold 300 --spacing 0.7 --method direct --volume nii --mesh stl"
fi

binaries=(after)
declare -A binary=([after]="$after")
if [ -n "$before" ]; then binaries=(before after); binary[before]="$before"; fi

run_one() {  # label job rep
  local label=$1 job=$2 rep=$3 dir="$work/out-$1-$2"
  rm -rf "$dir"
  local load; load="$(cut -d' ' -f1 /proc/loadavg)"
  # shellcheck disable=SC2086
  /usr/bin/time -f "%e %M" -o "$work/time.txt" "${binary[$label]}" run \
    "${job_series[$job]}" ${job_args[$job]} --out "$dir" \
    --report "$work/report.json" --quiet
  python3 - "$work/report.json" "$work/time.txt" "$dir" "$label" "$job" \
      "$rep" "$load" >> "$results" <<'PY'
import json, os, sys
report, timing, outdir, label, job, rep, load = sys.argv[1:]
r = json.load(open(report))
wall, rss_kb = open(timing).read().split()[-2:]
s = r["stages"]
size = sum(os.path.getsize(os.path.join(d, f))
           for d, _, fs in os.walk(outdir) for f in fs)
voxels = r["grid"]["size"][0] * r["grid"]["size"][1] * r["grid"]["size"][2]
print("\t".join(str(x) for x in [
    label, job, rep, load, s.get("solve", 0), s.get("mesh", 0),
    s.get("write", 0), sum(s.values()), wall, int(rss_kb) * 1024, size,
    voxels]))
PY
  rm -rf "$dir"
}

for rep in $(seq 1 "$repeat"); do
  for job in "${job_names[@]}"; do
    # The large job runs once per binary (minutes each).
    if [ "$job" = large ] && [ "$rep" -gt 1 ]; then continue; fi
    for label in "${binaries[@]}"; do
      if [ -n "${after_only[$job]:-}" ] && [ "$label" != after ]; then continue; fi
      echo "whole_jobs.sh: $label $job run $rep" >&2
      run_one "$label" "$job" "$rep"
    done
  done
done

python3 - "$results" "$repeat" > "$out" <<'PY'
import statistics, sys
rows = [l.rstrip("\n").split("\t") for l in open(sys.argv[1]) if l.strip()]
repeat = sys.argv[2]
def med(values): return statistics.median(values)
jobs = []
for r in rows:
    if r[1] not in jobs: jobs.append(r[1])
labels = []
for r in rows:
    if r[0] not in labels: labels.append(r[0])
desc = {
  "direct": "`--method direct`, nii + nrrd + stl + ply",
  "default": "default (`cg`, nii + stl)",
  "default-raw": "default with `--volume nii-uncompressed` (cg, .nii + stl)",
  "dicom-rle": "the DICOM job with `--dicom-compression rle`",
  "dicom": "direct + `--output-series mask,distance,intensity --seg` + 3 meshes",
  "large": "large: 100 x 5 mm 512x512 to 0.7 mm, direct, nii + stl",
}
print("| job | binary | solve s | mesh s | write s | stages total s | wall s | write share | peak RSS MiB | peak / output float volume | output MB | runs | load (1 min) |")
print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
for job in jobs:
    for label in labels:
        sel = [r for r in rows if r[0] == label and r[1] == job]
        if not sel: continue
        solve, mesh, write, total, wall = (med([float(r[i]) for r in sel]) for i in (4, 5, 6, 7, 8))
        rss = med([int(r[9]) for r in sel]); size = med([int(r[10]) for r in sel])
        vol = int(sel[0][11]) * 4
        loads = ", ".join(r[3] for r in sel)
        print(f"| {desc.get(job, job)} | {label} | {solve:.2f} | {mesh:.2f} | {write:.2f} | {total:.2f} | {wall:.2f} | {100 * write / total:.0f}% | {rss / 2**20:.0f} | {rss / vol:.2f} | {size / 1e6:.0f} | {len(sel)} | {loads} |")
PY
echo "whole_jobs.sh: raw rows in $results" >&2

#!/usr/bin/env bash
# Drop-k on multi-label segmentations: keep every k-th slice of a
# fully drawn label map, fill the rest with nearest-slice copy, linear
# stacking, the paper's refinement (cg, direct) and the default method auto
# (per-label choice on held-out key slices), and score every label on the
# withheld slices (Dice, HD95, MSD), plus gap voxels and fill time (wall
# clock and CPU).
#
#   scripts/eval-segmentations.sh [--series DIR] [--labels FILE] [--ks 2,3,5,8]
#                                 [--out DIR] [--threads N] [--build-dir DIR]
#                                 [--real DATA_DIR] [--no-run] [--no-publish]
#
# --real DATA_DIR (issue 24): the phantom's labels and the real
# segmentations prepared by scripts/prepare-fill-data.sh in DATA_DIR
# (TotalSegmentator's 41 and 31 labels, a clinical breast RT structure set:
# Breast + Heart together and Heart, Lt Lung, Tumor Bed one by one, a lung
# tumour drawn as a label map), each with nearest copy, linear stacking, the
# paper's refinement (direct), the morph, auto (its default rule, the
# doubled gap) and auto with the gap-trend rule (auto-trend); one report
# with the goals table, published to docs/eval/
# (CSV per series in docs/eval/segmentations/). About 30 minutes on 2 cores.
#
# Without --labels the labels are made from the series (HU bands after a 3x3
# median, split into 3D connected components, the 20 largest; neighbouring
# bands touch). Any label map on the series' grid can be given instead.
# Default series: ../shared/data/ct-head-phantom-thin; exits 0 with a message
# when it is absent. With the default data the report (segmentations.md,
# CSV, figure) is copied to docs/eval/. About 10 minutes on 2 cores.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
data="$(cd "$repo/.." && pwd)/shared/data"
series="$data/ct-head-phantom-thin"
labels=""
ks="2,3,5,8"
out="$repo/build-eval/segmentations"
build="$repo/build-eval"
threads=0
run=1
publish=1
real=""
# The command line the report quotes, every absolute path in it (also the
# DIR of NAME=DIR) relative to the repository root (../shared/data/...), so
# that no published report names a folder of one machine
# (tests/repo/machine_paths_test.sh keeps them out of docs/).
repo_arg() {
  case "$1" in
    /*) realpath -ms --relative-to="$repo" -- "$1" ;;
    *=/*) printf '%s=%s\n' "${1%%=/*}" \
            "$(realpath -ms --relative-to="$repo" -- "/${1#*=/}")" ;;
    *) printf '%s\n' "$1" ;;
  esac
}
command_line="scripts/eval-segmentations.sh"
for arg in "$@"; do command_line+=" $(repo_arg "$arg")"; done
while [ $# -gt 0 ]; do
  case "$1" in
    --series) series="$2"; shift 2 ;;
    --labels) labels="$2"; shift 2 ;;
    --ks) ks="$2"; shift 2 ;;
    --out) out="$2"; shift 2 ;;
    --threads) threads="$2"; shift 2 ;;
    --build-dir) build="$2"; shift 2 ;;
    --real) real="$2"; shift 2 ;;
    --no-run) run=0; shift ;;
    --no-publish) publish=0; shift ;;
    -h|--help) sed -n 2,27p "$0"; exit 0 ;;
    *) echo "eval-segmentations.sh: unknown option $1" >&2; exit 64 ;;
  esac
done
if [ ! -d "$series" ]; then
  echo "eval-segmentations.sh: series folder $series not found; skipping."
  exit 0
fi
build_harness() {
  if [ ! -f "$build/build.ninja" ]; then
    cmake -S "$repo" -B "$build" -G Ninja -DINTERSLICE_BUILD_SERVER=OFF \
      -DINTERSLICE_BUILD_TESTS=OFF -DINTERSLICE_BUILD_BENCHMARKS=OFF
  fi
  ninja -C "$build" -j2 interslice_fill_eval
}

if [ -n "$real" ]; then
  # Issue 24: the phantom and the real series, one report.
  if [ ! -f "$real/SOURCES" ]; then
    echo "eval-segmentations.sh: no prepared data in $real (scripts/prepare-fill-data.sh)" >&2
    exit 1
  fi
  methods=copy,linear,direct,morph,auto,auto-trend
  eval_bin="$build/tools/eval/interslice_fill_eval"
  run_one() {  # name, harness arguments...
    local name="$1"
    shift
    mkdir -p "$out/$name"
    "$eval_bin" "$@" --ks "$ks" --methods "$methods" --threads "$threads" \
      --out "$out/$name" | tee "$out/$name/run.log"
  }
  if [ "$run" = 1 ]; then
    build_harness
    run_one phantom --series "$series"
    run_one totalseg-41 --labels "$real/totalseg/example_seg.nii.gz"
    run_one totalseg-31 --series "$real/totalseg/ct_dicom" \
      --labels "$real/totalseg/example_seg_dicom.nii.gz"
    run_one rt-breast-heart --series "$real/dicompyler/ct" \
      --labels "$real/dicompyler/rtss.dcm" --rois 4,5
    run_one rt-heart --series "$real/dicompyler/ct" \
      --labels "$real/dicompyler/rtss.dcm" --rois 5
    run_one rt-lung --series "$real/dicompyler/ct" \
      --labels "$real/dicompyler/rtss.dcm" --rois 6
    run_one rt-tumour-bed --series "$real/dicompyler/ct" \
      --labels "$real/dicompyler/rtss.dcm" --rois 9
    run_one lung-tumour --labels "$real/pyradiomics/lung2_label.nrrd"
    # The issue's timing case: the phantom's labels on 150 slices, every
    # 5th a key slice, fills timed only (3 runs, fastest).
    "$eval_bin" --series "$series" --labels "$out/phantom/truth-labels.nii.gz" \
      --slices 150 --ks 5 --methods linear,direct,morph,auto,auto-trend \
      --threads "$threads" --no-score --repeat 3 --out "$out/phantom/timing" |
      tee "$out/phantom/timing.log"
    uptime | tee -a "$out/phantom/timing.log"
    cp "$out/phantom/timing/fill_timing.csv" "$out/phantom/"
  fi
  d="$(cd "$real" && pwd)"
  /usr/bin/python3 "$repo/tools/eval/fill_report.py" "$out" --command "$command_line" --series \
    "phantom=$out/phantom=20 labels made from the thin CT head phantom by HU bands and connected components (as before issue 24); with the timing case." \
    "totalseg-41=$out/totalseg-41=TotalSegmentator's own test data (Apache-2.0): its 41-label segmentation of a CT at 3 mm (example_seg.nii.gz, 122 x 101 x 30, RAS), model output; read on its own grid." \
    "totalseg-31=$out/totalseg-31=TotalSegmentator's 31-label segmentation (example_seg_dicom.nii.gz, nibabel LAS: rows flipped against the DICOM) of its 20-slice DICOM CT (512 x 512, 2 mm). Caveat: the model ran at 3 mm and its output was resampled to the 2 mm slices by nearest neighbour: 7 of the 19 pairs of consecutive slices are identical, so the truth itself is a copy of neighbouring slices and the nearest-slice copy is scored against it." \
    "rt-breast-heart=$out/rt-breast-heart=A clinical breast RT structure set drawn by a person (dicompyler-core test data, BSD-3-Clause): ROIs Breast and Heart (they do not overlap), 3 mm contour planes; its CT slice copied onto every plane (scripts/prepare-fill-data.sh); the key slices' distance from the polygons." \
    "rt-heart=$out/rt-heart=The same structure set, Heart alone (a compact organ drawn by a person)." \
    "rt-lung=$out/rt-lung=The same structure set, Lt Lung alone." \
    "rt-tumour-bed=$out/rt-tumour-bed=The same structure set, Tumor Bed alone (a small target volume drawn by a person)." \
    "lung-tumour=$out/lung-tumour=A lung tumour drawn by a person as a label map on 11 slices of a CT at 5 mm (pyradiomics test data lung2, BSD-3-Clause)."
  if [ "$publish" = 1 ]; then
    docs="$repo/docs/eval"
    mkdir -p "$docs/segmentations"
    cp "$out/segmentations.md" "$docs/"
    cp "$out"/segmentations_dice_*.png "$docs/" 2>/dev/null || true
    for name in phantom totalseg-41 totalseg-31 rt-breast-heart rt-heart rt-lung rt-tumour-bed lung-tumour; do
      mkdir -p "$docs/segmentations/$name"
      for f in fill_summary.csv fill_metrics.csv fill_choices.csv fill_validation_slices.csv fill_timing.csv labels.json; do
        [ -f "$out/$name/$f" ] && cp "$out/$name/$f" "$docs/segmentations/$name/"
      done
    done
    [ -f "$out/phantom/timing.log" ] && cp "$out/phantom/timing.log" "$docs/segmentations/phantom/"
    echo "eval-segmentations.sh: report published to $docs/segmentations.md"
  fi
  echo "eval-segmentations.sh: report at $out/segmentations.md"
  exit 0
fi

default_data=0
if [ "$(cd "$series" && pwd)" = "$data/ct-head-phantom-thin" ] && [ -z "$labels" ]; then
  default_data=1
fi
mkdir -p "$out"
if [ "$run" = 1 ]; then
  build_harness
  args=(--series "$series" --ks "$ks" --out "$out" --threads "$threads")
  if [ -n "$labels" ]; then args+=(--labels "$labels"); fi
  "$build/tools/eval/interslice_fill_eval" "${args[@]}" | tee "$out/run.log"
  # The issue's timing case: the same labels on 150 slices (nearest-slice
  # resampling), every 5th a key slice, fills timed only (3 runs, fastest).
  "$build/tools/eval/interslice_fill_eval" --series "$series" \
    --labels "${labels:-$out/truth-labels.nii.gz}" --slices 150 --ks 5 \
    --methods linear,direct,auto --threads "$threads" --no-score --repeat 3 \
    --out "$out/timing" | tee "$out/timing.log"
  uptime | tee -a "$out/timing.log"
  [ -f "$out/timing/fill_timing.csv" ] && cp "$out/timing/fill_timing.csv" "$out/"
fi
/usr/bin/python3 "$repo/tools/eval/fill_report.py" "$out" --command "$command_line"
if [ "$publish" = 1 ] && [ "$default_data" = 1 ]; then
  docs="$repo/docs/eval"
  mkdir -p "$docs"
  cp "$out/segmentations.md" "$out/fill_summary.csv" "$out/fill_metrics.csv" "$docs"/
  for f in fill_choices.csv fill_timing.csv; do
    [ -f "$out/$f" ] && cp "$out/$f" "$docs"/
  done
  cp "$out/labels.json" "$docs/segmentations_labels.json"
  [ -f "$out/segmentations_dice.png" ] && cp "$out/segmentations_dice.png" "$docs"/
  echo "eval-segmentations.sh: report published to $docs/segmentations.md"
fi
echo "eval-segmentations.sh: report at $out/segmentations.md"

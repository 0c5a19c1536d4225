#!/usr/bin/env bash
# Real segmentations with their series for the drop-k evaluation of
# `interslice fill` (issue 24; scripts/eval-segmentations.sh --real). Too
# large for the repository: prepared outside it, from local git mirrors of
# the public repositories below (clone them, or take them from wherever the
# session keeps mirrors), at the commits named.
#
#   scripts/prepare-fill-data.sh MIRRORS_DIR [OUT_DIR]
#
# MIRRORS_DIR holds one git repository (bare or not) per source, in a folder
# named owner+name (e.g. wasserth+TotalSegmentator/repo or
# wasserth+TotalSegmentator). OUT_DIR defaults to ../data-fill next to the
# repository. Sources, licences:
# - totalseg/: wasserth/TotalSegmentator tests/reference_files (Apache-2.0):
#   example_ct_dicom/ (a 20-slice abdominal CT, 512 x 512, 2 mm) with
#   example_seg_dicom.nii.gz (31 labels, the model's segmentation of it,
#   written by nibabel in LAS: rows flipped against the DICOM order), and
#   example_seg.nii.gz (41 labels on 122 x 101 x 30, 3 mm, RAS) of
#   example_ct_sm.nii.gz.
# - pyradiomics/: AIM-Harvard/pyradiomics data/ (BSD-3-Clause): tumours
#   drawn by a person as label maps (lung2: 11 slices of a lung tumour on
#   CT, 5 mm; brain1: 7 slices of a brain tumour on MR, 6.5 mm).
# - dicompyler/: dicompyler/dicompyler-core tests/testdata/example_data
#   (BSD-3-Clause): rtss.dcm, a clinical breast RT structure set drawn by a
#   person (BODY, Heart, Lt Lung, Breast, Tumor Bed, ...; 3 mm contour
#   planes) and ct.0.dcm, one slice of its CT. The CT's other slices are not
#   published; the reference series is that slice copied onto every contour
#   plane (dcmodify: position, instance number and UID per slice), which is
#   all the fill needs (the geometry; grey values are not used).
set -euo pipefail
mirrors="${1:?usage: prepare-fill-data.sh MIRRORS_DIR [OUT_DIR]}"
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
out="${2:-$(cd "$repo/.." && pwd)/data-fill}"
mkdir -p "$out"

git_dir() {
  local name="$1"
  for d in "$mirrors/$name/repo" "$mirrors/$name"; do
    if git -C "$d" rev-parse --git-dir >/dev/null 2>&1; then
      echo "$d"
      return
    fi
  done
  echo "prepare-fill-data.sh: no git mirror of ${name/+//} in $mirrors" >&2
  exit 1
}
show() { git -C "$1" show "HEAD:$2"; }

# TotalSegmentator.
ts="$(git_dir wasserth+TotalSegmentator)"
mkdir -p "$out/totalseg/ct_dicom"
for f in example_seg_dicom.nii.gz example_seg.nii.gz example_ct_sm.nii.gz; do
  show "$ts" "tests/reference_files/$f" >"$out/totalseg/$f"
done
git -C "$ts" ls-tree --name-only HEAD tests/reference_files/example_ct_dicom/ |
  while read -r f; do
    show "$ts" "$f" >"$out/totalseg/ct_dicom/$(basename "$f").dcm"
  done
show "$ts" LICENSE >"$out/totalseg/LICENSE"
echo "totalseg: $(git -C "$ts" rev-parse HEAD)" >"$out/SOURCES"

# pyradiomics.
pr="$(git_dir AIM-Harvard+pyradiomics)"
mkdir -p "$out/pyradiomics"
for f in lung2_label brain1_label; do
  show "$pr" "data/$f.nrrd" >"$out/pyradiomics/$f.nrrd"
done
show "$pr" LICENSE.txt >"$out/pyradiomics/LICENSE.txt"
echo "pyradiomics: $(git -C "$pr" rev-parse HEAD)" >>"$out/SOURCES"

# dicompyler-core: the structure set and its reference series.
dp="$(git_dir dicompyler+dicompyler-core)"
mkdir -p "$out/dicompyler/ct"
show "$dp" tests/testdata/example_data/rtss.dcm >"$out/dicompyler/rtss.dcm"
show "$dp" tests/testdata/example_data/ct.0.dcm >"$out/dicompyler/ct.0.dcm"
show "$dp" LICENSE >"$out/dicompyler/LICENSE"
echo "dicompyler-core: $(git -C "$dp" rev-parse HEAD)" >>"$out/SOURCES"
# Contour planes: every 3 mm from the lowest to the highest z of any
# contour (the CT's slice positions: its one published slice is at 168.56).
read -r zmin zmax < <(dcmdump +L "$out/dicompyler/rtss.dcm" |
  awk -F'[][]' '/ContourData/ {split($2, a, "\\"); z = a[3] + 0;
    if (n == 0 || z < lo) lo = z; if (n == 0 || z > hi) hi = z; n++}
    END {printf "%.2f %.2f\n", lo, hi}')
series_uid="$(dcmdump +P 0020,000e "$out/dicompyler/ct.0.dcm" |
  sed -n 's/.*\[\(.*\)\].*/\1/p')"
rm -f "$out/dicompyler/ct/"*.dcm
n=0
z="$zmax"
while awk -v z="$z" -v lo="$zmin" 'BEGIN {exit !(z >= lo - 0.01)}'; do
  f="$out/dicompyler/ct/slice$(printf %03d "$n").dcm"
  cp "$out/dicompyler/ct.0.dcm" "$f"
  dcmodify -nb -m "(0020,0032)=-275\\-524\\$z" -m "(0020,0013)=$((n + 1))" \
    -m "(0008,0018)=${series_uid}.9$n" -m "(0020,1041)=$z" "$f"
  n=$((n + 1))
  z="$(awk -v z="$z" 'BEGIN {printf "%.2f", z - 3}')"
done
echo "prepare-fill-data.sh: $n reference slices for the structure set"
echo "prepare-fill-data.sh: data in $out"

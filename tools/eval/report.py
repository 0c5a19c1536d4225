#!/usr/bin/python3
"""Markdown report of the quality harness.

Usage: /usr/bin/python3 tools/eval/report.py OUT_DIR --command CMD
Reads OUT_DIR/results.json (+ the PNGs plots.py made) and writes
OUT_DIR/report.md. Every number in the tables is also in results.json and
metrics.csv.
"""
import argparse
import datetime
import json
import math
import os
import platform
import subprocess

ORDER = ["nearest", "linear", "cg15", "cgtol", "direct", "direct-mm", "morph-raw", "morph"]
LABEL = {"nearest": "nearest original slice",
         "linear": "linear stacking of 2D distance maps",
         "cg15": "15 CG iterations, voxel units (the paper)",
         "cgtol": "CG to tolerance, voxel units",
         "direct": "exact minimiser, voxel units",
         "direct-mm": "exact minimiser, mm units",
         "morph-raw": "registration-based stacking alone (candidate)",
         "morph": "morph: registration, cubic trajectory, monotone values + component filter (`--method morph`)"}
# DESIGN.md section 5 (reference model on the phantom, 300 HU): Dice on
# withheld slices for k = 2, 4, 8, thick -> thin, and HD95 (mm) at k = 8.
DESIGN = {
    "nearest": (0.893, 0.858, 0.767, 0.828, 2.69),
    "mci": (0.925, 0.873, 0.772, 0.819, 3.75),
    "linear": (0.963, 0.925, 0.806, 0.815, 3.32),
    "direct": (0.964, 0.930, 0.814, 0.863, 3.00),
    "cg15": (0.964, 0.931, 0.819, None, 2.92),
}
# DESIGN.md section 1: exact minimiser in mm units.
DESIGN_MM = {4: 0.882, 8: 0.754, "thick": 0.786}


def num(x, fmt="{:.3f}"):
    if x is None:
        return "-"
    if isinstance(x, str):
        return "∞" if x == "inf" else x
    if isinstance(x, float) and (math.isinf(x) or math.isnan(x)):
        return "∞" if math.isinf(x) else "nan"
    return fmt.format(x)


def crease(x):
    if x is None:
        return "-"
    if isinstance(x, str) or x > 1e4:
        return "unbounded (f_zz = 0 between originals)" if (
            isinstance(x, str) or x > 1e4) else num(x)
    return num(x, "{:.2f}")


def comp(c):
    if not c:
        return "-"
    return f"{c['count']} ({c['count_ge100']})"


def rows_for(metrics, experiment, k=None):
    sel = [r for r in metrics if r["experiment"] == experiment
           and (k is None or r["k"] == k)]
    return sorted(sel, key=lambda r: ORDER.index(r["method"])
                  if r["method"] in ORDER else 99)


def full_table(rows, extra_mesh=False):
    head = ("| method | Dice | HD95 mm | HD max mm | MSD mm | crease index | "
            "components (>=100 vox) | truth components | CG iterations | "
            "rel. residual | solve s |")
    if extra_mesh:
        head = head + " mesh mean err mm | mesh max err mm |"
    out = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        it = r.get("iterations")
        line = (f"| {LABEL.get(r['method'], r['method'])} | {num(r['dice'], '{:.4f}')} "
                f"| {num(r['hd95_mm'], '{:.2f}')} | {num(r['hdmax_mm'], '{:.2f}')} "
                f"| {num(r['msd_mm'])} | {crease(r.get('crease'))} "
                f"| {comp(r.get('components'))} | {comp(r.get('truth_components'))} "
                f"| {it if it is not None and r['method'].startswith('cg') else '-'} "
                f"| {num(r.get('relative_residual'), '{:.2g}') if 'relative_residual' in r else '-'} "
                f"| {num(r.get('solve_seconds'), '{:.1f}')} |")
        if extra_mesh:
            line += (f" {num(r.get('mesh_mean_error_mm'))} "
                     f"| {num(r.get('mesh_max_error_mm'))} |")
        out.append(line)
    return "\n".join(out)


def repo_path(path):
    """`path` relative to the repository root (e.g. ../shared/data/...), so
    the report names no folder of one machine."""
    repo = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
    return os.path.relpath(os.path.abspath(path), repo) if os.path.isabs(path) else path


def machine():
    cpu = "?"
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    mem = "?"
    try:
        with open("/proc/meminfo") as f:
            kb = int(f.readline().split()[1])
            mem = f"{kb / 1024 / 1024:.1f} GiB"
    except (OSError, ValueError):
        pass
    return (f"{platform.node()}, {os.cpu_count()} hardware threads (nproc "
            f"{subprocess.run(['nproc'], capture_output=True, text=True).stdout.strip()}), "
            f"{cpu}, {mem} RAM")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("--command", default="")
    ap.add_argument("--default-data", action="store_true",
                    help="the shared phantom at 300 HU: show DESIGN.md figures")
    a = ap.parse_args()
    with open(os.path.join(a.out, "results.json")) as f:
        res = json.load(f)
    meta, metrics = res["meta"], res["metrics"]
    has = lambda name: os.path.exists(os.path.join(a.out, name))
    L = []
    L.append("# interslice quality report")
    L.append("")
    L.append(f"- date: {datetime.datetime.now().strftime('%Y-%m-%d %H:%M %Z').strip()}")
    L.append(f"- machine: {machine()}")
    L.append(f"- command: `{a.command}`")
    L.append(f"- threshold: {meta.get('threshold')} HU (object = value >= threshold); "
             f"threads: {meta.get('threads') or 'all'}")
    if "thin" in meta:
        t = meta["thin"]
        L.append(f"- thin series: `{repo_path(t['dir'])}`, grid {t['grid']['size']} voxels of "
                 f"{[round(s, 4) for s in t['grid']['spacing']]} mm; evaluated ROI "
                 f"(mode `{t['roi_mode']}`): voxels {t['roi_begin']} .. {t['roi_end']} "
                 "(in-plane bounding box of the thresholded series + margin, all slices)")
    if "thick" in meta:
        t = meta["thick"]
        L.append(f"- thick series: `{repo_path(t['dir'])}`, {t['grid']['size'][2]} slices of "
                 f"{t['grid']['spacing'][2]:.3g} mm, factor {t['factor']}, compared at "
                 f"{t['thin_slices_compared']} thin positions from thin slice {t['thin_slice_offset']}")
    L.append(f"- CG: `cg15` = {meta.get('cg_iterations')} iterations; `cgtol` = until "
             f"relative residual <= {meta.get('cg_tolerance')} or "
             f"{meta.get('cg_max_iterations')} iterations (cap)")
    secs = meta.get("seconds", {})
    L.append("- run time: " + ", ".join(f"{k} {v:.0f} s" for k, v in secs.items()))
    if meta.get("errors"):
        L.append(f"- **errors**: {meta['errors']}")
    L.append("")

    ks = sorted({r["k"] for r in metrics if r["experiment"] == "dropk"})
    if ks or any(r["experiment"] == "thick" for r in metrics):
        L.append("## Summary: Dice on withheld slices (DESIGN.md section 5 figures in brackets)")
        L.append("")
        cols = [f"every {k}th" if k != 2 else "every 2nd" for k in ks] + ["thick -> thin", "HD95 mm, every 8th"]
        L.append("| method | " + " | ".join(cols) + " |")
        L.append("|---|" + "---|" * len(cols))
        design_cols = {2: 0, 4: 1, 8: 2}
        methods = [m for m in ORDER if any(r["method"] == m for r in metrics)]
        for m in methods + ["mci"]:
            cells = []
            ref = DESIGN.get(m) if a.default_data else None
            if m == "direct-mm" and a.default_data:
                ref = (None, DESIGN_MM[4], DESIGN_MM[8], DESIGN_MM["thick"], None)
            for k in ks:
                r = [x for x in metrics if x["experiment"] == "dropk" and x["k"] == k and x["method"] == m]
                v = num(r[0]["dice"]) if r else "n/a"
                if ref and k in design_cols and ref[design_cols[k]] is not None:
                    v += f" [{ref[design_cols[k]]:.3f}]"
                cells.append(v)
            r = [x for x in metrics if x["experiment"] == "thick" and x["method"] == m]
            v = num(r[0]["dice"]) if r else "n/a"
            if ref and ref[3] is not None:
                v += f" [{ref[3]:.3f}]"
            cells.append(v)
            r = [x for x in metrics if x["experiment"] == "dropk" and x["k"] == 8 and x["method"] == m]
            v = num(r[0]["hd95_mm"], "{:.2f}") if r else "n/a"
            if ref and ref[4] is not None:
                v += f" [{ref[4]:.2f}]"
            cells.append(v)
            name = LABEL.get(m, "morphological contour interpolation (ITK module) — not run, see below")
            L.append(f"| {name} | " + " | ".join(cells) + " |")
        L.append("")
        L.append("Morphological contour interpolation (Zukić et al. 2016, the ITK remote module "
                 "MorphologicalContourInterpolation used by 3D Slicer and ITK-SNAP) is **not** in "
                 "Debian bookworm's ITK 5.2 (libinsighttoolkit5-dev), so the harness does not run it; "
                 "its row shows n/a (DESIGN.md's figures in brackets where the phantom is used).")
        L.append("")

    for k in ks:
        L.append(f"## Drop-k, k = {k}: keep every {k}th slice, reconstruct with factor {k}, compare withheld slices")
        L.append("")
        L.append(full_table(rows_for(metrics, "dropk", k)))
        L.append("")
        if has(f"reformat_dropk_k{k}.png"):
            L.append(f"![reformats k={k}](reformat_dropk_k{k}.png)")
            L.append("")

    if any(r["experiment"] == "thick" for r in metrics):
        L.append("## Thick -> thin: the thick series reconstructed at the thin series' positions")
        L.append("")
        L.append("Every thin position between the first and the last thick slice is compared "
                 "(the thick slices are 5 mm reconstructions, so even the coinciding positions differ "
                 "from the thin ground truth).")
        L.append("")
        L.append(full_table(rows_for(metrics, "thick")))
        L.append("")
        for name in sorted(os.listdir(a.out)):
            if name.startswith("reformat_thick"):
                L.append(f"![thick reformats]({name})")
                L.append("")

    arts = sorted({r["experiment"] for r in metrics if r["experiment"].startswith("artificial")})
    if arts:
        L.append("## The paper's artificial data (every 8th slice, 64x64x65 voxels of 1 mm, analytic ground truth)")
        L.append("")
        L.append("Shapes as in tests/core/pipeline/paper_artificial_test.cc: sphere r = 20 mm; cross of two "
                 "round-ended tubes r = 6 mm (an X in the xz plane). Ground truth = the analytic shape sampled "
                 "on every slice; mesh errors = |analytic signed distance| at the vertices of the zero level "
                 "set (OpenVDB mesher).")
        L.append("")
        for e in arts:
            L.append(f"### {e}")
            L.append("")
            L.append(full_table(rows_for(metrics, e), extra_mesh=True))
            L.append("")
            rows = rows_for(metrics, e)
            L.append("Energy (voxel units): " + ", ".join(
                f"{r['method']} {r['energy']:.0f}" for r in rows if isinstance(r.get("energy"), (int, float))))
            L.append("")
            if has(f"reformat_{e}_k8.png"):
                L.append(f"![{e}](reformat_{e}_k8.png)")
                L.append("")

    conv = [r for r in metrics if r["experiment"] == "fig5-sphere"]
    dk_cg = [r for r in metrics if r["experiment"] == "dropk" and r["method"] == "cgtol"]
    if conv or dk_cg:
        L.append("## Convergence (paper Figure 5)")
        L.append("")
        L.append("Relative residual |r_k|/|r_0| of projected CG per iteration (the paper plots |d|, "
                 "the update; both decay together). Curves (convergence.csv) are the recursive residual the solver's "
                 "progress callback reports, which drifts in float from the true residual; the table's final "
                 "residual is the one the solver re-measures at the end, which is why a run can stop on the "
                 "tolerance yet report converged = False.")
        L.append("")
        L.append("| data | factor | iterations run | final rel. residual (measured) | tolerance reached | "
                 "E(CG)/E(exact) - 1 | seconds |")
        L.append("|---|---|---|---|---|---|---|")
        for exp, rows in (("sphere (fig5)", conv), ("phantom drop-k", dk_cg)):
            for r in sorted(rows, key=lambda r: r["k"]):
                if r["method"] != "cgtol":
                    continue
                ex = [x for x in metrics if x["experiment"] == r["experiment"] and x["k"] == r["k"]
                      and x["method"] == "direct"]
                gap = (r["energy"] / ex[0]["energy"] - 1) if ex and isinstance(r["energy"], (int, float)) else None
                L.append(f"| {exp} | {r['k']} | {r['iterations']} (cap {r['max_iterations']}) | "
                         f"{num(r['relative_residual'], '{:.2g}')} | {r['converged']} (tol {r['tolerance']:g}) | "
                         f"{num(gap, '{:.2e}')} | {num(r['solve_seconds'], '{:.1f}')} |")
        L.append("")
        cg15 = [r for r in metrics if r["method"] == "cg15" and r["experiment"] == "dropk"]
        if cg15:
            L.append("After 15 iterations (the paper's setting) on the phantom: " + "; ".join(
                f"k={r['k']}: rel. residual {num(r['relative_residual'], '{:.2g}')}, E {num(r['energy'], '{:.4g}')} vs exact "
                + num(next((x['energy'] for x in metrics if x['experiment'] == 'dropk' and x['k'] == r['k'] and x['method'] == 'direct'), None), '{:.4g}')
                for r in cg15) + ".")
            L.append("")
        if has("fig5_convergence.png"):
            L.append("![Figure 5](fig5_convergence.png)")
            L.append("")

    mm = [r for r in metrics if r["method"] == "direct-mm"]
    if mm:
        L.append("## Energy in voxel units vs millimetres (anisotropic output grid)")
        L.append("")
        L.append("| data | Dice voxel | Dice mm | HD95 voxel | HD95 mm | MSD voxel | MSD mm | crease voxel | crease mm | components voxel | components mm |")
        L.append("|---|---|---|---|---|---|---|---|---|---|---|")
        for r in mm:
            v = [x for x in metrics if x["experiment"] == r["experiment"] and x["k"] == r["k"] and x["method"] == "direct"]
            if not v:
                continue
            v = v[0]
            name = f"{r['experiment']} k={r['k']}"
            L.append(f"| {name} | {num(v['dice'], '{:.4f}')} | {num(r['dice'], '{:.4f}')} | {num(v['hd95_mm'], '{:.2f}')} | "
                     f"{num(r['hd95_mm'], '{:.2f}')} | {num(v['msd_mm'])} | {num(r['msd_mm'])} | {crease(v.get('crease'))} | "
                     f"{crease(r.get('crease'))} | {comp(v['components'])} | {comp(r['components'])} |")
        L.append("")

    beyond = [r for r in metrics if r["method"] in ("morph", "morph-raw")]
    if beyond:
        L.append("## Beyond the paper: registration-based stacking, `--method morph`")
        L.append("")
        L.append("`morph-raw`: for every pair of neighbouring key slices, ITK's multi-resolution "
                 "symmetric-forces demons (4 levels, 25 iterations each, field sigma 2 px, maps clipped "
                 "to +-4 mm, registered at 1/4 resolution) gives a 2D correspondence u with "
                 "D1(x + u) ~ D0(x); an inserted slice at fraction t is (1 - t) D0(p - t u) + t D1(p + (1 - t) u) "
                 "(core/morph; Penney et al. 2004, Frakes et al. 2008): piecewise linear in z, so it creases at "
                 "the key slices. `morph` (the shipped method, `--method morph`): the same registrations "
                 "composed into one cubic Hermite trajectory per pixel through all key slices (Catmull-Rom "
                 "tangents), the distance values carried along it interpolated by the monotone cubic "
                 "(PCHIP, Fritsch & Carlson 1980: C1 at the key slices, never beyond the two key values), "
                 "no solver, then removal of object components that touch no key slice. No parameter was "
                 "chosen on ground truth (candidates.md: every candidate, and why). Time = registration + "
                 "interpolation + filter.")
        L.append("")
        L.append("| experiment | k | method | Dice | HD95 mm | MSD mm | crease index | components (>=100) | truth | skull-top slab (>=100) | truth slab | seconds |")
        L.append("|---|---|---|---|---|---|---|---|---|---|---|---|")
        for r in sorted([r for r in metrics if r["method"] in ("linear", "direct", "nearest", "morph-raw", "morph")],
                        key=lambda r: (r["experiment"], r["k"], ORDER.index(r["method"]))):
            L.append(f"| {r['experiment']} | {r['k']} | {r['method']} | {num(r['dice'], '{:.4f}')} | "
                     f"{num(r['hd95_mm'], '{:.2f}')} | {num(r['msd_mm'])} | {crease(r.get('crease'))} | "
                     f"{comp(r.get('components'))} | {comp(r.get('truth_components'))} | "
                     f"{comp(r.get('slab_components')) if r.get('slab_components') else '-'} | "
                     f"{comp(r.get('truth_slab_components')) if r.get('truth_slab_components') else '-'} | "
                     f"{num(r.get('solve_seconds'), '{:.1f}')} |")
        L.append("")
        L.append("The candidates that lost (the refined piecewise morph, Catmull-Rom / smoothstep / linear "
                 "values, fidelity weights, the component filter alone) "
                 "are in [candidates.md](candidates.md); a second object (the same phantom at a "
                 "soft-tissue threshold, -300 HU: the head outline) is in [soft-tissue.md](soft-tissue.md).")
        L.append("")
    slab_rows = [r for r in metrics if r.get("slab_components")]
    if slab_rows:
        L.append("## Topology: connected components (face connectivity), whole evaluated volume and skull-top slab")
        L.append("")
        L.append(f"Slab = the top {meta.get('top_slab_mm')} mm of the evaluated volume that holds object voxels. "
                 "Cells: all components (components of >= 100 voxels).")
        L.append("")
        L.append("| k | method | volume | truth volume | skull-top slab | truth slab |")
        L.append("|---|---|---|---|---|---|")
        for r in sorted(slab_rows, key=lambda r: (r["k"], ORDER.index(r["method"]) if r["method"] in ORDER else 99)):
            L.append(f"| {r['k']} | {r['method']} | {comp(r['components'])} | {comp(r['truth_components'])} | "
                     f"{comp(r['slab_components'])} | {comp(r['truth_slab_components'])} |")
        L.append("")
        if has("skull_top_k8.png"):
            L.append("### The known failure mode: the top of the skull at every 8th slice")
            L.append("")
            L.append("![skull top](skull_top_k8.png)")
            L.append("")
            if has("skull_top_axial_k8.png"):
                L.append("Withheld axial slices near the top (2D component counts in the titles):")
                L.append("")
                L.append("![skull top axial](skull_top_axial_k8.png)")
                L.append("")

    L.append("## Definitions")
    L.append("")
    L.append("""- **Drop-k**: original slices 0, k, 2k, ... of the thin series are kept; the 2D signed distance maps
  (core/sdf, ComputeSliceDistanceMaps on the kept slices only, so end caps see the sparse stack) are stacked
  with factor k (core/stack) and refined (core/solver). The output grid is the thin grid over slices
  0..(n-1)k; slices beyond the last kept slice are not reconstructed and not evaluated.
- **Reconstructed object** = field >= 0; **ground truth** = thin slice >= threshold (the same inside test
  the contouring uses, so original slices agree exactly).
- **Dice**: ITK LabelOverlapMeasuresImageFilter on the sub-volume made of the withheld slices only.
- **HD95 / HD max / MSD (mm)**: 3D. ITK SignedMaurerDistanceMapImageFilter (image spacing) of each full mask;
  boundary voxels (object voxels with a background face neighbour) of the reconstruction that lie on withheld
  slices are looked up in the ground truth's map and vice versa; the two directed sets are pooled: HD95 = 95th
  percentile, MSD = mean, HD max = maximum (the symmetric Hausdorff distance restricted to withheld slices).
  Distances are between voxel centres, so HD95 takes values like 1.0 (one slice) or 3.0 mm.
- **Crease index** (DESIGN.md section 5): mean |f_zz| (second difference per voxel step, mm) over voxels
  with |f| <= 2 mm on original slices divided by the same on inserted slices. Linear stacking has f_zz = 0
  on inserted slices: unbounded. ~1-2 means no crease at the original slices.
- **Components**: ITK ConnectedComponentImageFilter, face connectivity, on the evaluated volume.
- **Nearest original slice**: each output slice takes the thresholded mask of the nearest kept slice
  (ties go to the lower slice).""")
    L.append("")
    with open(os.path.join(a.out, "report.md"), "w") as f:
        f.write("\n".join(L))
    print(os.path.join(a.out, "report.md"))


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Report of the intensity harness (issue 23): reads the results.json of one
or more interslice_grey_eval runs (one folder per series), writes
intensity.md (tables and goals) and the reformat figures
intensity_<series>_k<k>.png (sagittal and coronal planes of the truth and each
interpolator side by side, with the difference to the truth under each).

    grey_report.py OUT_DIR RUN_DIR [RUN_DIR ...] --command "..." [--machine "..."]
"""
import argparse
import json
import math
import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

FIGURE_METHODS = ["truth", "linear", "catmull-rom", "morph"]


def load(run_dir):
    with open(os.path.join(run_dir, "results.json")) as f:
        r = json.load(f)
    r["dir_path"] = run_dir
    return r


def repo_path(path):
    """`path` relative to the repository root (e.g. ../shared/data/...), so
    the report names no folder of one machine (as tools/eval/report.py)."""
    repo = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
    return os.path.relpath(os.path.abspath(path), repo) if os.path.isabs(path) else path


def fmt(x, digits=2):
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return f"{x:.{digits}f}"


def window(r):
    # CT: bone and soft tissue both visible; otherwise the data's own range.
    if r.get("modality") == "CT":
        return -300.0, 1300.0
    return None


def figure(r, k, out_dir):
    planes = [p for p in r["planes"] if p["k"] == k]
    methods = [m for m in FIGURE_METHODS if any(p["method"] == m for p in planes)]
    if len(methods) < 2:
        return None
    fig, axes = plt.subplots(4, len(methods), figsize=(3.2 * len(methods), 11))
    win = window(r)
    for row, plane in enumerate(["sagittal", "coronal"]):
        truth = None
        for col, m in enumerate(methods):
            p = next(p for p in planes if p["method"] == m and p["plane"] == plane)
            a = np.fromfile(os.path.join(r["dir_path"], p["file"]),
                            dtype=np.float32).reshape(p["rows"], p["cols"])
            if m == "truth":
                truth = a
            lo, hi = win if win else (np.percentile(a, 1), np.percentile(a, 99.5))
            ext = [0, p["cols"] * p["col_mm"], 0, p["rows"] * p["row_mm"]]
            ax = axes[2 * row, col]
            ax.imshow(a, cmap="gray", vmin=lo, vmax=hi, origin="lower",
                      extent=ext, interpolation="nearest")
            ax.set_title(f"{m} ({plane})", fontsize=9)
            ax.tick_params(labelsize=6)
            ax = axes[2 * row + 1, col]
            if truth is not None:
                d = a - truth
                lim = 0.25 * (hi - lo)
                ax.imshow(d, cmap="RdBu_r", vmin=-lim, vmax=lim, origin="lower",
                          extent=ext, interpolation="nearest")
                ax.set_title(f"{m} - truth (+-{lim:.0f})", fontsize=8)
            ax.tick_params(labelsize=6)
    fig.suptitle(f"{r['series']}: keep every {k}th slice; withheld slices "
                 f"rebuilt (mm; z up)", fontsize=10)
    plt.tight_layout()
    name = f"intensity_{r['series']}_k{k}.png"
    plt.savefig(os.path.join(out_dir, name), dpi=80)
    plt.close(fig)
    return name


def noise_note(r):
    sigmas = [row["noise_sigma"] for row in r["rows"]
              if row["method"] == "morph" and "noise_sigma" in row]
    if not sigmas:
        return ""
    return f"; noise estimated by the morph {min(sigmas):.1f}-{max(sigmas):.1f} (k = 2-8)"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out")
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--command", default="")
    ap.add_argument("--machine", default="")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    runs = [load(d) for d in a.runs]
    lines = ["# Intensity series: linear vs Catmull-Rom vs morph (drop-k)", ""]
    if a.command:
        lines += [f"Made by `{a.command}`" + (f" on {a.machine}" if a.machine else "") + ".", ""]
    lines += [
        "Every k-th slice of a real series is kept, the withheld slices are rebuilt by each "
        "interpolator of the derived intensity series and compared with the truth "
        "(tools/eval/grey_metrics.h; harness tools/eval/grey_eval_main.cc). "
        "Regions are on the withheld slices only: *body* = truth >= the body level with holes "
        "filled slice by slice; *homogeneous* = body voxels of the soft-tissue range whose "
        "smoothed (1 mm) truth gradient is below 1% of the dynamic range per mm; *bone/skin "
        "band* = within 2 mm (|truth - level| / |gradient|) of the bone level / body level. "
        "PSNR = 20 log10(range / RMSE), range = the truth's 0.1-99.9 percentile span in the "
        "body. SSIM: Wang et al. 2004, 11x11 Gaussian window (sigma 1.5 px), mean over the body. "
        "Rise: median 10-90% rise distance (mm) across bone edges along the truth's gradient; "
        "*oblique* = edges whose normal is at least 30 degrees out of the slice plane "
        "(|n.z| >= 0.5), where interpolation in z decides the edge; the truth's own figure in "
        "brackets. Fallback: fraction of inserted voxels whose value is mostly the linear blend "
        "(where the key slices differ). Noise: the key slices' noise standard deviation the "
        "morph estimated from the data (1.4826 x the median absolute deviation of neighbouring key slices' difference; the unit of its pair check).",
        "",
    ]
    for r in runs:
        lines += [f"## {r['series']} ({r['modality']}, {repo_path(r['dir'])})", ""]
        tilt = r.get("gantry_tilt_degrees", 0)
        lines += [f"Grid (ROI) {r['grid']['size']} at {[round(s, 3) for s in r['grid']['spacing']]} mm"
                  + (f", gantry tilt {tilt:.1f} degrees (resampled by the reader)" if tilt else "")
                  + f"; edge (bone) level {r['bone']}, body level {r['body']}, soft tissue {r['soft']}"
                  + noise_note(r) + ".", ""]
        lines += ["| k | method | RMSE body | PSNR body dB | SSIM | RMSE homogeneous | RMSE bone band | RMSE skin band | rise bone mm (truth) | rise oblique mm (truth) | fallback | seconds |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for row in r["rows"]:
            br = row["bone_rise"]
            lines.append(
                f"| {row['k']} | {row['method']} | {fmt(row['body']['rmse'], 1)} | "
                f"{fmt(row['body']['psnr'])} | {fmt(row['ssim'], 4)} | "
                f"{fmt(row['homogeneous']['rmse'], 1)} | {fmt(row['bone_band']['rmse'], 1)} | "
                f"{fmt(row['skin_band']['rmse'], 1)} | {fmt(br['median_mm'])} ({fmt(br['truth_median_mm'])}) | "
                f"{fmt(br['oblique_median_mm'])} ({fmt(br['truth_oblique_median_mm'])}) | "
                f"{fmt(row.get('fallback_fraction'), 3) if 'fallback_fraction' in row else '-'} | "
                f"{fmt(row['seconds'], 1)} |")
        lines.append("")
        # Goals: PSNR over the better baseline, SSIM, sharpness, homogeneous.
        lines += ["Goals (issue 23) for `morph` against the better of linear and Catmull-Rom:", "",
                  "| k | PSNR gain dB (>= 1.0) | SSIM morph / best baseline | oblique rise morph / best baseline mm | homogeneous RMSE morph / linear |",
                  "|---|---|---|---|---|"]
        ks = sorted({row["k"] for row in r["rows"]})
        for k in ks:
            by = {row["method"]: row for row in r["rows"] if row["k"] == k}
            if not all(m in by for m in ("linear", "catmull-rom", "morph")):
                continue
            base = max(by["linear"]["body"]["psnr"], by["catmull-rom"]["body"]["psnr"])
            ssim_base = max(by["linear"]["ssim"], by["catmull-rom"]["ssim"])
            rise_base = min(by["linear"]["bone_rise"]["oblique_median_mm"],
                            by["catmull-rom"]["bone_rise"]["oblique_median_mm"])
            m = by["morph"]
            lines.append(
                f"| {k} | {m['body']['psnr'] - base:+.2f} | {m['ssim']:.4f} / {ssim_base:.4f} | "
                f"{fmt(m['bone_rise']['oblique_median_mm'])} / {fmt(rise_base)} | "
                f"{fmt(m['homogeneous']['rmse'], 1)} / {fmt(by['linear']['homogeneous']['rmse'], 1)} |")
        lines.append("")
        for k in (4, 8):
            name = figure(r, k, a.out)
            if name:
                lines += [f"![{r['series']} k={k}]({name})", ""]
    with open(os.path.join(a.out, "intensity.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print(os.path.join(a.out, "intensity.md"))


if __name__ == "__main__":
    main()

#!/usr/bin/python3
"""Figures of the quality harness, from interslice_eval's output folder.

Usage: /usr/bin/python3 tools/eval/plots.py OUT_DIR
Reads OUT_DIR/planes.json + raw/*.f32, convergence.csv, results.json and
writes OUT_DIR/*.png:
  reformat_<experiment>_k<k>.png  sagittal and coronal reformats, ground
      truth vs each method (object = value >= 0, grey; ground-truth boundary
      in red on every method panel); like the paper's Figures 3 and 4 but as
      cuts instead of renderings
  fig5_convergence.png  relative residual per CG iteration (paper Figure 5)
  skull_top_k8.png      the known failure mode: withheld axial slices near
      the top of the skull at every 8th slice, ground truth vs methods
"""
import csv
import json
import os
import sys

import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

try:
    from scipy import ndimage
except ImportError:  # only for the per-slice component counts
    ndimage = None

ORDER = ["truth", "nearest", "linear", "cg15", "cgtol", "direct", "direct-mm", "morph-raw", "morph"]
LABEL = {"truth": "ground truth", "nearest": "nearest slice",
         "linear": "linear SBI", "cg15": "CG 15 it.", "cgtol": "CG to tol.",
         "direct": "exact (voxel)", "direct-mm": "exact (mm)",
         "morph-raw": "morph (raw)", "morph": "morph"}


def load_planes(out):
    with open(os.path.join(out, "planes.json")) as f:
        planes = json.load(f)
    for p in planes:
        p["data"] = np.fromfile(os.path.join(out, p["file"]),
                                dtype=np.float32).reshape(p["rows"], p["cols"])
    return planes


def show(ax, plane, truth=None, title=""):
    d = plane["data"]
    extent = [0, d.shape[1] * plane["col_mm"], 0, d.shape[0] * plane["row_mm"]]
    ax.imshow(d >= 0, cmap="gray", origin="lower", extent=extent,
              interpolation="nearest", vmin=0, vmax=1)
    if truth is not None and plane["method"] != "truth":
        ys = (np.arange(d.shape[0]) + 0.5) * plane["row_mm"]
        xs = (np.arange(d.shape[1]) + 0.5) * plane["col_mm"]
        ax.contour(xs, ys, truth["data"], levels=[0], colors="r",
                   linewidths=0.4)
    ax.set_title(title, fontsize=8)
    ax.set_xticks([])
    ax.set_yticks([])


def reformats(out, planes):
    made = []
    keys = sorted({(p["experiment"], p["k"]) for p in planes
                   if p["plane"] in ("sagittal", "coronal")})
    for exp, k in keys:
        sel = [p for p in planes if p["experiment"] == exp and p["k"] == k]
        methods = [m for m in ORDER if any(p["method"] == m for p in sel)]
        rows = [r for r in ("sagittal", "coronal")
                if any(p["plane"] == r for p in sel)]
        fig, axes = plt.subplots(len(rows), len(methods),
                                 figsize=(2.2 * len(methods), 2.4 * len(rows)),
                                 squeeze=False)
        for r, plane_name in enumerate(rows):
            truth = next(p for p in sel if p["plane"] == plane_name
                         and p["method"] == "truth")
            for c, m in enumerate(methods):
                p = next(p for p in sel if p["plane"] == plane_name
                         and p["method"] == m)
                show(axes[r][c], p, truth,
                     f"{LABEL.get(m, m)}\n{plane_name} {p['index']}")
        fig.suptitle(f"{exp}, k = {k}: object (white), ground-truth boundary "
                     f"(red); z up", fontsize=9)
        fig.tight_layout()
        name = f"reformat_{exp}_k{k}.png"
        fig.savefig(os.path.join(out, name), dpi=130)
        plt.close(fig)
        made.append(name)
    return made


def convergence(out):
    path = os.path.join(out, "convergence.csv")
    if not os.path.exists(path):
        return []
    curves = {}
    with open(path) as f:
        for row in csv.DictReader(f):
            try:
                rr = float(row["relative_residual"])
            except ValueError:
                continue
            key = (row["experiment"], int(row["k"]), row["method"])
            curves.setdefault(key, []).append((int(row["iteration"]), rr))
    panels = [e for e in ("fig5-sphere", "dropk")
              if any(key[0] == e for key in curves)]
    if not panels:
        return []
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4),
                             squeeze=False)
    for ax, exp in zip(axes[0], panels):
        for (e, k, m), pts in sorted(curves.items()):
            if e != exp or m not in ("cgtol",):
                continue
            pts.sort()
            ax.semilogy([p[0] for p in pts], [max(p[1], 1e-12) for p in pts],
                        label=f"factor {k}")
        ax.set_xlabel("CG iteration")
        ax.set_ylabel("|r_k| / |r_0|")
        ax.set_title("sphere r = 20 mm, 64x64x65" if exp == "fig5-sphere"
                     else "CT phantom, drop-k (factor = k)", fontsize=9)
        ax.axvline(15, color="gray", lw=0.5, ls="--")
        ax.grid(True, which="both", lw=0.3)
        ax.legend()
    fig.suptitle("Convergence of CG (paper Figure 5; residual instead of |d|)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "fig5_convergence.png"), dpi=130)
    plt.close(fig)
    return ["fig5_convergence.png"]


def components_2d(mask):
    if ndimage is None:
        return -1
    return int(ndimage.label(mask)[1])


def skull_top(out, planes):
    ax_planes = [p for p in planes if p["plane"] == "axial"
                 and p["experiment"] == "dropk" and p["k"] == 8]
    if not ax_planes:
        return []
    slices = sorted({p["index"] for p in ax_planes})
    # The withheld slice where the exact minimiser's cross-section has the
    # most excess 2D components over the ground truth (ties: the highest).
    best, best_score = slices[-1], -1e9
    for z in slices:
        t = next(p for p in ax_planes if p["index"] == z
                 and p["method"] == "truth")
        d = next((p for p in ax_planes if p["index"] == z
                  and p["method"] == "direct"), None)
        if d is None:
            continue
        score = components_2d(d["data"] >= 0) - components_2d(t["data"] >= 0)
        if score >= best_score:
            best, best_score = z, score
    chosen = [z for z in (best - 2, best, best + 2) if z in slices] or [best]
    methods = [m for m in ORDER if any(p["method"] == m for p in ax_planes)]
    fig, axes = plt.subplots(len(chosen), len(methods),
                             figsize=(2.3 * len(methods), 2.4 * len(chosen)),
                             squeeze=False)
    for r, z in enumerate(chosen):
        truth = next(p for p in ax_planes if p["index"] == z
                     and p["method"] == "truth")
        for c, m in enumerate(methods):
            p = next(p for p in ax_planes if p["index"] == z
                     and p["method"] == m)
            n2 = components_2d(p["data"] >= 0)
            show(axes[r][c], p, truth,
                 f"{LABEL.get(m, m)}, slice {z}\n{n2} 2D components")
    fig.suptitle("Top of the skull, every 8th slice kept: withheld axial "
                 "slices (ground-truth boundary in red)", fontsize=9)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "skull_top_axial_k8.png"), dpi=130)
    plt.close(fig)
    with open(os.path.join(out, "skull_top_k8.json"), "w") as f:
        json.dump({"slices": chosen, "most_broken_slice": best,
                   "excess_components_direct": best_score}, f)
    return ["skull_top_axial_k8.png"] + skull_top_reformat(out, planes)


def skull_top_reformat(out, planes, height_mm=40.0):
    """Sagittal and coronal cuts through the top of the skull, k = 8."""
    sel = [p for p in planes if p["experiment"] == "dropk" and p["k"] == 8
           and p["plane"] in ("sagittal", "coronal")]
    if not sel:
        return []
    methods = [m for m in ("truth", "nearest", "linear", "cg15", "direct", "morph")
               if any(p["method"] == m for p in sel)]
    fig, axes = plt.subplots(len(methods), 2, figsize=(11, 1.45 * len(methods)),
                             squeeze=False)
    for c, plane_name in enumerate(("sagittal", "coronal")):
        truth = next(p for p in sel if p["plane"] == plane_name
                     and p["method"] == "truth")
        rows = truth["data"].shape[0]
        n = int(round(height_mm / truth["row_mm"]))
        r0 = max(0, rows - n)
        for r, m in enumerate(methods):
            p = next(p for p in sel if p["plane"] == plane_name
                     and p["method"] == m)
            d = p["data"][r0:]
            ax = axes[r][c]
            extent = [0, d.shape[1] * p["col_mm"], r0 * p["row_mm"],
                      rows * p["row_mm"]]
            ax.imshow(d >= 0, cmap="gray", origin="lower", extent=extent,
                      interpolation="nearest", aspect="equal")
            if m != "truth":
                ys = (np.arange(r0, rows) + 0.5) * p["row_mm"]
                xs = (np.arange(d.shape[1]) + 0.5) * p["col_mm"]
                ax.contour(xs, ys, truth["data"][r0:], levels=[0], colors="r",
                           linewidths=0.4)
            for z in range(r0, rows):
                if z % 8 == 0:  # original (kept) slices
                    ax.axhline((z + 0.5) * p["row_mm"], color="c", lw=0.3,
                               ls=":")
            ax.set_yticks([])
            ax.set_xticks([])
            ax.set_ylabel(LABEL.get(m, m), fontsize=7)
            if r == 0:
                ax.set_title(f"{plane_name} {p['index']}, top {height_mm:.0f} mm",
                             fontsize=8)
    fig.suptitle("Known failure mode: top of the skull, every 8th slice kept "
                 "(cyan: kept slices; red: ground-truth boundary)", fontsize=9)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "skull_top_k8.png"), dpi=140)
    plt.close(fig)
    return ["skull_top_k8.png"]


def main():
    out = sys.argv[1]
    planes = load_planes(out)
    made = reformats(out, planes) + convergence(out) + skull_top(out, planes)
    for m in made:
        print(os.path.join(out, m))


if __name__ == "__main__":
    main()

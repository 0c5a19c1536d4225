#!/usr/bin/env python3
"""Writes segmentations.md (and segmentations_dice.png when matplotlib is
present) from the CSV/JSON of interslice_fill_eval: one run (OUT), or with
--series NAME=DIR ... one section per series and a summary of the goals of
issue 24 (auto against the better of nearest copy and linear stacking)."""
import argparse
import csv
import json
import os

NAMES = {
    "copy": "nearest-slice copy",
    "linear": "linear stacking (per-label 2D SDF)",
    "cg": "paper: 15 CG iterations",
    "direct": "paper: exact minimiser",
    "morph": "morph (registration of the key slices, per label)",
    "auto": "**auto (default)**: per-label choice at the doubled gap",
    "auto-trend": "auto with the gap-trend rule (doubled and quadrupled gap)",
    "auto-doubled": "auto, choice at the doubled gap",
    "auto-nomorph": "auto without the morph candidate",
}


# The methods that are also auto's candidates and are scored on their own
# (auto's fifth candidate, "blend", the mean of the copy's and linear
# stacking's distance maps, is not).
CEILING_METHODS = ("copy", "linear", "direct", "morph")


def ceiling(metrics, k):
    """Mean over labels of each label's best withheld Dice among
    CEILING_METHODS at k: what a per-label choice among them would reach
    if it knew the withheld slices (an upper bound for auto's selection,
    but for the blend candidate). None without those methods' rows."""
    best = {}
    for r in metrics:
        if int(r["k"]) != k or r["method"] not in CEILING_METHODS:
            continue
        d = float(r["dice"])
        best[r["label"]] = max(best.get(r["label"], d), d)
    return sum(best.values()) / len(best) if best else None


def goal_lines(name, summary, metrics):
    """Issue 24's goals on one series: auto >= max(copy, linear) in mean
    Dice at every k, +0.01 at k >= 5; HD95 no worse than copy."""
    by = {(int(r["k"]), r["method"]): r for r in summary}
    ks = sorted({int(r["k"]) for r in summary})
    out = []
    for k in ks:
        if (k, "auto") not in by or (k, "copy") not in by or (k, "linear") not in by:
            continue
        a = float(by[(k, "auto")]["mean_dice"])
        c = float(by[(k, "copy")]["mean_dice"])
        l = float(by[(k, "linear")]["mean_dice"])
        best = max(c, l)
        need = best + (0.01 if k >= 5 else 0.0)
        ha = float(by[(k, "auto")]["mean_hd95_mm"])
        hc = float(by[(k, "copy")]["mean_hd95_mm"])
        top = ceiling(metrics, k)
        out.append("| %s | %d | %.4f | %.4f (%s) | %+.4f | %s | %s | %.2f / %.2f | %s |" % (
            name, k, a, best, "copy" if c >= l else "linear", a - best,
            "met" if a >= need - 1e-12 else "**not met**",
            "n/a" if top is None else "%+.4f" % (top - best), ha, hc,
            "met" if ha <= hc + 1e-9 else "**not met**"))
    return out


def section(out_dir, title, level, figure_name):
    """The report of one run of interslice_fill_eval, headings at `level`."""
    h = "#" * (level + 1) if title else "#" * level
    summary = list(csv.DictReader(open(os.path.join(out_dir, "fill_summary.csv"))))
    metrics = list(csv.DictReader(open(os.path.join(out_dir, "fill_metrics.csv"))))
    made = json.load(open(os.path.join(out_dir, "labels.json")))
    ks = sorted({int(r["k"]) for r in summary})
    methods = [m for m in NAMES if any(r["method"] == m for r in summary)]
    by = {(int(r["k"]), r["method"]): r for r in summary}
    lines = []
    if title:
        lines += ["#" * level + " " + title, ""]
    grid = made.get("grid")
    lines += [
        "Data: %d labels on a %s grid%s. Every k-th slice (0, k, 2k, ...) is "
        "a key slice for every label (`--key-slices`); the slices in between, "
        "up to the last key slice, are withheld and compared per label with "
        "the truth: Dice, HD95 and MSD (3D surface distances, mm, as in "
        "report.md), averaged over the labels present on the withheld slices. "
        "Gap voxels: background on a withheld slice at a pixel labelled on "
        "both bracketing key slices. Seconds: the whole fill of all labels "
        "(`FillBetweenSlices`, 2 threads), scoring excluded." % (
            len(made.get("labels", [])) or len({r["label"] for r in metrics}),
            " x ".join(str(v) for v in grid) if grid else "?",
            " made from the thin CT phantom by HU bands and connected "
            "components (segmentations_labels.json)" if made.get("labels") else ""),
        ""]
    for title, column, fmt in (("Mean Dice over labels", "mean_dice", "%.4f"),
                               ("Mean HD95 over labels, mm", "mean_hd95_mm", "%.2f"),
                               ("Mean MSD over labels, mm", "mean_msd_mm", "%.3f"),
                               ("Gap voxels (touching on both key slices, "
                                "background after the fill)", "gap_voxels", "%s"),
                               ("Seconds for the whole fill (wall clock)", "seconds", "%s"),
                               ("CPU seconds for the whole fill (all threads)", "cpu_seconds", "%s")):
        lines += [h + " " + title, "",
                  "| method | " + " | ".join("k = %d" % k for k in ks) + " |",
                  "|---|" + "---|" * len(ks)]
        for m in methods:
            cells = []
            for k in ks:
                r = by.get((k, m))
                if r is None or column not in r:
                    cells.append("-")
                elif fmt == "%s":
                    cells.append(r[column])
                else:
                    cells.append(fmt % float(r[column]))
            lines.append("| %s | %s |" % (NAMES[m], " | ".join(cells)))
        lines.append("")

    # Per-label Dice at the middle k.
    kmid = 5 if 5 in ks else ks[len(ks) // 2]
    per = {}
    for r in metrics:
        if int(r["k"]) == kmid:
            per.setdefault(int(r["label"]), {})[r["method"]] = float(r["dice"])
    info = {l["label"]: l for l in made.get("labels", [])}
    lines += [h + " Dice per label, k = %d" % kmid, "",
              "| label | HU band | voxels | " + " | ".join(NAMES[m] for m in methods) + " |",
              "|---|---|---|" + "---|" * len(methods)]
    for label in sorted(per):
        i = info.get(label, {})
        band = ("%g..%g" % (i["hu_from"], i["hu_to"])) if i else "-"
        lines.append("| %d | %s | %s | %s |" % (
            label, band, i.get("voxels", "-"),
            " | ".join("%.3f" % per[label][m] if m in per[label] else "-"
                       for m in methods)))
    lines.append("")

    # The timing case (fill_timing.csv, from --no-score runs).
    path = os.path.join(out_dir, "fill_timing.csv")
    if os.path.exists(path):
        rows = list(csv.DictReader(open(path)))
        lines += [h + " Timing: the labels on a %s grid, every %s-th slice" % (
                      rows[0]["grid"].replace("x", " x "), rows[0]["k"]) if rows else
                  h + " Timing", "",
                  "Fastest of 3 fills; wall clock on the shared machine (load "
                  "average in timing.log) and process CPU time of all threads.", "",
                  "| method | labels | threads | wall s | CPU s |",
                  "|---|---|---|---|---|"]
        for r in rows:
            lines.append("| %s | %s | %s | %s | %s |" % (
                NAMES.get(r["method"], r["method"]), r["labels"], r["threads"],
                r["seconds"], r["cpu_seconds"]))
        lines.append("")

    # What auto chose per label (from its own key slices, never the truth).
    path = os.path.join(out_dir, "fill_choices.csv")
    if os.path.exists(path):
        rows = [r for r in csv.DictReader(open(path))
                if r.get("method", "auto") == "auto"]
        cks = sorted({int(r["k"]) for r in rows})
        counts = {}
        for r in rows:
            counts.setdefault(int(r["k"]), {}).setdefault(r["chosen"], 0)
            counts[int(r["k"])][r["chosen"]] += 1
        names = sorted({r["chosen"] for r in rows})
        lines += [h + " Candidate chosen by auto (labels per candidate)", "",
                  "(from the label's own key slices, never the withheld "
                  "truth; fill_choices.csv has each label's validation Dice "
                  "at the doubled gap, with auto-trend's rows also at the "
                  "quadrupled gap, and its score)", "",
                  "| candidate | " + " | ".join("k = %d" % k for k in cks) + " |",
                  "|---|" + "---|" * len(cks)]
        for name in names:
            lines.append("| %s | %s |" % (name, " | ".join(
                str(counts.get(k, {}).get(name, 0)) for k in cks)))
        lines.append("")

    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(6, 4))
        for m in methods:
            ax.plot(ks, [float(by[(k, m)]["mean_dice"]) for k in ks], "o-",
                    label=NAMES[m].replace("*", ""))
        ax.set_xlabel("k (every k-th slice kept)")
        ax.set_ylabel("mean Dice over labels, withheld slices")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(os.path.join(out_dir, figure_name), dpi=100)
        lines += ["![mean Dice vs k](%s)" % figure_name, ""]
    except ImportError:
        lines += ["(matplotlib missing: no figure; `bash scripts/install-deps.sh --eval`)", ""]
    return lines, summary


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("out", help="the run (or, with --series, where the "
                        "report is written)")
    parser.add_argument("--command", default="")
    parser.add_argument("--series", nargs="*", default=[],
                        help="NAME=DIR[=DESCRIPTION]: one section per run")
    args = parser.parse_args()
    lines = ["# Segmentations in: drop-k on multi-label segmentations", ""]
    if args.command:
        lines += ["Generated by `%s` (tools/eval/fill_eval_main.cc, "
                  "tools/eval/fill_report.py); not hand-edited." % args.command, ""]
    if not args.series:
        body, _ = section(args.out, "", 2, "segmentations_dice.png")
        lines += body
    else:
        goals = []
        bodies = []
        for spec in args.series:
            parts = spec.split("=", 2)
            name, run = parts[0], parts[1]
            description = parts[2] if len(parts) > 2 else ""
            figure = "segmentations_dice_%s.png" % name
            body, summary = section(run, "%s" % name, 3, figure)
            if os.path.exists(os.path.join(run, figure)) and run != args.out:
                import shutil
                shutil.copy(os.path.join(run, figure), os.path.join(args.out, figure))
            if description:
                body.insert(2, description + "\n")
            bodies += body
            metrics = list(csv.DictReader(open(os.path.join(run, "fill_metrics.csv"))))
            goals += goal_lines(name, summary, metrics)
        lines += [
            "## Goals (issue 24)", "",
            "auto against the better of nearest-slice copy and linear "
            "stacking in mean Dice (goal: at least it at every k, +0.01 at "
            "k >= 5), and mean HD95 against the copy's (goal: no worse). "
            "\"Ceiling - it\": each label given the best of copy, linear, "
            "direct and morph by its own withheld slices, averaged, minus "
            "the better of copy and linear; no selection among those "
            "candidates does better (auto's fifth candidate, the mean of the "
            "copy's and linear stacking's distance maps, is not scored "
            "alone), so where it is below +0.01 at k >= 5 that goal is out "
            "of reach of a per-label choice among them.", "",
            "| series | k | auto | better of copy, linear | auto - it | "
            "Dice goal | ceiling - it | HD95 auto / copy, mm | HD95 goal |",
            "|---|---|---|---|---|---|---|---|---|"] + goals + [""]
        lines += ["## Series", ""] + bodies
    with open(os.path.join(args.out, "segmentations.md"), "w") as f:
        f.write("\n".join(lines))


if __name__ == "__main__":
    main()

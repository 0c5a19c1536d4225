#!/usr/bin/env python3
"""Key slices of the thick -> thin case, as read and slab-deconvolved.

Reads the harness's dump of the thick case (INTERSLICE_EVAL_DUMP=DIR
interslice_eval ... --experiments thick: DIR/thick_k5_truth.f32 = thin grey
values - threshold on the thin grid, DIR/thick_k5_originals.f32 = the thick
slices) and prints, per threshold, the Dice of the thick slices and of their
slab deconvolution (the iteration of core/slab, 5 mm box, factor 5, written
again here in numpy) against the thin slices at the same positions, and the
fraction of object pixels each keeps. docs/eval/candidates.md, "Slab
deconvolution".

    /usr/bin/python3 tools/eval/slab_probe.py DIR [--threshold 300] [HU ...]
"""
import argparse
import os

import numpy as np


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dump")
    ap.add_argument("--threshold", type=float, default=300.0,
                    help="the threshold the dump was made with")
    ap.add_argument("levels", type=float, nargs="*", default=[300, -300, 600, 100])
    ap.add_argument("--factor", type=int, default=5)
    a = ap.parse_args()
    n = a.factor
    keys = np.fromfile(os.path.join(a.dump, f"thick_k{n}_originals.f32"), np.float32)
    thin = np.fromfile(os.path.join(a.dump, f"thick_k{n}_truth.f32"), np.float32)
    slices = None
    # The thick stack has S slices, the thin grid (S - 1) n + 1 planes of the
    # same size: solve for the plane size from the two counts.
    for s in range(2, 1000):
        if keys.size % s == 0 and thin.size == ((s - 1) * n + 1) * (keys.size // s):
            slices = s
            break
    if slices is None:
        raise SystemExit("dump sizes do not match a factor-%d thick case" % n)
    plane = keys.size // slices
    keys = keys.reshape(slices, plane).astype(np.float64)
    thin = thin.reshape((slices - 1) * n + 1, plane).astype(np.float64) + a.threshold
    planes = (slices - 1) * n + 1
    z = np.arange(planes) / n
    s0 = np.minimum(np.floor(z).astype(int), slices - 2)
    f = (z - s0)[:, None]
    half = n // 2  # a box of one slice gap: n fine samples centred on the slice

    def interp(c):
        return (1 - f) * c[s0] + f * c[s0 + 1]

    def slab_average(c):
        i = interp(c)
        return np.stack([i[max(0, s * n - half):s * n + half + 1].mean(0)
                         for s in range(slices)])

    est = keys.copy()
    for _ in range(50):
        r = keys - slab_average(est)
        if np.sqrt((r ** 2).mean()) < 0.5:
            break
        est += r

    def dice(x, y):
        return 2 * (x & y).sum() / (x.sum() + y.sum())

    print("| threshold | thick slices as read | deconvolved | object pixels, thick / deconvolved (thin = 1) |")
    print("|---|---|---|---|")
    for t in a.levels:
        truth = thin[::n] >= t
        print(f"| {t:g} | {dice(keys >= t, truth):.4f} | {dice(est >= t, truth):.4f} | "
              f"{(keys >= t).sum() / truth.sum():.3f} / {(est >= t).sum() / truth.sum():.3f} |")


if __name__ == "__main__":
    main()

"""Summarises interslice_bench JSON output as markdown (scripts/bench.sh).

The CG target of the speed issue: one iteration at most twice the time the
STREAM triad bandwidth needs to move 32 bytes per voxel (eight float reads or
writes, a fully fused iteration). Our own traffic count is also given: the
iteration makes three passes, q = A d (read d, write q), r -= a q (read r, q;
write r) and f += a d; d = r + b d (read f, d, r; write f, d): 40 bytes per
free voxel, 44 counting the write-allocate read of q.
"""
import json
import sys


def load(path):
    with open(path) as f:
        return json.load(f)["benchmarks"]


def median_of(benchmarks, prefix):
    for b in benchmarks:
        if b["name"].startswith(prefix) and b.get("aggregate_name") == "median":
            return b
    for b in benchmarks:
        if b["name"].startswith(prefix) and "aggregate_name" not in b:
            return b
    return None


def seconds(b):
    unit = {"ns": 1e-9, "us": 1e-6, "ms": 1e-3, "s": 1.0}[b["time_unit"]]
    return b["real_time"] * unit


def main():
    kernels = load(sys.argv[1])
    solves = load(sys.argv[2]) if len(sys.argv) > 2 else []
    triad = median_of(kernels, "BM_StreamTriad")
    bw = triad["bytes_per_s"] if triad else float("nan")
    print("## Bandwidth limit and kernels (medians of 5)\n")
    print(f"STREAM triad on all cores: **{bw / 1e9:.1f} GB/s**.\n")
    print("| size | operator apply ms | CG iteration ms | 32 B/voxel at triad ms | ratio (target <= 2) | "
          "effective GB/s at 40 B/voxel |")
    print("|---|---|---|---|---|---|")
    for n, label in ((128, "128^3"), (256, "256^3"), (512, "512x512x300")):
        op = median_of(kernels, f"BM_OperatorApply/{n}/")
        cg = median_of(kernels, f"BM_ConjugateGradientIteration/{n}/")
        if not cg:
            continue
        voxels = cg["voxels"]
        t_cg = seconds(cg)
        t_limit = 32 * voxels / bw
        print(f"| {label} | {seconds(op) * 1e3:.2f} | {t_cg * 1e3:.2f} | {t_limit * 1e3:.2f} | "
              f"{t_cg / t_limit:.2f} | {40 * voxels / t_cg / 1e9:.1f} |")
    print()
    for b in solves:
        if b["name"].startswith("BM_DirectVersusCgToSameResidual"):
            n = b["name"].split("/")[1]
            print(f"- Direct vs CG at {n}^3 (every 8th slice fixed): direct {b['direct_s']:.3f} s "
                  f"(relative residual {b['direct_rel_residual']:.2e}); CG to the same residual "
                  f"{b['cg_same_residual_s']:.2f} s, {int(b['cg_same_residual_iters'])} iterations: "
                  f"**{b['ratio_cg_over_direct']:.1f}x**. CG asked for 1e-6: stopped at "
                  f"{b['cg_1e-6_reached']:.2e} (float floor) after {int(b['cg_1e-6_iters'])} iterations, "
                  f"{b['cg_1e-6_s']:.2f} s ({b['cg_1e-6_s'] / b['direct_s']:.0f}x the direct solve).")
    print()
    rows = [b for b in solves if b["name"].startswith("BM_SolveScaling")]
    if rows:
        print("## Scaling: a whole solve (15 CG iterations, or direct)\n")
        print("| voxels | method | seconds | ns per voxel |")
        print("|---|---|---|---|")
        for b in rows:
            print(f"| {int(b['voxels']):,} | {b['label']} | {seconds(b):.3f} | {b['ns_per_voxel'] * 1e9:.1f} |")
        print()
    rows = [b for b in solves if b["name"].startswith("BM_EndToEndPhantom")]
    if rows:
        print("## End to end: shipped thick phantom -> 0.45 mm (512x512x298), 300 HU, nii.gz + STL\n")
        print("| method | read s | contour s | stack s | solve s | mesh s | write s | total s |")
        print("|---|---|---|---|---|---|---|---|")
        for b in rows:
            print(f"| {b['label']} | {b['read_s']:.2f} | {b['contour_s']:.2f} | {b['stack_s']:.2f} | "
                  f"{b['solve_s']:.2f} | {b['mesh_s']:.2f} | {b['write_s']:.2f} | {seconds(b):.2f} |")
        print()
        print("Peak memory is measured per process with /usr/bin/time (see the issue notes), not here:"
              " the benchmarks share one process.")


if __name__ == "__main__":
    main()

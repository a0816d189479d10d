#!/usr/bin/env python3
"""Hierarchical clustering against CGAL's hierarchy_simplify_point_set at CGAL's own counts
(issue 19.4), both of Surfel's representatives: bench_peer_cgal's `simplify_hierarchical_*`,
bench_core's `simplify_hierarchical-positions-cgal-count_*` (the notes' centroid, the default)
and `simplify_hierarchical-members-cgal-count_*` (--representative member, CGAL's rule).

Each run is a fresh process (under `chrt -f 10` when allowed); a round runs the three rows of a
dataset and count one after the other, so a noisy stretch of the VM falls on all three alike.
Prints wall medians (min), CGAL's median over each row's, and the rows' errors (deterministic).

  python3 bench/hierarchy_vs_cgal.py --bin build/bin --data ../shared/data --rounds 5
"""
import argparse
import json
import os
import statistics
import subprocess
import tempfile

DATASETS = ("bunny_scans_merged", "person_scan")
PERCENTS = ("1pct", "10pct")
KINDS = (("CGAL", "bench_peer_cgal", "simplify_hierarchical_{pct}/{d}"),
         ("centroid", "bench_core", "simplify_hierarchical-positions-cgal-count_{pct}/{d}"),
         ("member", "bench_core", "simplify_hierarchical-members-cgal-count_{pct}/{d}"))


def run(exe, name, env, chrt):
    with tempfile.NamedTemporaryFile(suffix=".json") as out:
        args = ([*chrt, exe] if chrt else [exe]) + [f"--benchmark_filter=^{name}/", f"--benchmark_out={out.name}",
                                                    "--benchmark_out_format=json"]
        r = subprocess.run(args, capture_output=True, text=True, env=env)
        if r.returncode != 0:
            raise SystemExit(f"hierarchy_vs_cgal: {name} failed:\n{r.stderr[-2000:]}")
        records = json.load(open(out.name))["benchmarks"]
        if not records:
            raise SystemExit(f"hierarchy_vs_cgal: {name} ran nothing")
        return records[0]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin", default="build/bin", help="where bench_core and bench_peer_cgal are")
    ap.add_argument("--data", default="../shared/data", help="SURFEL_DATA: the scans")
    ap.add_argument("--rounds", type=int, default=5)
    a = ap.parse_args()
    env = dict(os.environ, SURFEL_DATA=a.data)
    chrt = ["chrt", "-f", "10"] if subprocess.run(["chrt", "-f", "10", "true"], capture_output=True).returncode == 0 else []
    groups = [(pct, d, [(label, os.path.join(a.bin, exe), name.format(pct=pct, d=d)) for label, exe, name in KINDS])
              for pct in PERCENTS for d in DATASETS]
    times, last = {}, {}
    for _ in range(a.rounds):
        for pct, d, rows in groups:
            for label, exe, name in rows:
                b = run(exe, name, env, chrt)
                times.setdefault(name, []).append(b["real_time"])
                last[name] = b
    for pct, d, rows in groups:
        cgal = statistics.median(times[rows[0][2]])
        for label, _, name in rows:
            b, t = last[name], times[name]
            mesh = f" mesh_mean={b['mesh_mean'] * 1e6:.1f}um" if "mesh_mean" in b else ""
            print(f"{d:20s} {pct:5s} {label:9s} points={b['points']:6.0f} median={statistics.median(t):7.1f} "
                  f"min={min(t):7.1f} ms  CGAL/this={cgal / statistics.median(t):5.2f}  "
                  f"avg={b['err_avg_rel']:.4e} cover_p95={b['cover_p95']:.4e}{mesh}")


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Resampling against the peers at the same output count (issue 15, item 8).

Sides: ours (particle resampling to the exact count), CGAL EAR (upsampling, with our normals;
its count is a request it may fall short of), CGAL WLOP (downsampling), PCL MLS upsampling in
its three modes (SAMPLE_LOCAL_PLANE, RANDOM_UNIFORM_DENSITY, VOXEL_GRID_DILATION; PCL takes no
count, so each mode's size parameter is first searched over untimed runs, then timed in a fresh
process). Each timed run is its own process; rounds are interleaved (ours, each peer, ours ...)
and medians reported. Distances relative to the input's bounding-box diagonal.

    python3 bench/bench_resample.py --bin build/bin --out bench/results-resample.md [--rounds 3]
"""
import argparse
import datetime
import json
import os
import statistics
import subprocess
import sys
import time

CASES = ["bunny-x4", "bunny_scan-x4", "bunny_scan-half", "person_scan-half"]
UP_PEERS = [("bench_resample", "cgal-ear"), ("bench_resample_pcl", "pcl-local-plane"),
            ("bench_resample_pcl", "pcl-random"), ("bench_resample_pcl", "pcl-voxel")]
DOWN_PEERS = [("bench_resample", "cgal-wlop")]
KEYS = ["time_ms", "process_ms", "points", "count_error", "mesh_mean_rel", "mesh_rms_rel", "mesh_max_rel",
        "coverage_p95_rel", "nn_cv", "peak_rss_mb"]


def run(binary, side, case, extra=()):
    cmd = [binary, "--side", side, "--case", case, *extra]
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "2"))
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = (time.perf_counter() - t0) * 1000
    if p.returncode != 0:
        print(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr.strip()[-300:]}", file=sys.stderr)
        return None
    j = json.loads(p.stdout.strip().splitlines()[-1])
    j["process_ms"] = wall
    return j


def fmt(v, spec):
    return "—" if v is None else format(v, spec)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin", default="build/bin")
    ap.add_argument("--out", default="bench/results-resample.md")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--cases", default=",".join(CASES))
    args = ap.parse_args()
    rows, raw = [], {}
    for case in args.cases.split(","):
        peers = UP_PEERS if "-x" in case else DOWN_PEERS
        params = {}
        for binary, side in peers:
            if binary == "bench_resample_pcl" and os.path.exists(f"{args.bin}/{binary}"):
                s = run(f"{args.bin}/{binary}", side, case, ["--search"])
                if s:
                    params[side] = s["param"]
                    print(f"{case} {side}: param {s['param']:.6g} ({s['param_meaning']})", file=sys.stderr)
        results = {"ours": []}
        for _ in range(args.rounds):
            o = run(f"{args.bin}/bench_resample", "ours", case)
            if o:
                results["ours"].append(o)
            for binary, side in peers:
                if not os.path.exists(f"{args.bin}/{binary}"):
                    continue
                if binary == "bench_resample_pcl" and side not in params:
                    continue
                extra = ["--param", repr(params[side])] if side in params else []
                r = run(f"{args.bin}/{binary}", side, case, extra)
                if r:
                    results.setdefault(side, []).append(r)
            print(f"{case}: round done", file=sys.stderr, flush=True)
        raw[case] = results
        for side, rs in results.items():
            if not rs:
                continue
            med = {k: statistics.median(r[k] for r in rs) if all(k in r for r in rs) else None for k in KEYS}
            med["param"] = params.get(side)
            rows.append((case, side, med, len(rs)))

    ours_time = {c: m["time_ms"] for c, s, m, _ in rows if s == "ours"}
    out = [f"# Resampling against the peers at the same count ({datetime.date.today()})", "",
           f"`python3 bench/bench_resample.py --bin {args.bin} --rounds {args.rounds}`: every timed run its own "
           "process, interleaved rounds, medians. Distances relative to the input's bounding-box diagonal; "
           "coverage = p95 of 200k area-uniform mesh samples → nearest output point; CV = coefficient of variation "
           "of nearest-neighbour distances (uniform random ≈ 0.52, hexagonal lattice 0).", "",
           "| case | side | ms (process) | time ÷ ours | points (count error) | mesh mean / RMS / max | coverage p95 | NN CV "
           "| RSS MB | size parameter |",
           "|---|---|---:|---:|---:|---|---:|---:|---:|---|"]
    for case, side, m, n in rows:
        ratio = "—" if side == "ours" else f"{m['time_ms'] / ours_time[case]:.1f}×" if case in ours_time else "—"
        out.append(
            f"| {case} | {side} | {m['time_ms']:.0f} ({m['process_ms']:.0f}) | {ratio} | {m['points']:.0f} "
            f"({100 * m['count_error']:+.1f} %) | {fmt(m['mesh_mean_rel'], '.2e')} / {fmt(m['mesh_rms_rel'], '.2e')} / "
            f"{fmt(m['mesh_max_rel'], '.2e')} | {fmt(m['coverage_p95_rel'], '.2e')} | {fmt(m['nn_cv'], '.3f')} | "
            f"{m['peak_rss_mb']:.0f} | {fmt(m['param'], '.4g')} |")
    text = "\n".join(out) + "\n"
    with open(args.out, "w") as f:
        f.write(text)
    with open(args.out.replace(".md", ".json"), "w") as f:
        json.dump(raw, f, indent=1)
    print(text)


if __name__ == "__main__":
    main()

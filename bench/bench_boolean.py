#!/usr/bin/env python3
"""Booleans on point sets against the path a user takes without them (issue 14, item 10).

Runs build/bin/bench_boolean once per side, case and round, in its own process, interleaved
(ours, then the peer's run of the same case, then ours again ...), takes medians, and writes a
Markdown table: time (the algorithm, and the whole process), peak RSS, output count and — for
the analytic cases — the distance of the output to the exact boundary and the coverage of that
boundary, all relative to A's bounding-box diagonal. The peer path: Open3D normals + Poisson
reconstruction of each input, CGAL corefine_and_compute_*, the result sampled uniformly to
our output's count.

    python3 bench/bench_boolean.py --bin build/bin --out bench/results-boolean.md [--rounds 3]
"""
import argparse
import datetime
import json
import os
import statistics
import subprocess
import sys
import time

CASES = [
    # name, rounds factor (the large case runs once a side)
    ("sphere-box-35k", 1.0),
    ("sphere-box-350k", 0.0),
    ("bunny-union-bunny", 1.0),
    ("bunny-minus-bunny", 1.0),
    ("dragon-union-dragon", 1.0),
    ("bunny-minus-sphere", 1.0),
]


def run(binary, side, case, count=None):
    cmd = [binary, "--side", side, "--case", case]
    if count:
        cmd += ["--count", str(count)]
    # Open3D's OpenMP would otherwise spin on every core it sees; the machine has 2, as ours uses.
    env = dict(os.environ, OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "2"))
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = (time.perf_counter() - t0) * 1000
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr.strip()}")
    j = json.loads(p.stdout.strip().splitlines()[-1])
    j["process_ms"] = wall
    return j


def median(rows, key):
    vals = [r[key] for r in rows if key in r]
    return statistics.median(vals) if vals else None


def fmt(v, spec):
    return "—" if v is None else format(v, spec)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin", default="build/bin")
    ap.add_argument("--out", default="bench/results-boolean.md")
    ap.add_argument("--rounds", type=int, default=3, help="rounds per side for the small cases (default 3)")
    ap.add_argument("--cases", default=",".join(c for c, _ in CASES), help="comma-separated subset")
    ap.add_argument("--no-peer", action="store_true", help="ours only (no CGAL/Open3D build)")
    args = ap.parse_args()
    binary = f"{args.bin}/bench_boolean"
    wanted = args.cases.split(",")
    lines = []
    raw = {}
    for case, factor in CASES:
        if case not in wanted:
            continue
        rounds = max(1, round(args.rounds * factor))
        ours, peer = [], []
        for _ in range(rounds):
            o = run(binary, "ours", case)
            ours.append(o)
            if not args.no_peer:
                peer.append(run(binary, "peer", case, o["points"]))
            print(f"{case}: ours {o['time_ms']:.0f} ms" + (f", peer {peer[-1]['time_ms']:.0f} ms" if peer else ""),
                  file=sys.stderr, flush=True)
        raw[case] = {"ours": ours, "peer": peer}
        row = {"case": case, "op": ours[0]["op"], "inputs": ours[0]["input_points"], "rounds": rounds}
        for side, rows in (("ours", ours), ("peer", peer)):
            if not rows:
                continue
            row[side] = {k: median(rows, k) for k in ("time_ms", "cpu_ms", "process_ms", "peak_rss_mb", "points",
                                                       "dist_mean_rel", "dist_p95_rel", "dist_max_rel",
                                                       "coverage_p95_rel", "coverage_max_rel")}
            row[side]["stages"] = {k: statistics.median(r["stages"][k] for r in rows) for k in rows[0]["stages"]}
            if side == "peer":
                row[side]["ok"] = all(r["ok"] for r in rows)
                row[side]["mesh_triangles"] = rows[0]["mesh_triangles"]
            else:
                row[side]["curve_samples"] = median(rows, "curve_samples")
                row[side]["mean_newton_iterations"] = median(rows, "mean_newton_iterations")
                row[side]["queries_saved_share"] = median(rows, "queries_saved_share")
                row["output_hash"] = rows[0].get("output_hash", "")
        lines.append(row)

    out = [f"# Booleans on point sets against Open3D Poisson + CGAL corefinement ({datetime.date.today()})", "",
           f"`python3 bench/bench_boolean.py --bin {args.bin} --rounds {args.rounds}`: each side of each case in its own "
           "process, interleaved, medians. Times in ms; distances relative to A's bounding-box diagonal (analytic cases "
           "only: |signed distance of the exact CSG solid| for the output points; coverage = dense samples of the exact "
           "boundary → nearest output point).", "",
           "| case | op | inputs | ours ms (process) | peer ms (process) | ratio | points | ours mean / p95 / max dist | "
           "peer mean / p95 / max dist | ours / peer coverage p95 | RSS MB ours / peer |",
           "|---|---|---|---:|---:|---:|---:|---|---|---|---|"]
    for r in lines:
        o, p = r["ours"], r.get("peer")
        ratio = f"{p['time_ms'] / o['time_ms']:.1f}×" if p else "—"
        od = f"{fmt(o['dist_mean_rel'], '.1e')} / {fmt(o['dist_p95_rel'], '.1e')} / {fmt(o['dist_max_rel'], '.1e')}"
        pd = (f"{fmt(p['dist_mean_rel'], '.1e')} / {fmt(p['dist_p95_rel'], '.1e')} / {fmt(p['dist_max_rel'], '.1e')}"
              if p else "—")
        cov = f"{fmt(o['coverage_p95_rel'], '.1e')} / {fmt(p['coverage_p95_rel'] if p else None, '.1e')}"
        out.append(f"| {r['case']} | {r['op']} | {r['inputs'][0]} + {r['inputs'][1]} | "
                   f"{o['time_ms']:.0f} ({o['process_ms']:.0f}) | "
                   + (f"{p['time_ms']:.0f} ({p['process_ms']:.0f})" if p else "—")
                   + f" | {ratio} | {o['points']:.0f} | {od} | {pd} | {cov} | {o['peak_rss_mb']:.0f} / "
                   + (f"{p['peak_rss_mb']:.0f}" if p else "—") + " |")
    out += ["", "Peer stages (medians, ms) and ours' report:", ""]
    for r in lines:
        o, p = r["ours"], r.get("peer")
        cpu = f" (CPU {o['cpu_ms']:.0f} ms, output {r['output_hash']})" if o.get("cpu_ms") is not None else ""
        s = (f"- {r['case']}: ours {o['time_ms']:.0f} ms{cpu}, {o['curve_samples']:.0f} curve samples, "
             f"{o['mean_newton_iterations']:.2f} Newton iterations, {100 * o['queries_saved_share']:.0f} % of "
             "classification queries saved")
        if p:
            s += ("; peer " + ", ".join(f"{k} {v:.0f}" for k, v in p["stages"].items())
                  + f", meshes {p['mesh_triangles'][0]} + {p['mesh_triangles'][1]} → {p['mesh_triangles'][2]} "
                  "triangles" + ("" if p["ok"] else ", **corefinement failed**"))
        out.append(s)
    text = "\n".join(out) + "\n"
    with open(args.out, "w") as f:
        f.write(text)
    with open(args.out.replace(".md", ".json"), "w") as f:
        json.dump(raw, f, indent=1)
    print(text)


if __name__ == "__main__":
    main()

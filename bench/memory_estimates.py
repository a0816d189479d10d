#!/usr/bin/env python3
"""Job memory estimates against measured peak RSS (issue 18.2).

Runs every job kind in-process (`surfel <kind> --json`) on the shared scans at a few option
settings under /usr/bin/time -v, reads the peak RSS, subtracts the baseline (the peak of
`surfel info` on the same cloud: the process, its libraries and the loaded cloud's parse), and
compares with the job report's memory_estimate_bytes (JobKind::EstimateMemory). Writes
bench/results-memory.md. Target: estimate / measured within 1/1.5 .. 1.5.

Usage: bench/memory_estimates.py [--surfel build/bin/surfel] [--data ../shared/data] [--quick]
"""
import argparse
import json
import os
import re
import subprocess
import sys
import tempfile


def peak_rss(cmd):
    """Runs cmd under /usr/bin/time -v; returns (peak RSS bytes, stdout)."""
    p = subprocess.run(["/usr/bin/time", "-v"] + cmd, capture_output=True, text=True)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr[-2000:]}")
    m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", p.stderr)
    return int(m.group(1)) * 1024, p.stdout


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    ap = argparse.ArgumentParser()
    ap.add_argument("--surfel", default=os.path.join(here, "..", "build", "bin", "surfel"))
    ap.add_argument("--data", default=os.path.join(here, "..", "..", "shared", "data"))
    ap.add_argument("--out", default=os.path.join(here, "results-memory.md"))
    ap.add_argument("--quick", action="store_true", help="fewer cases")
    a = ap.parse_args()
    d = a.data
    tmp = tempfile.mkdtemp(prefix="surfel-mem-")
    cases = [
        ("render", "bunny.ply", ["--width", "512", "--height", "512"]),
        ("render", "bunny.ply", ["--width", "2048", "--height", "2048"]),
        ("render", "person_scan.ply", ["--width", "1024", "--height", "1024"]),
        ("render", "dragon.ply", ["--width", "4096", "--height", "4096", "--no-shadows", "--png", os.path.join(tmp, "x.png")]),
        ("render", "person_scan.ply", ["--width", "256", "--height", "256"]),
        ("render", "lucy.ply", ["--width", "1024", "--height", "1024"]),
        ("simplify", "bunny_scans_merged.ply", ["--target", "20000"]),
        ("simplify", "person_scan.ply", ["--target", "5000", "--method", "voxel"]),
        ("simplify", "buddha_scan.ply", ["--target", "5000", "--method", "incremental"]),
    ]
    # Every simplification method on a large and a mid-sized scan (the estimate is per method).
    for method in ["hierarchical", "incremental", "iterative", "particle", "voxel"]:
        cases.append(("simplify", "bunny_scans_merged.ply", ["--target", "18000", "--method", method]))
        cases.append(("simplify", "buddha_scan.ply", ["--target", "4000", "--method", method]))
    cases += [
        ("resample", "bunny.ply", ["--target", "200000", "--iterations", "10"]),
        ("resample", "dragon_scan.ply", ["--target", "20000", "--iterations", "10"]),
        ("resample", "bunny_scan.ply", ["--method", "mls"]),
        ("resample", "dragon_scan.ply", ["--method", "split", "--spacing", "0.0015"]),
        ("resample", "buddha_scan.ply", ["--method", "split", "--spacing", "0.001"]),
        ("boolean", "bunny.ply", ["--op", "union", "--translate", "0.03,0,0"]),
        ("boolean", "dragon.ply", ["--op", "difference", "--translate", "0.02,0.01,0"]),
    ]
    if a.quick:
        cases = cases[::3]
    rows = []
    for kind, cloud, opts in cases:
        path = os.path.join(d, cloud)
        base, _ = peak_rss([a.surfel, "info", path])
        ext = ".exr" if kind == "render" else ".ply"
        inputs = [path, path] if kind == "boolean" else [path]
        cmd = [a.surfel, kind] + inputs + ["-o", os.path.join(tmp, "out" + ext), "--json", "--quiet"] + opts
        peak, out = peak_rss(cmd)
        report = json.loads(out)
        est = report["memory_estimate_bytes"]
        measured = max(peak - base, 1)
        ratio = est / measured
        rows.append((kind, cloud, " ".join(o for o in opts if not o.startswith(tmp)), report.get("points"), est,
                     measured, ratio, base))
        print(f"{kind:9s} {cloud:24s} {' '.join(opts):40s} est {est/2**20:9.1f} MiB  measured {measured/2**20:9.1f} "
              f"MiB  ratio {ratio:5.2f}", flush=True)
    load = os.getloadavg()
    with open(a.out, "w") as f:
        f.write("# Job memory: estimate vs measured peak RSS\n\n")
        f.write(f"`bench/memory_estimates.py{' --quick' if a.quick else ''}`; peak RSS from /usr/bin/time -v minus the "
                "peak of `surfel info` on the same file (process baseline + parse). Memory figures are not disturbed "
                f"by CPU load (load average at the end: {load[0]:.1f}). Target: ratio within 0.67..1.5.\n\n")
        f.write("| kind | cloud | options | points | estimate MiB | measured MiB | ratio | baseline MiB |\n")
        f.write("|---|---|---|---:|---:|---:|---:|---:|\n")
        for kind, cloud, opts, pts, est, meas, ratio, base in rows:
            flag = "" if 1 / 1.5 <= ratio <= 1.5 else " **(outside)**"
            f.write(f"| {kind} | {cloud} | `{opts}` | {pts} | {est/2**20:.1f} | {meas/2**20:.1f} | {ratio:.2f}{flag} | "
                    f"{base/2**20:.1f} |\n")
    print("wrote", a.out)


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Runs Surfel's benchmarks and the peers' (CGAL, PCL, Open3D) in one go and writes markdown
tables with ratios: bench/compare.py [--bin build/bin] [--out bench/results.md] [--filter REGEX]
[--json ROWS] (then bench/compare.py --from-json ROWS --out FILE writes the tables again)

Each benchmark runs in its own process, so `peak_rss_mb` is that benchmark's own peak (the
dataset loaded plus the algorithm). Times are wall-clock (both cores available to everyone);
benchmarks under 3 s are run 5 more times, interleaved with the peers' runs of the same task
(Surfel, CGAL, PCL, Open3D, Surfel, ...), and the median is reported.
"""
import argparse
import datetime
import json
import os
import re
import subprocess
import sys
import tempfile

MEDIAN_BELOW_MS = 3000  # benchmarks shorter than this are repeated (median reported)
ROUNDS = 5  # interleaved repetitions of each short benchmark

PROGRAMS = [("bench_core", "surfel"), ("bench_peer_cgal", "CGAL 5.5"), ("bench_peer_pcl", "PCL 1.13"),
            ("bench_peer_open3d", "Open3D 0.16")]

# Which surfel benchmark a peer's task is compared with, and what the task is called in the table.
SIMPLIFY_PEER_NAMES = {("CGAL 5.5", "hierarchical"): "hierarchy_simplify_point_set",
                       ("CGAL 5.5", "voxel"): "grid_simplify_point_set",
                       ("CGAL 5.5", "wlop"): "wlop_simplify_and_regularize_point_set",
                       ("PCL 1.13", "voxel"): "VoxelGrid", ("Open3D 0.16", "voxel"): "VoxelDownSample"}


def filter_escape(name):
    """`name` as a literal in Google Benchmark's filter. Not re.escape: it escapes '-' too, which
    the library's std::regex rejects ("Invalid escape"), and the run then exits 0 having run
    nothing (the hierarchical-positions rows)."""
    return re.sub(r"([.^$|?*+()\[\]{}\\])", r"\\\1", name)


def run_benchmark(exe, name, repetitions=1):
    """One process running one benchmark; its JSON records (the median aggregate when repeated)."""
    with tempfile.NamedTemporaryFile(suffix=".json") as out:
        args = [exe, f"--benchmark_filter=^{filter_escape(name)}$", f"--benchmark_out={out.name}",
                "--benchmark_out_format=json"]
        if repetitions > 1:
            args += [f"--benchmark_repetitions={repetitions}", "--benchmark_report_aggregates_only=true"]
        r = subprocess.run(args, capture_output=True, text=True)
        if r.returncode != 0:
            print(f"compare: {name} failed:\n{r.stderr[-2000:]}", file=sys.stderr)
            return None
        text = open(out.name).read()
        if not text.strip():
            print(f"compare: {name} ran nothing:\n{r.stderr[-2000:]}", file=sys.stderr)
            return None
        records = json.loads(text)["benchmarks"]
        if repetitions > 1:
            records = [b for b in records if b.get("aggregate_name") == "median"] or records
        return records


def real_ms(b):
    return b["real_time"] if b["time_unit"] == "ms" else b["real_time"] / 1e6


def cpu_ms(b):
    """CPU time of the whole process (bench_common.h registers with MeasureProcessCPUTime)."""
    return b["cpu_time"] if b["time_unit"] == "ms" else b["cpu_time"] / 1e6


def run_all(bin_dir, regex):
    """Every benchmark once (its counters and a first time); then the short ones (under
    MEDIAN_BELOW_MS) again ROUNDS times, interleaved: each round runs Surfel's benchmark and every
    peer's benchmark of the same name one after the other, so a noisy stretch of the shared VM
    falls on all of them alike; the median of the rounds is reported."""
    first = {}  # (impl, name) -> records
    order = []
    for program, impl in PROGRAMS:
        exe = os.path.join(bin_dir, program)
        if not os.path.exists(exe):
            print(f"compare: {program} not built, skipped", file=sys.stderr)
            continue
        names = subprocess.run([exe, "--benchmark_list_tests"], capture_output=True, text=True,
                               check=True).stdout.split()
        for name in names:
            if regex and not re.search(regex, name):
                continue
            print(f"compare: {impl}: {name}", file=sys.stderr, flush=True)
            records = run_benchmark(exe, name)
            if records:
                first[(impl, name)] = (exe, records)
                order.append((impl, name))
    short = {}
    for key in order:
        exe, records = first[key]
        if real_ms(records[0]) < MEDIAN_BELOW_MS:
            short.setdefault(key[1], []).append((key[0], exe))
    times = {key: [] for name, group in short.items() for key in ((impl, name) for impl, _ in group)}
    for name, group in short.items():
        print(f"compare: {ROUNDS} interleaved rounds of {name} ({', '.join(i for i, _ in group)})",
              file=sys.stderr, flush=True)
        for _ in range(ROUNDS):
            for impl, exe in group:
                records = run_benchmark(exe, name)
                if records:
                    times[(impl, name)].append((real_ms(records[0]), cpu_ms(records[0])))
    rows = []
    for impl, name in order:
        _, records = first[(impl, name)]
        for b in records:
            task, dataset = b["name"].split("/")[:2]
            samples = times.get((impl, name), [])
            walls = sorted(t for t, _ in samples)
            cpus = sorted(c for _, c in samples)
            ms = walls[len(walls) // 2] if walls else real_ms(b)
            cpu = cpus[len(cpus) // 2] if cpus else cpu_ms(b)
            extra = {k: v for k, v in b.items() if k not in (
                "name", "run_name", "run_type", "repetitions", "repetition_index", "threads", "iterations",
                "real_time", "cpu_time", "time_unit", "family_index", "per_family_instance_index",
                "aggregate_name", "aggregate_unit", "label")}
            rows.append({"impl": impl, "task": task, "dataset": dataset, "ms": ms, "cpu_ms": cpu, **extra})
    return rows


def fmt(v, digits=3):
    if isinstance(v, float):
        if v == 0:
            return "0"
        if abs(v) >= 1000:
            return f"{v:,.0f}"
        if abs(v) >= 1:
            return f"{v:.{digits}g}" if abs(v) < 100 else f"{v:.0f}"
        return f"{v:.{digits}g}"
    return str(v)


def table(header, body):
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" if i == 0 else "---:" for i in range(len(header))) + "|"]
    out += ["| " + " | ".join(fmt(c) for c in row) + " |" for row in body]
    return "\n".join(out)


def core_section(rows):
    lines = ["## Issue 3: neighbours, normals, MLS (`bench_core` beside the peers)", ""]
    for task, title, quality in [
            ("knn16", "16 nearest neighbours of every point (tree build included)", []),
            ("normals_oriented", "normals (k = 16) + consistent orientation (MST, k = 10)",
             [("within30", "within 30° of the mesh normal")]),
            ("mls_project", "MLS projection of every point (degree 2; each row's support: `radius`; "
             "mls_project = Surfel's defaults, h = 2 x median spacing, 3h, given to PCL too; _c15/_c20 = "
             "Surfel cut at 1.5h/2h; _pcl_r10/15/20 = PCL's own weighting exp(-d²/r²) at r = 1, 1.5, 2 h)",
             [("radius", "support radius"), ("points", "points projected"),
              ("mesh_mean", "mean distance to the mesh"), ("mesh_rms", "RMS distance")])]:
        lines += [f"### {title}", ""]
        match = (lambda t: t.startswith("mls_project")) if task == "mls_project" else (lambda t: t == task)
        for dataset in sorted({r["dataset"] for r in rows if match(r["task"])}):
            sel = [r for r in rows if match(r["task"]) and r["dataset"] == dataset]
            ours = next((r for r in sel if r["impl"] == "surfel" and r["task"] == task), None)
            body = []
            for r in sorted(sel, key=lambda r: r["ms"]):
                ratio = r["ms"] / ours["ms"] if ours else float("nan")
                name = r["impl"] if r["task"] == task else f"{r['impl']} {r['task'][len(task):]}"
                body.append([name, r["ms"], r.get("cpu_ms", "–"), f"{ratio:.2f}×"] + [r.get(k, "–") for k, _ in quality])
            lines += [f"`{dataset}`", "", table(["implementation", "time (ms)", "CPU (ms)", "time / surfel's"] +
                                                 [q for _, q in quality], body), ""]
    return lines


def render_section(rows):
    lines = ["## Issue 4: render (surfel: ray tracing the point-set surface; Open3D: normals + Poisson + "
             "Embree ray cast of the mesh)", ""]
    for task in sorted({r["task"] for r in rows if r["task"].startswith("render")}):
        sel = [r for r in rows if r["task"] == task]
        ours = next((r for r in sel if r["impl"] == "surfel"), None)
        body = []
        for r in sorted(sel, key=lambda r: r["ms"]):
            ratio = r["ms"] / ours["ms"] if ours else float("nan")
            body.append([r["impl"], r["dataset"], r["ms"], f"{ratio:.2f}×", r.get("hits", "–"),
                         r.get("avg_iterations", "–"), r.get("rays_per_s", "–")])
        lines += [f"### {task}", "", table(["implementation", "dataset", "time (ms)", "time / surfel's", "hits",
                                              "iterations per hit", "rays/s"], body), ""]
    return lines


def simplify_section(rows):
    lines = ["## Issue 5: simplification at the same output count", "",
             "`err` is Surfel's surface error (Δavg, Δmax of the input surface against the result's MLS "
             "surface, relative to the bounding-box diagonal), the same metric for every implementation: "
             "`err avg` weights each sample by the area it stands for (the notes' area integral), "
             "`per sample` is the plain mean over the input's samples (it leans to densely scanned regions); "
             "`linear` is Δavg by area with the notes' linear basis for the projection onto the result's "
             "surface (Surfel's default is quadratic, see docs/surface-model.md); "
             "`cover p95` is the 95th percentile of the distance from points spread uniformly over bunny_mesh.ply "
             "(person_scan: from its input points) to the nearest output point, relative to the diagonal; "
             "`mesh` is the mean distance of the output points to bunny_mesh.ply (bunny only). "
             "`vs surfel` divides by Surfel's time for the same kind of method (voxel for the grids, "
             "particle for WLOP; for CGAL's hierarchy, Surfel's hierarchical clustering with positions only "
             "at CGAL's count, `hierarchical-positions-cgal-count`, what CGAL returns: `hierarchical` also "
             "estimates and orients the output's normals and gives each point a radius; "
             "`hierarchical-members-cgal-count` is the same with `--representative member`, CGAL's own "
             "representative, the member nearest each centroid).", ""]
    sel = [r for r in rows if r["task"].startswith("simplify_")]
    for key in sorted({(r["dataset"], r["task"].rsplit("_", 1)[1]) for r in sel}):
        dataset, pct = key
        group = [r for r in sel if r["dataset"] == dataset and r["task"].endswith("_" + pct)]
        ours = {r["task"].split("_")[1]: r for r in group if r["impl"] == "surfel"}
        body = []
        for r in sorted(group, key=lambda r: r["ms"]):
            method = r["task"].split("_")[1]
            name = method if r["impl"] == "surfel" else SIMPLIFY_PEER_NAMES.get((r["impl"], method), method)
            ref = ours.get({"wlop": "particle"}.get(method, method))
            if r["impl"] == "CGAL 5.5" and method == "hierarchical":
                # Like for like: CGAL returns positions only, at its own count.
                ref = ours.get("hierarchical-positions-cgal-count") or ours.get("hierarchical-positions") or ref
            ratio = f"{r['ms'] / ref['ms']:.2f}×" if ref and r["impl"] != "surfel" else "–"
            body.append([f"{r['impl']} {name}", int(r.get("points", 0)), r["ms"], r.get("cpu_ms", "–"), ratio,
                         r.get("err_avg_rel", "–"), r.get("cover_p95", "–"), r.get("err_avg_ps_rel", "–"), r.get("err_avg_lin_rel", "–"),
                         r.get("err_max_rel", "–"),
                         r.get("mesh_mean", "–"),
                         r.get("peak_rss_mb", "–")])
        lines += [f"### `{dataset}` to {pct.replace('pct', ' %')}", "",
                  table(["implementation", "points", "time (ms)", "CPU (ms, all threads)", "vs surfel", "err avg (rel)",
                         "cover p95 (rel)", "per sample", "linear",
                         "err max (rel)",
                         "mesh mean", "peak RSS (MB)"], body), ""]
    return lines


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--bin", default="build/bin")
    ap.add_argument("--out", default="bench/results.md")
    ap.add_argument("--filter", default="")
    ap.add_argument("--json", help="also keep the raw rows here")
    ap.add_argument("--from-json", metavar="FILE",
                    help="write the tables from the rows a --json run kept, running nothing")
    a = ap.parse_args()
    rows = json.load(open(a.from_json)) if a.from_json else run_all(a.bin, a.filter)
    if a.json and not a.from_json:
        json.dump(rows, open(a.json, "w"), indent=1)
    uname = os.uname()
    lines = [f"# Benchmark results ({datetime.date.today()}, {os.cpu_count()} cores, {uname.sysname} "
             f"{uname.release})", "", (f"Tables written by `bench/compare.py --from-json {a.from_json}` from an "
                                       "earlier run's rows" if a.from_json else
                                       f"Produced by `bench/compare.py --bin {a.bin}`" +
                                       (f" --filter '{a.filter}'" if a.filter else "")) + "; wall-clock times; benchmarks under 3 s: the median of 5 runs, "
             "each run beside the peers' runs of the same task (interleaved rounds).", ""]
    lines += core_section(rows) + render_section(rows) + simplify_section(rows)
    text = "\n".join(lines) + "\n"
    open(a.out, "w").write(text)
    print(text)


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Interleaved A/B rounds of the headline render (issue 19.1) for several `surfel` binaries:

    python3 bench/render_ab.py ROUNDS BIN [BIN ...]

Each round runs every binary once (a fresh process, after one untimed warm-up round) on
../shared/data/bunny.ply with bench/regress's RENDER_ARGS, and prints per binary the median and
minimum of the wall ms (fork to exit), the process CPU ms (user + system) and the render's own
time_ms and setup_ms, with the load average before and after. For before/after comparisons of builds kept
side by side (each binary with its image plugins beside it)."""
import json, os, subprocess, sys, time, statistics
ARGS = "--width 320 --height 250 --eye -0.0100,0.1080,0.3300 --target -0.0100,0.1080,-0.0014 --up 0,1,0 --fovy 30 --light dir:-0.4,-0.5,-1 --spp 1".split()
bins = sys.argv[2:]; rounds = int(sys.argv[1])
env = {k: v for k, v in os.environ.items() if k not in ("SURFEL_IMAGE_PLUGIN", "SURFEL_EXR_PLUGIN")}
res = {b: {"wall": [], "cpu": [], "time_ms": [], "setup_ms": []} for b in bins}
print("load before", os.getloadavg())
for r in range(rounds + 1):
    for b in bins:
        t = time.perf_counter()
        p = subprocess.Popen([b, "render", os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data", "bunny.ply"), "-o", "/tmp/render_ab.exr", "-q", "--json"] + ARGS, stdout=subprocess.PIPE, env=env)
        out = p.stdout.read(); _, st, ru = os.wait4(p.pid, 0)
        wall = (time.perf_counter() - t) * 1000
        if r == 0: continue
        j = json.loads(out.decode().strip().splitlines()[-1])
        res[b]["wall"].append(wall); res[b]["cpu"].append((ru.ru_utime + ru.ru_stime) * 1000); res[b]["time_ms"].append(j["time_ms"]); res[b]["setup_ms"].append(j["setup_ms"])
for b in bins:
    print(b, " ".join(f"{k} median {statistics.median(v):.0f} min {min(v):.0f}" for k, v in res[b].items()))
print("load after", os.getloadavg())

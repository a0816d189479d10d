#!/usr/bin/env python3
"""A/B of `surfel upload` end to end (issue 19.3): for each LABEL=BINDIR, a fresh surfel-server on a
fresh data dir per round, the real CLI, interleaved rounds, medians; the server's CPU from /proc.
usage: bench/ab_upload.py FILE ROUNDS label=bindir[@server args] [label=bindir[@server args] ...]
(e.g. new0="build-bench/bin@--transfer-threads 0": the same binaries, the server started with those flags)"""
import resource, json, os, shutil, signal, statistics, subprocess, sys, tempfile, time
f, rounds = sys.argv[1], int(sys.argv[2])
bins = [a.split("=", 1) for a in sys.argv[3:]]
EXTRA = {}
for l, b in bins:
    EXTRA[b] = b.split("@")[1].split() if "@" in b else []
res = {l: {"time_ms": [], "wall_ms": []} for l, _ in bins}
size = os.path.getsize(f)
def one(bindir):
    d = tempfile.mkdtemp(prefix="m-", dir=tempfile.gettempdir())
    pf = d + "/port"
    srv = subprocess.Popen([bindir.split("@")[0] + "/surfel-server"] + EXTRA[bindir] + ["--port", "0", "--port-file", pf, "--data-dir", d + "/d",
                            "--log-level", "warn"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while not os.path.exists(pf) or not open(pf).read().strip(): time.sleep(0.001)
    port = open(pf).read().strip()
    tck = os.sysconf("SC_CLK_TCK")
    def scpu():
        st = open(f"/proc/{srv.pid}/stat").read().rsplit(")", 1)[1].split()
        return (int(st[11]) + int(st[12])) * 1000.0 / tck
    s0 = scpu()
    t = time.perf_counter()
    p = subprocess.Popen([bindir.split("@")[0] + "/surfel", "upload", f, "--server", "127.0.0.1:" + port, "-q", "--json"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    so, se = p.communicate()
    _, _, ru = os.wait4(p.pid, 0) if False else (0, 0, None)
    wall = (time.perf_counter() - t) * 1000
    scpu_ms = scpu() - s0
    ccpu_ms = (resource.getrusage(resource.RUSAGE_CHILDREN).ru_utime + resource.getrusage(resource.RUSAGE_CHILDREN).ru_stime) * 1000
    global last_children
    c_ms = ccpu_ms - last_children; last_children = ccpu_ms
    class O: pass
    out = O(); out.returncode = p.returncode; out.stdout = so; out.stderr = se
    srv.send_signal(signal.SIGTERM); srv.wait()
    shutil.rmtree(d)
    if out.returncode != 0: raise SystemExit(out.stderr)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert not r["deduplicated"]
    cpu.setdefault(bindir, {"server": [], "client": []})
    cpu[bindir]["server"].append(scpu_ms); cpu[bindir]["client"].append(c_ms)
    return r["time_ms"], wall
cpu = {}
last_children = 0.0
for l, b in bins: one(b)  # warm-up
for i in range(rounds):
    for l, b in bins:
        t, w = one(b)
        res[l]["time_ms"].append(t); res[l]["wall_ms"].append(w)
print("load before/after:", os.getloadavg())
for l, _b in bins:
    t = statistics.median(res[l]["time_ms"]); w = statistics.median(res[l]["wall_ms"])
    print(f"{l}: time_ms median {t:.1f} (min {min(res[l]['time_ms']):.1f}) = {size/1e9/(t/1000):.3f} GB/s; "
          f"whole process wall median {w:.1f} ms (min {min(res[l]['wall_ms']):.1f}) = {size/1e9/(w/1000):.3f} GB/s; "
          f"server CPU ms median {statistics.median(cpu[_b]['server'][1:]):.0f}")

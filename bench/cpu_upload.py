#!/usr/bin/env python3
"""CPU seconds per GiB of an upload (issue 19.3), server and client apart: the figure that a
loaded, shared machine still measures (wall time there says little).

For each LABEL=BINDIR and each round: a fresh `surfel-server` on a fresh data dir, then the real
`surfel upload FILE --json` under perf stat and GNU time (the client's CPU: its whole process,
start-up, reading, hashing, sending); the server's CPU (all its threads) from `perf stat -p`
attached across the upload, and /proc/PID/stat before and after (receive, hash, write, parse, fsync,
store; not its start-up). The totals are perf stat's task-clock (exact); the user / system split
is from the kernel's tick accounting (10 ms steps). Rounds are interleaved (each binary once per round); medians.

usage: bench/cpu_upload.py FILE ROUNDS label=bindir [label=bindir ...]
"""
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time

TCK = os.sysconf("SC_CLK_TCK")


def proc_cpu(pid):
    st = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return int(st[11]) / TCK, int(st[12]) / TCK  # utime, stime in seconds, all threads


def task_clock(path):
    for line in open(path):
        f = line.strip().split(",")
        if len(f) > 2 and f[2] == "task-clock":
            return float(f[0]) / 1000.0  # msec -> s
    raise SystemExit(f"no task-clock in {path}")


def one(bindir, path):
    d = tempfile.mkdtemp(prefix="cpu-upload-", dir=tempfile.gettempdir())
    pf, tf = d + "/port", d + "/time"
    srv = subprocess.Popen([bindir + "/surfel-server", "--port", "0", "--port-file", pf, "--data-dir", d + "/d",
                            "--log-level", "warn"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        while not os.path.exists(pf) or not open(pf).read().strip():
            time.sleep(0.002)
        port = open(pf).read().strip()
        time.sleep(0.05)  # the server's start-up is not the upload's
        sf, cf = d + "/server-stat", d + "/client-stat"
        perf = subprocess.Popen(["perf", "stat", "-x,", "-e", "task-clock", "-o", sf, "-p", str(srv.pid)],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(0.1)  # perf attached
        su0, ss0 = proc_cpu(srv.pid)
        t = time.perf_counter()
        p = subprocess.run(["perf", "stat", "-x,", "-e", "task-clock", "-o", cf, "--", "/usr/bin/time", "-f", "%U %S",
                            "-o", tf, bindir + "/surfel", "upload", path,
                            "--server", "127.0.0.1:" + port, "-q", "--json"], capture_output=True, text=True)
        wall = time.perf_counter() - t
        su1, ss1 = proc_cpu(srv.pid)
        perf.send_signal(signal.SIGINT)
        perf.wait()
        if p.returncode != 0:
            raise SystemExit(p.stderr)
        cu, cs = (float(x) for x in open(tf).read().split()[-2:])
        s_clock, c_clock = task_clock(sf), task_clock(cf)
    finally:
        srv.send_signal(signal.SIGTERM)
        srv.wait()
        shutil.rmtree(d, ignore_errors=True)
    r = json.loads(p.stdout.strip().splitlines()[-1])
    assert not r["deduplicated"], "a fresh data dir deduplicated the upload"
    return {"time_ms": r["time_ms"], "wall_ms": wall * 1000, "server": s_clock, "client": c_clock,
            "server_user": su1 - su0, "server_sys": ss1 - ss0,
            "client_user": cu, "client_sys": cs}


def main():
    path, rounds = sys.argv[1], int(sys.argv[2])
    bins = [a.split("=", 1) for a in sys.argv[3:]]
    gib = os.path.getsize(path) / (1 << 30)
    res = {l: [] for l, _ in bins}
    for _, b in bins:
        one(b, path)  # warm-up: page cache
    load0 = os.getloadavg()[0]
    for _ in range(rounds):
        for l, b in bins:
            res[l].append(one(b, path))
    load1 = os.getloadavg()[0]
    print(f"{path}: {gib * 1024:.1f} MiB, {rounds} interleaved rounds, load average {load0:.2f} -> {load1:.2f}")
    print("| build | server CPU s (user + sys) | server s/GiB | client CPU s (user + sys) | client s/GiB "
          "| sum s/GiB | CLI time_ms | wall ms |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for l, _ in bins:
        rows = res[l]

        def med(f):
            return statistics.median(f(x) for x in rows)

        s = med(lambda x: x["server"])
        c = med(lambda x: x["client"])
        tot = med(lambda x: x["server"] + x["client"])
        print(f"| {l} | {s:.3f} ({med(lambda x: x['server_user']):.3f} + {med(lambda x: x['server_sys']):.3f}) "
              f"| {s / gib:.2f} | {c:.3f} ({med(lambda x: x['client_user']):.3f} + "
              f"{med(lambda x: x['client_sys']):.3f}) | {c / gib:.2f} | {tot / gib:.2f} "
              f"| {med(lambda x: x['time_ms']):.0f} (min {min(x['time_ms'] for x in rows):.0f}) "
              f"| {med(lambda x: x['wall_ms']):.0f} |")


if __name__ == "__main__":
    main()

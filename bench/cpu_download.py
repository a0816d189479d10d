#!/usr/bin/env python3
"""CPU seconds per GiB of a result download (issue 19.3), server and client apart.

For each LABEL=BINDIR and each round: a fresh `surfel-server` on a fresh data dir, FILE uploaded
and a job run whose result is about as large as FILE (`simplify --method voxel` to TARGET points,
default 95 % of the input's: a binary PLY of positions and normals); then, measured, the real
`surfel download JOB -o OUT` under perf stat (the client's task-clock, start-up included) while
`perf stat -p` counts the server's (reading the result blob, hashing it, sending it). Rounds
are interleaved; medians. The downloaded bytes are compared with the job's recorded size.

usage: bench/cpu_download.py FILE ROUNDS label=bindir [label=bindir ...]
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


def task_clock(path):
    for line in open(path):
        f = line.strip().split(",")
        if len(f) > 2 and f[2] == "task-clock":
            return float(f[0]) / 1000.0
    raise SystemExit(f"no task-clock in {path}")


def last_json(text):
    return json.loads(text.strip().splitlines()[-1])


def one(bindir, path, target):
    d = tempfile.mkdtemp(prefix="cpu-download-", dir=tempfile.gettempdir())
    pf = d + "/port"
    srv = subprocess.Popen([bindir + "/surfel-server", "--port", "0", "--port-file", pf, "--data-dir", d + "/d",
                            "--log-level", "warn"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        while not os.path.exists(pf) or not open(pf).read().strip():
            time.sleep(0.002)
        server = "127.0.0.1:" + open(pf).read().strip()
        run = subprocess.run([bindir + "/surfel", "simplify", path, "-o", d + "/ignored.ply", "--method", "voxel",
                              "--target", str(target), "--server", server, "--detach", "-q", "--json"],
                             capture_output=True, text=True, check=True)
        job = last_json(run.stdout)["job_id"]
        while True:
            j = last_json(subprocess.run([bindir + "/surfel", "job", job, "--server", server, "--json", "-q"],
                                         capture_output=True, text=True, check=True).stdout)
            if j.get("state") in ("SUCCEEDED", "succeeded"):
                break
            if j.get("state") in ("FAILED", "CANCELLED", "failed", "cancelled"):
                raise SystemExit(f"job {job}: {j}")
            time.sleep(0.1)
        sf, cf = d + "/server-stat", d + "/client-stat"
        perf = subprocess.Popen(["perf", "stat", "-x,", "-e", "task-clock", "-o", sf, "-p", str(srv.pid)],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(0.1)
        t = time.perf_counter()
        p = subprocess.run(["perf", "stat", "-x,", "-e", "task-clock", "-o", cf, "--", bindir + "/surfel", "download",
                            job, "-o", d + "/out.ply", "--server", server, "-q", "--json"],
                           capture_output=True, text=True)
        wall = time.perf_counter() - t
        perf.send_signal(signal.SIGINT)
        perf.wait()
        if p.returncode != 0:
            raise SystemExit(p.stderr)
        size = last_json(p.stdout)["size_bytes"]
        assert size == os.path.getsize(d + "/out.ply")
        return {"server": task_clock(sf), "client": task_clock(cf), "wall_ms": wall * 1000, "bytes": size}
    finally:
        srv.send_signal(signal.SIGTERM)
        srv.wait()
        shutil.rmtree(d, ignore_errors=True)


def main():
    path, rounds = sys.argv[1], int(sys.argv[2])
    bins = [a.split("=", 1) for a in sys.argv[3:]]
    info = last_json(subprocess.run([bins[0][1] + "/surfel", "info", path, "--json"], capture_output=True,
                                    text=True, check=True).stdout)
    target = int(info["points"] * 0.95)
    res = {l: [] for l, _ in bins}
    load0 = os.getloadavg()[0]
    for _ in range(rounds):
        for l, b in bins:
            res[l].append(one(b, path, target))
    load1 = os.getloadavg()[0]
    size = res[bins[0][0]][0]["bytes"]
    gib = size / (1 << 30)
    print(f"result {size / (1 << 20):.1f} MiB (voxel simplify of {path} to {target} points), {rounds} interleaved "
          f"rounds, load average {load0:.2f} -> {load1:.2f}")
    print("| build | server CPU s | server s/GiB | client CPU s | client s/GiB | sum s/GiB | wall ms |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for l, _ in bins:
        rows = res[l]
        s = statistics.median(x["server"] for x in rows)
        c = statistics.median(x["client"] for x in rows)
        tot = statistics.median(x["server"] + x["client"] for x in rows)
        print(f"| {l} | {s:.3f} | {s / gib:.2f} | {c:.3f} | {c / gib:.2f} | {tot / gib:.2f} "
              f"| {statistics.median(x['wall_ms'] for x in rows):.0f} |")


if __name__ == "__main__":
    main()

#!/usr/bin/python3
"""A/B of the HTTP upload between two surfel-server binaries (e.g. before and after a change to the
HTTP front): both servers run side by side, every round uploads the same generated file to each
with curl and with Python's http.client, interleaved, and the medians are printed.

  cp build/bin/surfel-server /tmp/surfel-server-old   # before the change, then rebuild
  /usr/bin/python3 bench/ab_http_upload.py --a /tmp/surfel-server-old --b build/bin/surfel-server
"""
import argparse
import http.client
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "tests", "http"))
sys.path.insert(0, HERE)
from surfel_http import Server, request  # noqa: E402
from bench_http import write_torus  # noqa: E402


def upload_curl(server, path, size):
    out = subprocess.run(["curl", "-sS", "--fail-with-body", "-H", "Expect:", "-X", "POST", "-T", path,
                          server.base + "/v1/clouds?filename=t.ply"], capture_output=True, check=True)
    return json.loads(out.stdout)["id"]


def upload_python(server, path, size):
    conn = http.client.HTTPConnection("127.0.0.1", server.http_port, timeout=600)
    conn.putrequest("POST", "/v1/clouds?filename=t.ply")
    conn.putheader("Content-Length", str(size))
    conn.endheaders()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            conn.send(block)
    r = conn.getresponse()
    body = json.loads(r.read())
    conn.close()
    assert r.status == 200, body
    return body["id"]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--a", required=True, help="surfel-server binary A (baseline)")
    ap.add_argument("--b", required=True, help="surfel-server binary B")
    ap.add_argument("--points", type=int, default=8_000_000)
    ap.add_argument("--rounds", type=int, default=5)
    a = ap.parse_args()
    work = tempfile.mkdtemp(prefix="ab_http_")
    servers = {}
    try:
        path = os.path.join(work, "t.ply")
        write_torus(path, a.points)
        size = os.path.getsize(path)
        servers = {k: Server(b, os.path.join(work, k), ["--max-upload-mb", str(size // (1 << 20) + 64)])
                   for k, b in [("A", a.a), ("B", a.b)]}
        clients = {"curl": upload_curl, "python": upload_python}
        times = {(k, c): [] for k in servers for c in clients}
        loads = []
        for _ in range(a.rounds):
            for k, server in servers.items():
                for c, fn in clients.items():
                    loads.append(os.getloadavg()[0])
                    t0 = time.monotonic()
                    cloud_id = fn(server, path, size)
                    times[(k, c)].append(time.monotonic() - t0)
                    assert request("DELETE", f"{server.base}/v1/clouds/{cloud_id}").status == 200
        mib = size / (1 << 20)
        print(f"{mib:.1f} MiB, {a.rounds} interleaved rounds, 1-min load {min(loads):.1f}-{max(loads):.1f} "
              f"on {os.cpu_count()} cores; A = {a.a}, B = {a.b}")
        for (k, c), ts in times.items():
            m = statistics.median(ts)
            print(f"{k} {c:7} median {m:.2f} s = {mib / m:.0f} MiB/s  ({' '.join(f'{t:.2f}' for t in ts)})")
    finally:
        for server in servers.values():
            server.stop()
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()

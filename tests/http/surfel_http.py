"""Shared by the HTTP tests: start the real surfel-server with --http on free loopback ports,
plain-urllib requests, and a sampled shape to upload."""
import json
import math
import os
import shutil
import signal
import struct
import subprocess
import time
import urllib.error
import urllib.request


class Server:
    """surfel-server on port 0 (gRPC and HTTP); the ports come back through --*-port-file."""

    def __init__(self, server_bin, work_dir, extra=()):
        shutil.rmtree(work_dir, ignore_errors=True)
        os.makedirs(work_dir)
        self.work_dir = work_dir
        port_file = os.path.join(work_dir, "port")
        http_port_file = os.path.join(work_dir, "http-port")
        self.log = open(os.path.join(work_dir, "server.log"), "w")
        self.proc = subprocess.Popen(
            [server_bin, "--port", "0", "--port-file", port_file, "--data-dir", os.path.join(work_dir, "data"),
             "--http", "127.0.0.1:0", "--http-port-file", http_port_file, "--log-level", "warn", *extra],
            stdout=self.log, stderr=self.log)
        for _ in range(1000):
            if os.path.exists(port_file):
                break
            if self.proc.poll() is not None:
                raise RuntimeError("surfel-server exited during start: " + self.read_log())
            time.sleep(0.01)
        else:
            raise RuntimeError("surfel-server did not start")
        self.http_port = int(open(http_port_file).read())
        self.base = f"http://127.0.0.1:{self.http_port}"

    def read_log(self):
        self.log.flush()
        return open(os.path.join(self.work_dir, "server.log")).read()

    def stop(self, sig=signal.SIGTERM, timeout=20):
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                return self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
                raise AssertionError(f"surfel-server did not stop within {timeout} s of {sig}")
        return self.proc.returncode


class Reply:
    def __init__(self, status, headers, body):
        self.status, self.headers, self.body = status, headers, body

    def json(self):
        return json.loads(self.body)


def request(method, url, body=None, headers=None, timeout=60):
    """One request with urllib; HTTP errors are returned, not raised."""
    req = urllib.request.Request(url, data=body, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return Reply(r.status, r.headers, r.read())
    except urllib.error.HTTPError as e:
        return Reply(e.code, e.headers, e.read())


def post_json(url, obj, **kw):
    return request("POST", url, json.dumps(obj).encode(), {"Content-Type": "application/json"}, **kw)


def sphere_ply(n, binary=False):
    """n points on the unit sphere (Fibonacci lattice), ASCII or binary little-endian PLY."""
    golden = math.pi * (3 - math.sqrt(5))
    pts = []
    for i in range(n):
        z = 1 - 2 * (i + 0.5) / n
        r = math.sqrt(1 - z * z)
        pts.append((r * math.cos(golden * i), r * math.sin(golden * i), z))
    fmt = "binary_little_endian" if binary else "ascii"
    header = (f"ply\nformat {fmt} 1.0\nelement vertex {n}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n").encode()
    if binary:
        return header + b"".join(struct.pack("<fff", *p) for p in pts)
    return header + "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in pts).encode()


def sse_events(response, limit=100):
    """Reads Server-Sent Events from an open response: yields ('comment', text) or (id, json)."""
    data, event_id = [], None
    for raw in response:
        line = raw.decode().rstrip("\r\n")
        if line.startswith(":"):
            yield ("comment", line[1:].strip())
        elif line.startswith("id:"):
            event_id = int(line[3:].strip())
        elif line.startswith("data:"):
            data.append(line[5:].strip())
        elif line == "" and data:
            yield (event_id, json.loads("\n".join(data)))
            data, event_id = [], None
            limit -= 1
            if limit == 0:
                return

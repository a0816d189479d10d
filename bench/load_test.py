#!/usr/bin/python3
"""Load test of a real surfel-server (issue 18, item 7; a bench program, not a CI test).

N concurrent clients (default 200, each with its own gRPC channel, as separate users would) run
for --seconds (default 60), each in a loop picking one action at random:

  upload     a fresh 2,000-point binary PLY (unique bytes: no deduplication), in 64 KiB chunks
  render     a tiny render (32 x 24) of a shared cloud from a random view (unique spec: no reuse)
  simplify   hierarchical simplification of a shared cloud to a random count (unique spec)
  watch      Submit a tiny render, then Watch it to its final event (with the result's bytes)
  cancel     Submit a larger render (256 x 256), Cancel it at once, check it ends CANCELLED
             (or SUCCEEDED when it finished first)
  read       GetJob / GetCloud / ListJobs (cheap metadata calls)

It records every call's latency and status code, samples the server's resident memory every
100 ms, and writes one row per call kind: calls, errors by code, p50 / p99 / max latency.
Passes (exit 0) when no call failed with a code other than RESOURCE_EXHAUSTED (the server's
admission control: a full queue or ingest queue) and the server's RSS stayed under --max-rss-mb.

    /usr/bin/python3 bench/load_test.py --bin build/bin [--clients 200] [--seconds 60] \\
        [--workers 2] [--out bench/results-load.md]

The server runs with its defaults except --workers; start-up and the clients' own CPU share the
machine with it (on the 2-core VM the clients take a good part of a core: say so with figures).
"""
import argparse
import asyncio
import collections
import os
import random
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests", "integration"))
from python_client import generate  # noqa: E402


def sphere_ply_binary(n, rng):
    """A binary little-endian PLY of n jittered points on the unit sphere (unique per call)."""
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\nend_header\n")
    import math
    golden = math.pi * (3 - math.sqrt(5))
    out = bytearray(header.encode())
    jitter = rng.random() * 1e-4
    for i in range(n):
        z = 1 - 2 * (i + 0.5) / n
        r = math.sqrt(max(0.0, 1 - z * z))
        a = golden * i + jitter
        out += struct.pack("<fff", r * math.cos(a), r * math.sin(a), z)
    return bytes(out)


def rss_mb(pid):
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def percentile(values, q):
    if not values:
        return float("nan")
    s = sorted(values)
    k = min(len(s) - 1, max(0, int(round(q * (len(s) - 1)))))
    return s[k]


class Recorder:
    def __init__(self):
        self.lat = collections.defaultdict(list)
        self.codes = collections.defaultdict(collections.Counter)
        self.details = collections.defaultdict(set)

    def add(self, kind, seconds, code, detail=""):
        self.lat[kind].append(seconds)
        self.codes[kind][code] += 1
        if code not in ("OK", "RESOURCE_EXHAUSTED") and len(self.details[kind]) < 5:
            self.details[kind].add(f"{code}: {detail[:200]}")


async def client_loop(idx, addr, pb, rpc, grpc, shared_cloud, deadline, rec, seed):
    rng = random.Random(seed * 1000003 + idx)
    async with grpc.aio.insecure_channel(addr) as channel:
        stub = rpc.SurfelStub(channel)

        async def call(kind, coro_fn):
            t0 = time.perf_counter()
            try:
                result = await coro_fn()
                rec.add(kind, time.perf_counter() - t0, "OK")
                return result
            except grpc.aio.AioRpcError as e:
                rec.add(kind, time.perf_counter() - t0, e.code().name, e.details() or "")
                return None
            except AssertionError as e:
                rec.add(kind, time.perf_counter() - t0, "WRONG_RESULT", str(e))
                return None

        def view():
            return pb.Vec3(x=rng.uniform(-1, 1), y=rng.uniform(-1, 1), z=rng.uniform(0.2, 1))

        async def upload():
            data = sphere_ply_binary(2000, rng)
            uid = f"load-{idx}-{rng.getrandbits(48):x}"

            async def reqs():
                chunk = 64 * 1024
                for off in range(0, len(data), chunk):
                    yield pb.UploadRequest(upload_id=uid, filename="s.ply", write_offset=off,
                                           data=data[off:off + chunk],
                                           finish_write=off + chunk >= len(data))
            cloud = await stub.Upload(reqs())
            assert cloud.points == 2000, f"upload stored {cloud.points} points"
            return cloud

        async def submit(spec):
            return await stub.Submit(pb.SubmitRequest(spec=spec))

        async def watch(job_id):
            final, nbytes = None, 0
            async for ev in stub.Watch(pb.WatchRequest(job_id=job_id, include_result=True)):
                k = ev.WhichOneof("event")
                if k == "finished":
                    final = ("finished", ev.finished.size_bytes)
                elif k == "failed":
                    final = ("failed", ev.failed.code, ev.failed.message)
                elif k == "result_chunk":
                    nbytes += len(ev.result_chunk.data)
            assert final is not None, "watch ended without a final event"
            if final[0] == "failed":
                name = next((c.name for c in grpc.StatusCode if c.value[0] == final[1]), str(final[1]))
                rec.add("job", 0.0, name, final[2])
                return None
            assert nbytes == final[1], f"result {nbytes} bytes, announced {final[1]}"
            rec.add("job", 0.0, "OK")
            return nbytes

        while time.monotonic() < deadline:
            action = rng.choices(["upload", "render", "simplify", "watch", "cancel", "read"],
                                 weights=[2, 3, 2, 3, 1, 3])[0]
            if action == "upload":
                await call("Upload", upload)
            elif action == "render":
                spec = pb.JobSpec(render=pb.RenderJob(cloud_id=shared_cloud, width=32, height=24,
                                                      view=view(), format=pb.RenderJob.PNG))
                await call("Submit(render)", lambda: submit(spec))
            elif action == "simplify":
                spec = pb.JobSpec(simplify=pb.SimplifyJob(cloud_id=shared_cloud,
                                                          target=rng.randint(200, 2000),
                                                          no_error_report=True))
                await call("Submit(simplify)", lambda: submit(spec))
            elif action == "watch":
                spec = pb.JobSpec(render=pb.RenderJob(cloud_id=shared_cloud, width=32, height=24,
                                                      view=view(), format=pb.RenderJob.PNG))
                job = await call("Submit(render)", lambda: submit(spec))
                if job is not None:
                    await call("Watch", lambda: watch(job.id))
            elif action == "cancel":
                spec = pb.JobSpec(render=pb.RenderJob(cloud_id=shared_cloud, width=256, height=256,
                                                      view=view()))
                job = await call("Submit(render)", lambda: submit(spec))
                if job is not None:
                    got = await call("Cancel", lambda: stub.Cancel(pb.CancelRequest(job_id=job.id)))
                    if got is not None:
                        async def settled():
                            for _ in range(600):
                                j = await stub.GetJob(pb.GetJobRequest(job_id=job.id))
                                if j.state in (pb.CANCELLED, pb.SUCCEEDED):
                                    return j
                                assert j.state != pb.FAILED, f"cancelled job FAILED: {j.status_message}"
                                await asyncio.sleep(0.05)
                            raise AssertionError("cancelled job still not final after 30 s")
                        await call("GetJob(after cancel)", settled)
            else:
                which = rng.randrange(3)
                if which == 0:
                    await call("GetCloud", lambda: stub.GetCloud(pb.GetCloudRequest(cloud_id=shared_cloud)))
                elif which == 1:
                    await call("ListJobs", lambda: stub.ListJobs(pb.ListJobsRequest(limit=20)))
                else:
                    async def one():
                        jobs = (await stub.ListJobs(pb.ListJobsRequest(limit=1))).jobs
                        if jobs:
                            await stub.GetJob(pb.GetJobRequest(job_id=jobs[0].id))
                    await call("GetJob", one)


async def run(a, pb, rpc, grpc, addr, server_pid):
    # One shared cloud for the jobs, uploaded before the clock starts.
    async with grpc.aio.insecure_channel(addr) as channel:
        stub = rpc.SurfelStub(channel)
        data = sphere_ply_binary(5000, random.Random(a.seed))

        async def reqs():
            yield pb.UploadRequest(upload_id="load-shared", filename="shared.ply", write_offset=0,
                                   data=data, finish_write=True)
        shared = (await stub.Upload(reqs())).id

    rec = Recorder()
    rss = []
    stop = asyncio.Event()

    async def sample():
        while not stop.is_set():
            rss.append(rss_mb(server_pid))
            await asyncio.sleep(0.1)

    sampler = asyncio.create_task(sample())
    t0 = time.monotonic()
    deadline = t0 + a.seconds
    await asyncio.gather(*[client_loop(i, addr, pb, rpc, grpc, shared, deadline, rec, a.seed)
                           for i in range(a.clients)])
    wall = time.monotonic() - t0
    stop.set()
    await sampler
    return rec, rss, wall


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin", default="build/bin", help="directory with surfel-server")
    ap.add_argument("--clients", type=int, default=200)
    ap.add_argument("--seconds", type=float, default=60)
    ap.add_argument("--workers", type=int, default=2, help="the server's --workers")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--max-rss-mb", type=float, default=1024)
    ap.add_argument("--out", default="", help="write the table (markdown) here too")
    a = ap.parse_args()

    work = tempfile.mkdtemp(prefix="surfel-load-")
    root = os.path.join(HERE, "..")
    generate(os.path.join(root, "proto"), os.path.join(work, "gen"))
    import grpc
    import grpc.aio  # noqa: F401
    from surfel.v1 import surfel_pb2 as pb, surfel_pb2_grpc as rpc

    port_file = os.path.join(work, "port")
    server = subprocess.Popen([os.path.join(a.bin, "surfel-server"), "--port", "0",
                               "--data-dir", os.path.join(work, "data"), "--port-file", port_file,
                               "--workers", str(a.workers), "--log-level", "error"])
    try:
        for _ in range(1000):
            if os.path.exists(port_file) and open(port_file).read().strip():
                break
            time.sleep(0.01)
        addr = f"127.0.0.1:{int(open(port_file).read())}"
        cpu0 = os.times()
        rec, rss, wall = asyncio.run(run(a, pb, rpc, grpc, addr, server.pid))
        cpu1 = os.times()
        alive = server.poll() is None
        server.send_signal(signal.SIGTERM)
        rc = server.wait(timeout=60)
    finally:
        if server.poll() is None:
            server.kill()
        shutil.rmtree(work, ignore_errors=True)

    client_cpu = (cpu1.user - cpu0.user) + (cpu1.system - cpu0.system)
    lines = [f"{a.clients} clients, {wall:.1f} s, server --workers {a.workers}; "
             f"server RSS max {max(rss):.0f} MiB (median {percentile(rss, 0.5):.0f} MiB); "
             f"the load generator's own CPU {client_cpu:.1f} s ({client_cpu / wall:.2f} cores); "
             f"server alive at the end: {alive}, exit on SIGTERM {rc}", "",
             "| call | calls | per s | errors (other than RESOURCE_EXHAUSTED) | RESOURCE_EXHAUSTED | p50 ms | p99 ms | max ms |",
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    bad_total = 0
    for kind in sorted(rec.lat):
        codes = rec.codes[kind]
        n = sum(codes.values())
        bad = n - codes["OK"] - codes["RESOURCE_EXHAUSTED"]
        bad_total += bad
        lat = [x * 1000 for x in rec.lat[kind]] if kind != "job" else []
        p50 = f"{percentile(lat, 0.5):.1f}" if lat else "–"
        p99 = f"{percentile(lat, 0.99):.1f}" if lat else "–"
        mx = f"{max(lat):.1f}" if lat else "–"
        label = kind if kind != "job" else "job outcome (watched)"
        lines.append(f"| {label} | {n} | {n / wall:.1f} | {bad} | {codes['RESOURCE_EXHAUSTED']} | {p50} | {p99} | {mx} |")
    for kind, ds in rec.details.items():
        for d in sorted(ds):
            lines.append(f"- {kind}: {d}")
    text = "\n".join(lines)
    print(text)
    if a.out:
        with open(a.out, "a") as f:
            f.write(f"\n### {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}: "
                    f"`bench/load_test.py --clients {a.clients} --seconds {a.seconds:g} --workers {a.workers}`\n\n")
            f.write(text + "\n")
    ok = bad_total == 0 and max(rss) <= a.max_rss_mb and alive and rc == 0
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())

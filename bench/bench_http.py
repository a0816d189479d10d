#!/usr/bin/python3
"""Upload throughput of the HTTP front against the gRPC upload, on one real surfel-server and one
file; optionally the page's Render click -> image time for the bunny (tests/http/test_page_chromium.py).

Clients, each run once per round, the rounds interleaved (so a noisy stretch of a shared machine
falls on every client alike), medians reported:
  http-curl     curl -T FILE -X POST  /v1/clouds        (C, streams the file, Content-Length)
  http-python   http.client, 1 MiB writes                (Python, Content-Length)
  grpc-surfel   surfel upload FILE --server              (the C++ client: SHA-256 of the file first,
                                                          then 256 KiB chunks; its hash is included;
                                                          timed by its own report's time_ms, as the
                                                          process' start and exit cost ~1 s more)
  grpc-python   grpcio Upload stream, 256 KiB chunks     (Python, Debian's python3-grpcio)
  nginx-h2-curl curl --http2 over TLS through deploy/nginx/surfel.conf   (with --nginx)
Every upload is end to end: bytes sent, hashed and written by the server, parsed, validated and
stored, the Cloud answered (the server-side work is the same for all four). The cloud is deleted
after each upload so the next one is not deduplicated (`surfel upload` would otherwise send
nothing).

  /usr/bin/python3 bench/bench_http.py --bin build/bin [--points 8000000] [--rounds 5] \\
      [--page] [--out bench/results-http.md]
"""
import argparse
import datetime
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
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "tests", "http"))
sys.path.insert(0, os.path.join(ROOT, "tests", "integration"))
from surfel_http import Server, request  # noqa: E402


def write_torus(path, n, seed=1):
    """n points on a torus with normals, binary little-endian PLY (numpy)."""
    import numpy as np
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 2 * np.pi, n)
    R, r = 1.0, 0.35
    p = np.stack([(R + r * np.cos(v)) * np.cos(u), (R + r * np.cos(v)) * np.sin(u), r * np.sin(v)], 1)
    nrm = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], 1)
    data = np.concatenate([p, nrm], 1).astype("<f4")
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property float nx\nproperty float ny\nproperty float nz\nend_header\n").encode()
    with open(path, "wb") as f:
        f.write(header)
        f.write(data.tobytes())


MARKS = {}  # "sent": when a Python client handed over its last byte


def run_rounds(rounds, clients, times, loads, server, walls, sending):
    for rnd in range(rounds):
        for name, fn in clients.items():
            loads.append(os.getloadavg()[0])
            MARKS.clear()
            t0 = time.monotonic()
            cloud_id = fn()
            wall = time.monotonic() - t0
            if isinstance(cloud_id, tuple):  # (id, the client's own time of the upload)
                cloud_id, own = cloud_id
                walls.append(wall)
                wall = own
            times[name].append(wall)
            if "sent" in MARKS:
                sending.setdefault(name, []).append((MARKS["sent"] - t0, wall))
            r = request("DELETE", f"{server.base}/v1/clouds/{cloud_id}")
            assert r.status == 200, (r.status, r.body)
        print(f"round {rnd + 1}: " + ", ".join(f"{k} {v[-1]:.2f} s" for k, v in times.items()), flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bin", default=os.path.join(ROOT, "build", "bin"))
    ap.add_argument("--file", help="PLY/XYZ to upload (default: a generated torus of --points)")
    ap.add_argument("--points", type=int, default=8_000_000)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--page", action="store_true", help="also time Render click -> image in Chromium")
    ap.add_argument("--page-rounds", type=int, default=5)
    ap.add_argument("--nginx", action="store_true", help="also upload through deploy/nginx/surfel.conf (HTTP/2, TLS)")
    ap.add_argument("--out", help="write the results as Markdown here")
    a = ap.parse_args()

    work = tempfile.mkdtemp(prefix="bench_http_")
    try:
        path = a.file or os.path.join(work, "torus.ply")
        if not a.file:
            write_torus(path, a.points)
        size = os.path.getsize(path)
        mib = size / (1 << 20)
        server = Server(os.path.join(a.bin, "surfel-server"), os.path.join(work, "srv"),
                        ["--max-upload-mb", str(int(mib) + 64)])
        grpc_port = int(open(os.path.join(work, "srv", "port")).read())
        target = f"127.0.0.1:{grpc_port}"

        import python_client  # noqa: E402  (generates the grpcio stubs from proto/)
        python_client.generate(os.path.join(ROOT, "proto"), os.path.join(work, "gen"))
        import grpc
        from surfel.v1 import surfel_pb2 as pb, surfel_pb2_grpc as rpc
        stub = rpc.SurfelStub(grpc.insecure_channel(target, options=[("grpc.max_send_message_length", 8 << 20)]))

        def http_curl():
            out = subprocess.run(["curl", "-sS", "--fail-with-body", "-H", "Expect:", "-X", "POST", "-T", path,
                                  f"{server.base}/v1/clouds?filename=torus.ply"], capture_output=True, check=True)
            return json.loads(out.stdout)["id"]

        def http_python():
            conn = http.client.HTTPConnection("127.0.0.1", server.http_port, timeout=600)
            conn.putrequest("POST", "/v1/clouds?filename=torus.ply")
            conn.putheader("Content-Length", str(size))
            conn.endheaders()
            with open(path, "rb") as f:
                while block := f.read(1 << 20):
                    conn.send(block)
            MARKS["sent"] = time.monotonic()
            r = conn.getresponse()
            body = json.loads(r.read())
            assert r.status == 200, body
            conn.close()
            return body["id"]

        def grpc_surfel():
            out = subprocess.run([os.path.join(a.bin, "surfel"), "upload", path, "--server", target, "--json",
                                  "--quiet"], capture_output=True, check=True)
            report = json.loads(out.stdout)
            return report["cloud_id"], report["time_ms"] / 1000

        seq = [0]

        def grpc_python(chunk=256 << 10):
            seq[0] += 1

            def requests():
                with open(path, "rb") as f:
                    off = 0
                    while True:
                        data = f.read(chunk)
                        yield pb.UploadRequest(upload_id=f"bench-{seq[0]}", filename="torus.ply", write_offset=off,
                                               data=data, finish_write=off + len(data) >= size)
                        off += len(data)
                        if off >= size:
                            MARKS["sent"] = time.monotonic()  # gRPC asked for more: the last chunk is out
                            return
            return stub.Upload(requests()).id

        clients = {"http-curl": http_curl, "http-python": http_python,
                   "grpc-surfel": grpc_surfel, "grpc-python": grpc_python}
        nginx = None
        if a.nginx:
            import test_nginx  # renders the shipped site file with free ports into a temp prefix
            prefix = os.path.join(work, "nginx")
            os.makedirs(prefix)
            subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256",
                            "-nodes", "-days", "2", "-subj", "/CN=localhost", "-keyout", f"{prefix}/key.pem",
                            "-out", f"{prefix}/cert.pem"], check=True, capture_output=True)
            https_port = test_nginx.free_port()
            conf = test_nginx.render_config(os.path.join(ROOT, "deploy", "nginx", "surfel.conf"), prefix,
                                            server.http_port, test_nginx.free_port(), https_port)
            nginx = subprocess.Popen(test_nginx.nginx_cmd(prefix, conf, "-g", "daemon off;"))
            time.sleep(1)

            def nginx_h2_curl():
                out = subprocess.run(["curl", "-sS", "-k", "--http2", "--fail-with-body", "-X", "POST", "-T", path,
                                      f"https://127.0.0.1:{https_port}/v1/clouds?filename=torus.ply"],
                                     capture_output=True, check=True)
                return json.loads(out.stdout)["id"]
            clients["nginx-h2-curl"] = nginx_h2_curl
        times = {k: [] for k in clients}
        loads, walls, sending = [], [], {}
        try:
            run_rounds(a.rounds, clients, times, loads, server, walls, sending)
        finally:
            server.stop()
            if nginx:
                nginx.terminate()
                nginx.wait()

        date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
        lines = [f"## Upload, {date}", "",
                 f"{os.path.basename(path)}: {mib:.1f} MiB binary PLY; {a.rounds} interleaved rounds, median "
                 f"(min–max); 1-min load average during the runs {min(loads):.1f}–{max(loads):.1f} on "
                 f"{os.cpu_count()} cores. End to end: sent, hashed, parsed, stored, answered.", "",
                 "| client | path | median | MiB/s | range |", "|---|---|---:|---:|---|"]
        for name, ts in times.items():
            med = statistics.median(ts)
            route = {"http": "HTTP POST /v1/clouds", "grpc": "gRPC Upload",
                     "nginx": "HTTPS + HTTP/2 via nginx, POST /v1/clouds"}[name.split("-")[0]]
            lines.append(f"| {name} | {route} | "
                         f"{med:.2f} s | {mib / med:.0f} | {min(ts):.2f}–{max(ts):.2f} s |")
        lines += ["", f"grpc-surfel is the CLI's own `time_ms` (its SHA-256 of the file, the upload, the server's "
                  f"work); the whole `surfel upload` process took {statistics.median(walls):.2f} s (median), "
                  "the rest being the process' start and exit.", "",
                  "Split of the Python clients' time at their last byte handed over (for gRPC: when the stream "
                  "asked for the next message after the last), medians:", "",
                  "| client | sending | MiB/s while sending | after the last byte (server: hash end, parse, store) |",
                  "|---|---:|---:|---:|"]
        for name, pairs in sending.items():
            sent = statistics.median(p[0] for p in pairs)
            after = statistics.median(p[1] - p[0] for p in pairs)
            lines.append(f"| {name} | {sent:.2f} s | {mib / sent:.0f} | {after:.2f} s |")
        lines.append("")

        if a.page:
            bunny = os.path.join(ROOT, "..", "shared", "data", "bunny.ply")
            page_json = os.path.join(work, "page.json")
            subprocess.run(["/usr/bin/python3", os.path.join(ROOT, "tests", "http", "test_page_chromium.py"),
                            "--server-bin", os.path.join(a.bin, "surfel-server"), "--work-dir",
                            os.path.join(work, "page"), "--bunny", bunny, "--bunny-rounds", str(a.page_rounds),
                            "--bench-out", page_json], check=True)
            p = json.load(open(page_json))
            lines += [f"## Render click -> image in the page, {p['date']}", "",
                      f"{p['what']} ({p['points']} points), headless Chromium (tests/http/test_page_chromium.py), "
                      f"browser clock; 1-min load {p['load_1min']:.1f} on {p['cores']} cores.", "",
                      f"median **{p['median_ms']} ms** over {len(p['rounds_ms'])} rounds: {p['rounds_ms']} ms; "
                      f"of which the render job itself (created -> finished on the server) median "
                      f"{p['job_median_ms']} ms: {p['job_rounds_ms']} ms. The rest is the page's submit, "
                      "the event stream's last event, and fetching and decoding the PNG.", ""]
        text = "\n".join(lines)
        print(text)
        if a.out:
            with open(a.out, "w") as f:
                f.write("# HTTP front benchmarks (bench/bench_http.py; see bench/README.md)\n\n"
                        f"Command: `/usr/bin/python3 bench/bench_http.py {' '.join(sys.argv[1:])}`\n\n" + text)
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()

#!/usr/bin/python3
"""deploy/nginx/surfel.conf in front of a real surfel-server: the site file is rendered with free
loopback ports, a self-signed certificate and the test's upstream into a temporary nginx prefix,
checked with `nginx -t`, and run (`-g 'daemon off;'`). Then, through nginx: the page and three.js
over HTTP/2; an upload whose body reaches the server while it is still being sent
(proxy_request_buffering off); a job whose event stream arrives unbuffered over HTTP/2 (a
progress event while the job is still running); eight event streams multiplexed on one HTTP/2
connection; Range requests answered 206 with the server's bytes; the HTTP listener's redirect;
nginx's own failures (body over client_max_body_size, no server behind) as google.rpc.Status
JSON."""
import argparse
import http.client
import json
import os
import re
import shutil
import socket
import ssl
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from surfel_http import Server, post_json, request, sphere_ply  # noqa: E402

NGINX = "/usr/sbin/nginx"
CURL = "/usr/bin/curl"


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def substitute(text, old, new):
    """Replaces a line of the shipped config that the test must change; fails loudly if the
    config no longer has it (so a changed config cannot silently skip the test's rendering)."""
    count = text.count(old)
    assert count >= 1, f"deploy/nginx/surfel.conf has no {old!r} any more"
    return text.replace(old, new)


def render_config(site_conf, prefix, upstream_port, http_port, https_port):
    """The site file with the test's ports, certificate and upstream, inside a main config whose
    every path (pid, logs, temp dirs) lies in PREFIX."""
    text = open(site_conf).read()
    text = substitute(text, "server 127.0.0.1:8080;", f"server 127.0.0.1:{upstream_port};")
    text = substitute(text, "listen 80;", f"listen 127.0.0.1:{http_port};")
    text = substitute(text, "listen 443 ssl http2;", f"listen 127.0.0.1:{https_port} ssl http2;")
    text = re.sub(r"\n\s*listen \[::\]:\d+[^;]*;", "", text)  # no IPv6 listeners in the test
    text = substitute(text, "/etc/ssl/certs/surfel.example.org.pem", os.path.join(prefix, "cert.pem"))
    text = substitute(text, "/etc/ssl/private/surfel.example.org.key", os.path.join(prefix, "key.pem"))
    open(os.path.join(prefix, "surfel.conf"), "w").write(text)
    temp = "\n".join(f"    {kind}_temp_path {os.path.join(prefix, kind)};"
                     for kind in ["client_body", "proxy", "fastcgi", "uwsgi", "scgi"])
    main = f"""# rendered by tests/http/test_nginx.py
{"user root;" if os.geteuid() == 0 else ""}
worker_processes 1;
pid {prefix}/nginx.pid;
error_log {prefix}/error.log info;
events {{ worker_connections 512; }}
http {{
    access_log {prefix}/access.log;
{temp}
    include {prefix}/surfel.conf;
}}
"""
    path = os.path.join(prefix, "nginx.conf")
    open(path, "w").write(main)
    return path


def nginx_cmd(prefix, conf, *extra):
    return [NGINX, "-p", prefix + "/", "-e", os.path.join(prefix, "error.log"), "-c", conf, *extra]


def curl(*args, timeout=60):
    out = subprocess.run([CURL, "-sS", "-k", *args], capture_output=True, timeout=timeout)
    assert out.returncode == 0, (args, out.returncode, out.stderr.decode())
    return out.stdout


def tls_connection(port, timeout=60):
    """HTTP/1.1 over TLS to nginx (http.client offers no ALPN, so nginx speaks HTTP/1.1)."""
    ctx = ssl.create_default_context()
    ctx.check_hostname = False
    ctx.verify_mode = ssl.CERT_NONE
    return http.client.HTTPSConnection("127.0.0.1", port, context=ctx, timeout=timeout)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--server-bin", required=True)
    ap.add_argument("--work-dir", required=True)
    ap.add_argument("--site-conf", required=True)
    a = ap.parse_args()
    t0 = time.monotonic()
    server = Server(a.server_bin, a.work_dir, ["--workers", "1", "--grace", "0"])
    prefix = os.path.join(a.work_dir, "nginx")
    os.makedirs(prefix)
    nginx = None
    try:
        subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256",
                        "-nodes", "-days", "2", "-subj", "/CN=localhost",
                        "-keyout", os.path.join(prefix, "key.pem"), "-out", os.path.join(prefix, "cert.pem")],
                       check=True, capture_output=True)
        http_port, https_port = free_port(), free_port()
        conf = render_config(a.site_conf, prefix, server.http_port, http_port, https_port)

        # nginx -t on the rendered config.
        t = subprocess.run(nginx_cmd(prefix, conf, "-t"), capture_output=True, text=True)
        assert t.returncode == 0 and "test is successful" in t.stderr, t.stderr
        print("ok  nginx -t:", t.stderr.strip().splitlines()[-1])

        nginx = subprocess.Popen(nginx_cmd(prefix, conf, "-g", "daemon off;"),
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        base = f"https://127.0.0.1:{https_port}"
        for _ in range(200):
            if nginx.poll() is not None:
                raise AssertionError("nginx exited: " + nginx.stdout.read().decode())
            try:
                socket.create_connection(("127.0.0.1", https_port), 0.2).close()
                break
            except OSError:
                time.sleep(0.05)

        # The page and three.js, over HTTP/2.
        out = curl("--http2", "-o", "/dev/null", "-w", "%{http_version} %{http_code} %{content_type}", base + "/")
        assert out.decode().startswith("2 200 text/html"), out
        three = curl("--http2", base + "/three/build/three.module.js")
        assert len(three) > 100000, len(three)
        print("ok  page over HTTP/2 through nginx")

        # Upload: the body reaches the server while it is still being sent. The server's front
        # writes the part file in 256 KiB blocks, so the first half (~1.2 MB) of a 2.4 MB body
        # must put at least one block there before the second half is sent.
        ply = sphere_ply(200000, binary=True)
        half = len(ply) // 2
        block = 256 * 1024
        uploads = os.path.join(a.work_dir, "data", "uploads")
        conn = tls_connection(https_port)
        conn.putrequest("POST", "/v1/clouds?filename=sphere.ply")
        conn.putheader("Content-Length", str(len(ply)))
        conn.endheaders()
        conn.send(ply[:half])

        def arrived():
            if not os.path.isdir(uploads):
                return 0
            return sum(os.path.getsize(os.path.join(uploads, f)) for f in os.listdir(uploads))
        deadline = time.monotonic() + 20
        while arrived() < half - block and time.monotonic() < deadline:
            time.sleep(0.02)
        early = arrived()
        assert early >= half - block, f"only {early} of the first {half} bytes reached the server: request buffered?"
        conn.send(ply[half:])
        reply = conn.getresponse()
        cloud = json.loads(reply.read())
        assert reply.status == 200 and cloud["points"] == "200000", (reply.status, cloud)
        conn.close()
        print(f"ok  upload streamed through nginx: {early} of {len(ply)} bytes at the server before the second "
              f"half was sent")

        # A job: its events arrive through nginx, over HTTP/2, while it runs.
        direct = server.base
        job = post_json(direct + "/v1/jobs", {"render": {
            "cloudId": cloud["id"], "width": 1536, "height": 1536, "samplesPerPixel": 8}}).json()
        stream = subprocess.Popen([CURL, "-sS", "-k", "-N", "--http2", f"{base}/v1/jobs/{job['id']}/events"],
                                  stdout=subprocess.PIPE)
        state_at_progress, events = None, []
        for raw in stream.stdout:
            line = raw.decode().strip()
            if not line.startswith("data:"):
                continue
            event = json.loads(line[5:])
            events.append(event)
            if "running" in event and state_at_progress is None:
                state_at_progress = request("GET", f"{direct}/v1/jobs/{job['id']}").json()["state"]
                request("POST", f"{direct}/v1/jobs/{job['id']}:cancel")
            if "finished" in event or "failed" in event:
                break
        stream.wait(20)
        assert state_at_progress == "RUNNING", (state_at_progress, events[:3])
        assert "failed" in events[-1] and events[-1]["failed"]["code"] == 1, events[-1]
        print(f"ok  event stream unbuffered over HTTP/2: progress seen while the job was {state_at_progress}, "
              f"{len(events)} events, ends cancelled")

        # A small job to the end; eight event streams of it on one HTTP/2 connection.
        small = post_json(direct + "/v1/jobs", {"render": {
            "cloudId": cloud["id"], "width": 64, "height": 48, "format": "PNG"}}).json()
        url = f"{base}/v1/jobs/{small['id']}/events"
        out = curl("--http2", "--parallel", "--parallel-max", "8", "-w", "\n@@%{http_version} %{num_connects}\n",
                   *([url] * 8), timeout=60).decode()
        tails = re.findall(r"@@(\S+) (\d+)", out)
        assert len(tails) == 8 and all(v == "2" for v, _ in tails), tails
        assert sum(int(n) for _, n in tails) == 1, f"connections opened: {tails}"
        assert out.count('"finished"') == 8, out[-500:]
        print("ok  8 event streams multiplexed on one HTTP/2 connection")

        # Range: the server's 206 with its bytes, through nginx.
        whole = request("GET", f"{direct}/v1/jobs/{small['id']}/result").body
        conn = tls_connection(https_port)
        conn.request("GET", f"/v1/jobs/{small['id']}/result", headers={"Range": "bytes=10-109"})
        r = conn.getresponse()
        part = r.read()
        assert r.status == 206 and part == whole[10:110], (r.status, len(part))
        assert r.getheader("Content-Range") == f"bytes 10-109/{len(whole)}", r.getheader("Content-Range")
        assert r.getheader("Content-Type") == "image/png", r.getheader("Content-Type")
        conn.request("GET", f"/v1/jobs/{small['id']}/result", headers={"Range": f"bytes={len(whole) + 5}-"})
        r = conn.getresponse()
        body = json.loads(r.read())
        assert r.status == 416 and body["code"] == 11, (r.status, body)
        conn.close()
        suffix = curl("--http2", "-H", "Range: bytes=-16", base + f"/v1/jobs/{small['id']}/result")
        assert suffix == whole[-16:], suffix
        print(f"ok  Range through nginx: 206 bytes 10-109/{len(whole)}, suffix, 416")

        # The plain-HTTP listener redirects to HTTPS.
        out = curl("-o", "/dev/null", "-w", "%{http_code} %{redirect_url}", f"http://127.0.0.1:{http_port}/v1/jobs")
        assert out.decode().startswith("301 https://127.0.0.1/v1/jobs"), out

        # nginx's own failures, shaped like the server's errors.
        conn = tls_connection(https_port)
        conn.putrequest("POST", "/v1/clouds?filename=huge.ply")
        conn.putheader("Content-Length", str(3 << 30))
        conn.endheaders()
        r = conn.getresponse()
        body = json.loads(r.read())
        assert r.status == 429 and body["code"] == 8 and "client_max_body_size" in body["message"], (r.status, body)
        conn.close()
        assert server.stop() == 0
        r = tls_connection(https_port)
        r.request("GET", "/v1/jobs")
        reply = r.getresponse()
        body = json.loads(reply.read())
        assert reply.status == 503 and body["code"] == 14, (reply.status, body)
        print("ok  proxy errors as google.rpc.Status: 429 over client_max_body_size, 503 with no server")
    except BaseException:
        print("server log:\n" + server.read_log())
        log = os.path.join(prefix, "error.log")
        if os.path.exists(log):
            print("nginx error.log:\n" + open(log).read()[-4000:])
        raise
    finally:
        if nginx:
            subprocess.run(nginx_cmd(prefix, os.path.join(prefix, "nginx.conf"), "-s", "quit"), capture_output=True)
            try:
                nginx.wait(10)
            except subprocess.TimeoutExpired:
                nginx.kill()
                nginx.wait()
        server.stop()
    shutil.rmtree(prefix, ignore_errors=True)
    print(f"nginx test passed ({time.monotonic() - t0:.1f} s)")


if __name__ == "__main__":
    main()

#!/usr/bin/python3
"""The HTTP/JSON API of the real surfel-server, driven with a plain client (urllib): every route,
every error status (400 naming the field, 404, 429, 416), google.rpc.Status-shaped error bodies,
CORS (preflight included), Server-Sent Events (order, ids, Last-Event-ID resumption, keep-alive
comments), the result with Content-Type, Content-Disposition and Range, and a clean SIGTERM with an
event stream open."""
import argparse
import json
import os
import re
import signal
import socket
import sys
import threading
import time
import urllib.request

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from surfel_http import Server, post_json, request, sphere_ply, sse_events  # noqa: E402

ALLOWED = "http://page.example"
STEPS = []


def step(fn):
    STEPS.append(fn)
    return fn


def expect_status(reply, http_status, grpc_code, *words):
    """An error reply: the HTTP status, a google.rpc.Status body with the gRPC code, words named."""
    assert reply.status == http_status, (reply.status, reply.body[:300])
    assert reply.headers.get("Content-Type", "").startswith("application/json"), reply.headers
    body = reply.json()
    assert set(body) == {"code", "message", "details"}, body
    assert body["code"] == grpc_code, body
    assert body["details"] == [], body
    for w in words:
        assert w in body["message"], (w, body["message"])
    return body


class Ctx:
    pass


@step
def static_page(c):
    r = request("GET", c.base + "/")
    assert r.status == 200 and r.headers["Content-Type"].startswith("text/html"), (r.status, r.headers)
    assert b"Surfel" in r.body
    r = request("GET", c.base + "/app.js")
    assert r.status == 200 and "javascript" in r.headers["Content-Type"], r.headers
    r = request("GET", c.base + "/three/build/three.module.js")
    assert r.status == 200 and len(r.body) > 100000, (r.status, len(r.body))
    r = request("GET", c.base + "/three/examples/jsm/controls/OrbitControls.js")
    assert r.status == 200, r.status
    expect_status(request("GET", c.base + "/no/such/route"), 404, 5, "no such route")


@step
def upload_with_length(c):
    r = request("POST", c.base + "/v1/clouds?filename=sphere.ply", c.ply, {"Content-Type": "application/octet-stream"})
    assert r.status == 200, (r.status, r.body)
    cloud = r.json()
    assert re.fullmatch(r"[0-9a-f]{64}", cloud["id"]), cloud
    assert cloud["points"] == str(c.n), cloud  # uint64 is a string in proto3 JSON
    assert cloud["format"] == "ply-ascii", cloud
    assert cloud["deduplicated"] is False, cloud
    for axis in "xyz":
        assert abs(cloud["boundsMin"][axis] + 1) < 0.01 and abs(cloud["boundsMax"][axis] - 1) < 0.01, cloud
    c.cloud = cloud


@step
def upload_chunked_dedupes(c):
    def chunks():
        for i in range(0, len(c.ply), 4096):
            yield c.ply[i:i + 4096]
    req = urllib.request.Request(c.base + "/v1/clouds?filename=sphere.ply", data=chunks(), method="POST")
    with urllib.request.urlopen(req, timeout=60) as r:  # no Content-Length: chunked transfer coding
        cloud = json.loads(r.read())
    assert cloud["id"] == c.cloud["id"] and cloud["deduplicated"] is True, cloud


@step
def get_cloud(c):
    r = request("GET", f"{c.base}/v1/clouds/{c.cloud['id']}")
    assert r.status == 200 and r.json()["id"] == c.cloud["id"] and r.json()["points"] == str(c.n), r.body
    expect_status(request("GET", c.base + "/v1/clouds/feedbeef"), 404, 5, "cloud feedbeef not found")


@step
def malformed_upload(c):
    bad = b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n" \
          b"end_header\n0 0 0\n1 1\n"
    body = expect_status(request("POST", c.base + "/v1/clouds?filename=bad.ply", bad), 400, 3)
    assert "bad.ply" in body["message"] or "line" in body["message"], body
    c.malformed_message = body["message"]
    expect_status(request("POST", c.base + "/v1/clouds?filename=empty.xyz", b""), 400, 3)


@step
def upload_limits(c):
    big = b"0 0 0\n" * (c.max_upload // 6 + 100)  # over --max-upload-mb, refused from its Content-Length
    expect_status(request("POST", c.base + "/v1/clouds?filename=big.xyz", big), 429, 8, "exceeds the limit")

    def chunks():  # over the limit without a Content-Length: refused while streaming
        for _ in range(0, len(big), 8192):
            yield b"0 0 0\n" * 1365
    req = urllib.request.Request(c.base + "/v1/clouds?filename=big.xyz", data=chunks(), method="POST")
    try:
        urllib.request.urlopen(req, timeout=60)
        raise AssertionError("an upload over the limit was accepted")
    except urllib.error.HTTPError as e:
        assert e.code == 429, e.code
    except (ConnectionError, urllib.error.URLError):
        pass  # the server answered 429 and closed while the client was still sending
    many = sphere_ply(c.max_points + 500, binary=True)
    assert len(many) < c.max_upload
    expect_status(request("POST", c.base + "/v1/clouds?filename=many.ply", many), 429, 8)
    # Nothing of the refused uploads is left behind.
    uploads = os.path.join(c.server.work_dir, "data", "uploads")
    if os.path.isdir(uploads):
        assert os.listdir(uploads) == [], os.listdir(uploads)


@step
def upload_inflight_counts_the_gathered_block(c):
    # The bytes an upload has read and gathers in memory (up to 256 KiB before they go to the part
    # file) count in --max-upload-inflight-mb from the moment they are read, and are released
    # when the upload ends early. Beside 200 KiB held so, 100 KiB more pass the cap of 256 KiB:
    # whichever of the two the server reads first, the other is refused 429 naming the flag.
    s = Server(c.server_bin, c.work_dir + "-inflight", ["--max-upload-inflight-mb", "0.25"])
    try:
        held = socket.create_connection(("127.0.0.1", s.http_port))
        held.sendall(b"POST /v1/clouds?filename=held.xyz HTTP/1.1\r\nHost: x\r\n"
                     b"Content-Length: 307200\r\n\r\n" + b"0 0 0\n" * (200 * 1024 // 6))
        probe = sphere_ply(3500)
        assert 60 * 1024 < len(probe) < 200 * 1024, len(probe)
        r = request("POST", s.base + "/v1/clouds?filename=probe.ply", probe)
        if r.status == 429:
            expect_status(r, 429, 8, "--max-upload-inflight-mb")
        else:  # the probe was read first: the held upload is refused when it reads past the cap
            assert r.status == 200, (r.status, r.body)
            held.settimeout(10)
            answer = b""
            try:
                while chunk := held.recv(65536):
                    answer += chunk
            except socket.timeout:
                raise AssertionError("an upload was taken beside 200 KiB held in memory and not "
                                     "counted, and the held one was not refused either: " + repr(answer))
            assert answer.startswith(b"HTTP/1.1 429") and b"--max-upload-inflight-mb" in answer, answer
        held.close()  # the held upload ends early: its bytes are no longer in flight
        deadline = time.monotonic() + 10
        while True:
            r = request("POST", s.base + "/v1/clouds?filename=probe.ply", probe)
            if r.status == 200:
                break
            assert r.status == 429 and time.monotonic() < deadline, (r.status, r.body)
            time.sleep(0.02)
    finally:
        s.stop(signal.SIGKILL)


@step
def submit_errors(c):
    cid = c.cloud["id"]
    expect_status(post_json(c.base + "/v1/jobs", {"render": {"cloudId": cid, "bogusField": 1}}), 400, 3, "bogusField")
    expect_status(post_json(c.base + "/v1/jobs", {"render": {"cloudId": cid, "width": 99999}}), 400, 3, "render.width")
    expect_status(post_json(c.base + "/v1/jobs", {"render": {"cloudId": "nope"}}), 404, 5, "nope")
    expect_status(request("POST", c.base + "/v1/jobs", b"{not json", {"Content-Type": "application/json"}), 400, 3,
                  "JobSpec")
    expect_status(request("POST", c.base + "/v1/jobs", b""), 400, 3, "empty")
    expect_status(post_json(c.base + "/v1/jobs", {}), 400, 3)


@step
def render_and_events(c):
    spec = {"render": {"cloudId": c.cloud["id"], "width": 48, "height": 32, "format": "PNG"}}
    r = post_json(c.base + "/v1/jobs", spec)
    assert r.status == 200, r.body
    job = r.json()
    assert job["state"] in ("QUEUED", "RUNNING", "SUCCEEDED") and job["type"] == "render", job
    c.job = job
    with urllib.request.urlopen(f"{c.base}/v1/jobs/{job['id']}/events", timeout=60) as resp:
        assert resp.headers["Content-Type"].startswith("text/event-stream"), resp.headers
        events = [e for e in sse_events(resp) if e[0] != "comment"]
    ids = [i for i, _ in events]
    assert ids == sorted(ids) and len(set(ids)) == len(ids) and ids[0] >= 1, ids
    kinds = [next(k for k in e if k != "jobId") for _, e in events]
    assert kinds[0] == "state" and kinds[-1] == "finished", kinds
    assert all(k in ("queued", "running") for k in kinds[1:-1]), kinds
    fractions = [e["running"].get("fraction", 0) for _, e in events if "running" in e]
    assert fractions == sorted(fractions), fractions
    finished = events[-1][1]["finished"]
    assert finished["mediaType"] == "image/png" and finished["extension"] == ".png", finished
    c.events = events

    # Resumption: after the first event, exactly the rest (same ids); after the last, 204.
    req = urllib.request.Request(f"{c.base}/v1/jobs/{job['id']}/events", headers={"Last-Event-ID": str(ids[0])})
    with urllib.request.urlopen(req, timeout=60) as resp:
        resumed = [e for e in sse_events(resp) if e[0] != "comment"]
    assert resumed and all(i > ids[0] for i, _ in resumed), (ids, [i for i, _ in resumed])
    assert resumed[-1] == events[-1], (resumed[-1], events[-1])
    r = request("GET", f"{c.base}/v1/jobs/{job['id']}/events", headers={"Last-Event-ID": str(ids[-1])})
    assert r.status == 204, r.status
    expect_status(request("GET", f"{c.base}/v1/jobs/{job['id']}/events", headers={"Last-Event-ID": "x"}), 400, 3,
                  "Last-Event-ID")
    expect_status(request("GET", c.base + "/v1/jobs/nojob/events"), 404, 5, "nojob")


@step
def get_and_list_jobs(c):
    r = request("GET", f"{c.base}/v1/jobs/{c.job['id']}")
    assert r.status == 200 and r.json()["state"] == "SUCCEEDED", r.body
    expect_status(request("GET", c.base + "/v1/jobs/nojob"), 404, 5, "nojob")
    r = request("GET", c.base + "/v1/jobs")
    assert r.status == 200 and c.job["id"] in [j["id"] for j in r.json()["jobs"]], r.body
    r = request("GET", c.base + "/v1/jobs?state=SUCCEEDED&limit=5")
    jobs = r.json()["jobs"]
    assert jobs and all(j["state"] == "SUCCEEDED" for j in jobs), jobs
    r = request("GET", c.base + "/v1/jobs?state=QUEUED")
    assert r.status == 200 and r.json().get("jobs", []) == [], r.body
    expect_status(request("GET", c.base + "/v1/jobs?state=BOGUS"), 400, 3, "state")
    expect_status(request("GET", c.base + "/v1/jobs?limit=20000"), 400, 3, "limit")
    expect_status(request("GET", c.base + "/v1/jobs?limit=-1"), 400, 3, "limit")


@step
def result_and_ranges(c):
    url = f"{c.base}/v1/jobs/{c.job['id']}/result"
    r = request("GET", url)
    assert r.status == 200 and r.headers["Content-Type"] == "image/png", (r.status, r.headers)
    assert r.body.startswith(b"\x89PNG\r\n\x1a\n"), r.body[:8]
    size = len(r.body)
    assert int(r.headers["Content-Length"]) == size
    assert re.fullmatch(r'(inline|attachment); filename="render-[0-9a-zA-Z_-]+\.png"',
                        r.headers["Content-Disposition"]), r.headers["Content-Disposition"]
    assert r.headers["Accept-Ranges"] == "bytes"
    part = request("GET", url, headers={"Range": "bytes=0-7"})
    assert part.status == 206 and part.body == r.body[:8], (part.status, part.body)
    assert part.headers["Content-Range"] == f"bytes 0-7/{size}", part.headers
    tail = request("GET", url, headers={"Range": "bytes=-10"})
    assert tail.status == 206 and tail.body == r.body[-10:], tail.status
    middle = request("GET", url, headers={"Range": f"bytes=10-{size + 100}"})
    assert middle.status == 206 and middle.body == r.body[10:], middle.status
    bad = request("GET", url, headers={"Range": f"bytes={size}-"})
    expect_status(bad, 416, 11, "Range")
    assert bad.headers["Content-Range"] == f"bytes */{size}", bad.headers
    assert request("GET", url, headers={"Range": "pages=1-2"}).status == 416
    expect_status(request("GET", c.base + "/v1/jobs/nojob/result"), 404, 5, "nojob")


@step
def simplify_result(c):
    r = post_json(c.base + "/v1/jobs", {"simplify": {"cloudId": c.cloud["id"], "method": "VOXEL", "target": 200}})
    assert r.status == 200, r.body
    job_id = r.json()["id"]
    with urllib.request.urlopen(f"{c.base}/v1/jobs/{job_id}/events", timeout=60) as resp:
        last = [e for e in sse_events(resp) if e[0] != "comment"][-1][1]
    assert "finished" in last, last
    r = request("GET", f"{c.base}/v1/jobs/{job_id}/result")
    assert r.status == 200 and r.headers["Content-Type"] == "application/ply" and r.body.startswith(b"ply"), r.headers
    assert re.search(r'attachment; filename="simplify-.*\.ply"', r.headers["Content-Disposition"]), r.headers
    # The member representative through the JSON API: its report names it, and a particle job
    # that asks for it is refused with the field.
    r = post_json(c.base + "/v1/jobs", {"simplify": {"cloudId": c.cloud["id"], "method": "VOXEL", "target": 200,
                                                     "representative": "MEMBER"}})
    assert r.status == 200, r.body
    job_id = r.json()["id"]
    with urllib.request.urlopen(f"{c.base}/v1/jobs/{job_id}/events", timeout=60) as resp:
        last = [e for e in sse_events(resp) if e[0] != "comment"][-1][1]
    assert "finished" in last, last
    job = request("GET", f"{c.base}/v1/jobs/{job_id}").json()
    assert job["state"] == "SUCCEEDED", job
    assert json.loads(job["result"]["reportJson"])["representative"] == "member", job
    bad = post_json(c.base + "/v1/jobs", {"simplify": {"cloudId": c.cloud["id"], "method": "PARTICLE", "target": 200,
                                                       "representative": "MEMBER"}})
    expect_status(bad, 400, 3, "simplify.representative")


@step
def cancel_and_keepalive(c):
    slow = {"render": {"cloudId": c.cloud["id"], "width": 2048, "height": 2048, "samplesPerPixel": 64}}
    running = post_json(c.base + "/v1/jobs", slow).json()
    slow["render"]["samplesPerPixel"] = 63  # a different job (identical ones are reused)
    queued = post_json(c.base + "/v1/jobs", slow).json()
    # With one worker the second job waits: after its state and position, only comments come.
    with urllib.request.urlopen(f"{c.base}/v1/jobs/{queued['id']}/events", timeout=10) as resp:
        seen = []
        for e in sse_events(resp):
            seen.append(e)
            if e[0] == "comment":
                break
    assert seen[0][1]["state"]["id"] == queued["id"], seen
    assert seen[-1] == ("comment", "keep-alive"), seen
    expect_status(request("GET", f"{c.base}/v1/jobs/{queued['id']}/result"), 400, 9, "results exist only")
    # The running job: progress events, then a resumption in the middle of its run.
    url = f"{c.base}/v1/jobs/{running['id']}/events"
    with urllib.request.urlopen(url, timeout=30) as resp:
        head = []
        for e in sse_events(resp):
            if e[0] != "comment":
                head.append(e)
                if "running" in e[1]:
                    break
    assert "state" in head[0][1] and "running" in head[-1][1], head
    assert 0 <= head[-1][1]["running"].get("fraction", 0) <= 1, head
    req = urllib.request.Request(url, headers={"Last-Event-ID": str(head[-1][0])})
    with urllib.request.urlopen(req, timeout=30) as resp:
        nxt = next(e for e in sse_events(resp) if e[0] != "comment")
    assert nxt[0] > head[-1][0] and "running" in nxt[1], (head, nxt)
    for j in (queued, running):
        r = request("POST", f"{c.base}/v1/jobs/{j['id']}:cancel")
        assert r.status == 200 and r.json()["id"] == j["id"], r.body
    with urllib.request.urlopen(f"{c.base}/v1/jobs/{running['id']}/events", timeout=30) as resp:
        last = [e for e in sse_events(resp) if e[0] != "comment"][-1][1]
    assert last["failed"]["code"] == 1, last  # CANCELLED
    assert request("GET", f"{c.base}/v1/jobs/{running['id']}").json()["state"] == "CANCELLED"
    expect_status(request("POST", c.base + "/v1/jobs/nojob:cancel"), 404, 5, "nojob")


@step
def cors(c):
    pre = request("OPTIONS", c.base + "/v1/jobs", headers={
        "Origin": ALLOWED, "Access-Control-Request-Method": "POST", "Access-Control-Request-Headers": "content-type"})
    assert pre.status == 204, pre.status
    assert pre.headers["Access-Control-Allow-Origin"] == ALLOWED, pre.headers
    assert "POST" in pre.headers["Access-Control-Allow-Methods"], pre.headers
    assert "content-type" in pre.headers["Access-Control-Allow-Headers"].lower(), pre.headers
    denied = request("OPTIONS", c.base + "/v1/jobs", headers={
        "Origin": "http://evil.example", "Access-Control-Request-Method": "POST"})
    expect_status(denied, 403, 7, "http://evil.example")
    assert "Access-Control-Allow-Origin" not in denied.headers
    r = request("GET", c.base + "/v1/jobs", headers={"Origin": ALLOWED})
    assert r.headers["Access-Control-Allow-Origin"] == ALLOWED and "Origin" in r.headers["Vary"], r.headers
    assert "Content-Disposition" in r.headers["Access-Control-Expose-Headers"]
    r = request("GET", c.base + "/v1/jobs", headers={"Origin": "http://evil.example"})
    assert r.status == 200 and "Access-Control-Allow-Origin" not in r.headers, r.headers


@step
def delete_cloud(c):
    r = request("DELETE", f"{c.base}/v1/clouds/{c.cloud['id']}")
    assert r.status == 200 and r.json() == {"deleted": True}, r.body
    expect_status(request("DELETE", f"{c.base}/v1/clouds/{c.cloud['id']}"), 404, 5, c.cloud["id"])
    expect_status(request("GET", f"{c.base}/v1/clouds/{c.cloud['id']}"), 404, 5)


@step
def sigterm_with_open_stream(c):
    spec = {"render": {"cloudId": c.other_cloud, "width": 2048, "height": 2048, "samplesPerPixel": 32}}
    job = post_json(c.base + "/v1/jobs", spec).json()
    resp = urllib.request.urlopen(f"{c.base}/v1/jobs/{job['id']}/events", timeout=30)
    first = next(sse_events(resp))
    assert first[1]["state"]["id"] == job["id"], first
    reader = threading.Thread(target=lambda: [None for _ in sse_events(resp)], daemon=True)
    reader.start()
    start = time.monotonic()
    code = c.server.stop(signal.SIGTERM, timeout=20)
    assert code == 0, code
    reader.join(10)
    assert not reader.is_alive(), "the event stream stayed open after the server stopped"
    print(f"  SIGTERM with an open event stream: exit 0 in {time.monotonic() - start:.1f} s")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--server-bin", required=True)
    ap.add_argument("--work-dir", required=True)
    a = ap.parse_args()
    c = Ctx()
    c.server_bin, c.work_dir = a.server_bin, a.work_dir
    c.n = 1500
    c.max_upload = 100 * 1024
    c.max_points = 3000
    c.server = Server(a.server_bin, a.work_dir, [
        "--workers", "1", "--max-upload-mb", str(c.max_upload / 1048576), "--max-points", str(c.max_points),
        "--http-cors-origins", ALLOWED + ",http://other.example", "--http-keepalive-s", "0.3", "--grace", "0"])
    c.base = c.server.base
    c.ply = sphere_ply(c.n)
    r = request("POST", c.base + "/v1/clouds?filename=other.ply", sphere_ply(800, binary=True))
    assert r.status == 200, r.body
    c.other_cloud = r.json()["id"]
    try:
        for fn in STEPS:
            t = time.monotonic()
            fn(c)
            print(f"ok  {fn.__name__} ({time.monotonic() - t:.1f} s)")
    except BaseException:
        print("server log:\n" + c.server.read_log())
        raise
    finally:
        c.server.stop(signal.SIGKILL)
    print(f"all {len(STEPS)} HTTP API checks passed")


if __name__ == "__main__":
    main()

#!/usr/bin/python3
"""Authentication, tenancy and TLS (docs/security.md) through the real surfel-server, driven by
Python grpcio (stubs generated from our proto), urllib for the HTTP front and the real `surfel`
CLI for TLS. Certificates come from `openssl` at test time.

Checks: without a token or with a wrong one every RPC is UNAUTHENTICATED and every API route 401
(google.rpc.Status body, WWW-Authenticate), while grpc.health.v1 and the page's files stay open;
tenants A and B: B gets NOT_FOUND for A's cloud/job on every call (get, delete, submit, watch,
download, cancel, events, result), lists show only their own, the same file uploaded by both is
stored once on disk and B's upload says nothing of A's (deduplicated false); a signed events URL
works without headers and a forged one is 401; TLS: CLI --ca and HTTPS with the CA; mutual TLS
refuses clients without a certificate on both ports; a malformed token file stops the start
naming file and line.
"""
import argparse
import json
import os
import shutil
import ssl
import subprocess
import sys
import time
import urllib.error
import urllib.request

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from python_client import generate, sphere_ply  # noqa: E402

TOKEN_A = "tok-alice-0123456789abcdef"
TOKEN_B = "tok-bob-fedcba9876543210"


def start(server_bin, work, name, extra, scheme="http"):
    d = os.path.join(work, name)
    shutil.rmtree(d, ignore_errors=True)
    os.makedirs(d)
    pf, hpf = os.path.join(d, "port"), os.path.join(d, "http-port")
    log = open(os.path.join(d, "server.log"), "w")
    proc = subprocess.Popen([server_bin, "--port", "0", "--port-file", pf, "--data-dir", os.path.join(d, "data"),
                             "--http", "127.0.0.1:0", "--http-port-file", hpf, "--log-level", "warn", *extra],
                            stdout=log, stderr=log)
    for _ in range(1000):
        if os.path.exists(pf) and os.path.exists(hpf):
            break
        if proc.poll() is not None:
            raise RuntimeError("surfel-server exited: " + open(log.name).read())
        time.sleep(0.01)
    return proc, int(open(pf).read()), f"{scheme}://127.0.0.1:{int(open(hpf).read())}", d


def stop(proc):
    proc.terminate()
    assert proc.wait(30) == 0


def http(method, url, body=None, token=None, ctx=None, headers=None):
    h = dict(headers or {})
    if token:
        h["Authorization"] = "Bearer " + token
    req = urllib.request.Request(url, data=body, method=method, headers=h)
    try:
        with urllib.request.urlopen(req, timeout=60, context=ctx) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--server-bin", required=True)
    ap.add_argument("--cli-bin", required=True)
    ap.add_argument("--proto-dir", required=True)
    ap.add_argument("--work-dir", required=True)
    a = ap.parse_args()
    shutil.rmtree(a.work_dir, ignore_errors=True)
    os.makedirs(a.work_dir)
    generate(a.proto_dir, os.path.join(a.work_dir, "gen"))
    import grpc
    from health_check import health_pb2, health_pb2_grpc
    from surfel.v1 import surfel_pb2 as pb, surfel_pb2_grpc as rpc

    # ---- a malformed token file stops the start, naming file and line
    bad = os.path.join(a.work_dir, "bad-tokens")
    open(bad, "w").write("# tenants\nalice " + TOKEN_A + "\nbob short\n")
    r = subprocess.run([a.server_bin, "--port", "0", "--auth-tokens", bad, "--data-dir",
                        os.path.join(a.work_dir, "bad-data")], capture_output=True, text=True, timeout=30)
    assert r.returncode == 1 and f"{bad}:3" in r.stderr and "16 to 4096" in r.stderr, r.stderr
    hashed = subprocess.run([a.server_bin, "--hash-token"], input=TOKEN_B + "\n", capture_output=True,
                            text=True, timeout=30).stdout.strip()
    assert hashed.startswith("sha256:") and len(hashed) == 71, hashed

    tokens = os.path.join(a.work_dir, "tokens")
    open(tokens, "w").write(f"# name token\nalice {TOKEN_A}\n\nbob {hashed}\n")  # bob's stored hashed
    proc, port, base, d = start(a.server_bin, a.work_dir, "auth", ["--auth-tokens", tokens])
    try:
        channel = grpc.insecure_channel(f"127.0.0.1:{port}")
        stub = rpc.SurfelStub(channel)
        md = {t: [("authorization", "Bearer " + t)] for t in (TOKEN_A, TOKEN_B)}
        A, B = md[TOKEN_A], md[TOKEN_B]

        # ---- health open; every RPC refused without / with a wrong token
        health = health_pb2_grpc.HealthStub(channel)
        assert health.Check(health_pb2.HealthCheckRequest(service="surfel.v1.Surfel")).status == \
            health_pb2.HealthCheckResponse.SERVING

        def upload_reqs(uid, data):
            yield pb.UploadRequest(upload_id=uid, filename="s.ply", write_offset=0, data=data, finish_write=True)

        calls = {
            "Upload": lambda m: stub.Upload(upload_reqs("u1", sphere_ply(10)), metadata=m),
            "QueryUpload": lambda m: stub.QueryUpload(pb.QueryUploadRequest(upload_id="u1"), metadata=m),
            "GetCloud": lambda m: stub.GetCloud(pb.GetCloudRequest(cloud_id="x"), metadata=m),
            "DeleteCloud": lambda m: stub.DeleteCloud(pb.DeleteCloudRequest(cloud_id="x"), metadata=m),
            "Submit": lambda m: stub.Submit(pb.SubmitRequest(spec=pb.JobSpec()), metadata=m),
            "Watch": lambda m: list(stub.Watch(pb.WatchRequest(job_id="x"), metadata=m)),
            "Download": lambda m: list(stub.Download(pb.DownloadRequest(job_id="x"), metadata=m)),
            "Cancel": lambda m: stub.Cancel(pb.CancelRequest(job_id="x"), metadata=m),
            "GetJob": lambda m: stub.GetJob(pb.GetJobRequest(job_id="x"), metadata=m),
            "ListJobs": lambda m: stub.ListJobs(pb.ListJobsRequest(), metadata=m),
        }
        assert set(calls) == {m.name for m in pb.DESCRIPTOR.services_by_name["Surfel"].methods}
        for name, call in calls.items():
            for m in (None, [("authorization", "Bearer wrong-token-0000000000")], [("authorization", "Basic x")]):
                try:
                    call(m)
                    raise AssertionError(f"{name} answered without a valid token")
                except grpc.RpcError as e:
                    assert e.code() == grpc.StatusCode.UNAUTHENTICATED, (name, e.code(), e.details())

        # ---- HTTP: every API route 401 with a Status body; the page open
        routes = [("POST", "/v1/clouds?filename=s.ply"), ("GET", "/v1/clouds/x"), ("DELETE", "/v1/clouds/x"),
                  ("POST", "/v1/jobs"), ("GET", "/v1/jobs"), ("GET", "/v1/jobs/x"), ("POST", "/v1/jobs/x:cancel"),
                  ("GET", "/v1/jobs/x/events"), ("GET", "/v1/jobs/x/result"), ("POST", "/v1/jobs/x:eventsUrl")]
        for method, path in routes:
            for tok in (None, "wrong-token-0000000000"):
                status, headers, body = http(method, base + path, b"{}" if method == "POST" else None, tok)
                assert status == 401, (method, path, status, body)
                assert json.loads(body)["code"] == 16 and "Bearer" in headers.get("WWW-Authenticate", ""), body
        status, _, body = http("GET", base + "/")
        assert status == 200 and b"<html" in body.lower(), status

        # ---- tenancy: A uploads and runs a job; B sees none of it
        data = sphere_ply(2000)
        cloud_a = stub.Upload(upload_reqs("s1", data), metadata=A)
        assert not cloud_a.deduplicated
        assert stub.Upload(upload_reqs("s2", data), metadata=A).deduplicated  # A's own: deduplicated
        spec = pb.JobSpec(simplify=pb.SimplifyJob(cloud_id=cloud_a.id, target=200))
        job_a = stub.Submit(pb.SubmitRequest(spec=spec), metadata=A)
        assert job_a.tenant == "alice", job_a.tenant
        events = list(stub.Watch(pb.WatchRequest(job_id=job_a.id), metadata=A))
        assert events[-1].WhichOneof("event") == "finished", events[-1]

        def not_found(call):
            try:
                call()
                raise AssertionError("another tenant's id answered")
            except grpc.RpcError as e:
                assert e.code() == grpc.StatusCode.NOT_FOUND, (e.code(), e.details())
                return e.details()

        unknown = not_found(lambda: stub.GetCloud(pb.GetCloudRequest(cloud_id="0" * 64), metadata=B))
        foreign = not_found(lambda: stub.GetCloud(pb.GetCloudRequest(cloud_id=cloud_a.id), metadata=B))
        assert foreign == unknown.replace("0" * 64, cloud_a.id)  # the same words as an unknown id
        not_found(lambda: stub.Submit(pb.SubmitRequest(spec=spec), metadata=B))
        not_found(lambda: stub.GetJob(pb.GetJobRequest(job_id=job_a.id), metadata=B))
        not_found(lambda: stub.Cancel(pb.CancelRequest(job_id=job_a.id), metadata=B))
        not_found(lambda: list(stub.Watch(pb.WatchRequest(job_id=job_a.id), metadata=B)))
        not_found(lambda: list(stub.Download(pb.DownloadRequest(job_id=job_a.id), metadata=B)))
        not_found(lambda: stub.DeleteCloud(pb.DeleteCloudRequest(cloud_id=cloud_a.id), metadata=B))
        assert len(stub.ListJobs(pb.ListJobsRequest(), metadata=A).jobs) == 1
        assert len(stub.ListJobs(pb.ListJobsRequest(), metadata=B).jobs) == 0
        assert len(b"".join(c.data for c in stub.Download(pb.DownloadRequest(job_id=job_a.id), metadata=A))) > 0
        for method, path in [("GET", f"/v1/clouds/{cloud_a.id}"), ("GET", f"/v1/jobs/{job_a.id}"),
                             ("POST", f"/v1/jobs/{job_a.id}:cancel"), ("GET", f"/v1/jobs/{job_a.id}/events"),
                             ("GET", f"/v1/jobs/{job_a.id}/result"), ("POST", f"/v1/jobs/{job_a.id}:eventsUrl"),
                             ("DELETE", f"/v1/clouds/{cloud_a.id}")]:
            status, _, body = http(method, base + path, b"" if method == "POST" else None, TOKEN_B)
            assert status == 404 and json.loads(body)["code"] == 5, (method, path, status, body)
        status, _, body = http("GET", base + "/v1/jobs", token=TOKEN_B)
        assert status == 200 and json.loads(body).get("jobs", []) == [], body
        status, _, body = http("GET", base + "/v1/jobs", token=TOKEN_A)
        assert status == 200 and len(json.loads(body)["jobs"]) == 1, body

        # ---- the same file from B: stored once on disk, and nothing tells B that A has it
        cloud_b = stub.Upload(upload_reqs("s1", data), metadata=B)  # A's upload id too: ids are per tenant
        assert cloud_b.id == cloud_a.id and not cloud_b.deduplicated, cloud_b
        assert len(os.listdir(os.path.join(d, "data", "clouds"))) == 1
        job_b = stub.Submit(pb.SubmitRequest(spec=spec), metadata=B)  # reuse is per tenant: a new job
        assert job_b.id != job_a.id and not job_b.reused and job_b.tenant == "bob", job_b
        list(stub.Watch(pb.WatchRequest(job_id=job_b.id), metadata=B))
        # B deletes its copy; A keeps the cloud and its bytes
        assert stub.DeleteCloud(pb.DeleteCloudRequest(cloud_id=cloud_a.id), metadata=B).deleted
        assert stub.GetCloud(pb.GetCloudRequest(cloud_id=cloud_a.id), metadata=A).id == cloud_a.id
        not_found(lambda: stub.GetCloud(pb.GetCloudRequest(cloud_id=cloud_a.id), metadata=B))
        assert len(os.listdir(os.path.join(d, "data", "clouds"))) == 1

        # ---- the browser's event stream: a signed URL, no header
        status, _, body = http("POST", f"{base}/v1/jobs/{job_a.id}:eventsUrl", b"", TOKEN_A)
        assert status == 200, body
        url = json.loads(body)["url"]
        status, _, body = http("GET", base + url)
        assert status == 200 and b"finished" in body, (status, body)
        forged = url[:-4] + ("0000" if not url.endswith("0000") else "1111")
        assert http("GET", base + forged)[0] == 401
        status, _, body = http("POST", f"{base}/v1/jobs/{job_b.id}:eventsUrl", b"", TOKEN_B)
        other = json.loads(body)["url"].replace(job_b.id, job_a.id)  # B's signature on A's job
        assert http("GET", base + other)[0] == 401
        stop(proc)
    finally:
        if proc.poll() is None:
            proc.kill()

    # ---- TLS: a CA, a server certificate for 127.0.0.1/localhost, a client certificate
    pki = os.path.join(a.work_dir, "pki")
    os.makedirs(pki)

    def ossl(*args):
        subprocess.run(["openssl", *args], cwd=pki, check=True, capture_output=True, timeout=60)

    ossl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out", "ca.pem", "-days", "2",
         "-subj", "/CN=surfel test CA")
    for who, ext in (("server", "subjectAltName=DNS:localhost,IP:127.0.0.1"), ("client", "extendedKeyUsage=clientAuth")):
        ossl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{who}.key", "-out", f"{who}.csr", "-subj", f"/CN={who}")
        open(os.path.join(pki, f"{who}.ext"), "w").write(ext + "\n")
        ossl("x509", "-req", "-in", f"{who}.csr", "-CA", "ca.pem", "-CAkey", "ca.key", "-CAcreateserial",
             "-out", f"{who}.pem", "-days", "2", "-extfile", f"{who}.ext")
    P = lambda f: os.path.join(pki, f)  # noqa: E731
    tls = ["--tls-cert", P("server.pem"), "--tls-key", P("server.key")]

    proc, port, base, d = start(a.server_bin, a.work_dir, "tls", tls + ["--auth-tokens", tokens], "https")
    try:
        r = subprocess.run([a.cli_bin, "jobs", "--server", f"localhost:{port}", "--ca", P("ca.pem"),
                            "--token", TOKEN_A, "--json"], capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        r = subprocess.run([a.cli_bin, "jobs", "--server", f"localhost:{port}", "--ca", P("ca.pem")],
                           capture_output=True, text=True, timeout=60, env={**os.environ, "SURFEL_TOKEN": "wrong-token-000000"})
        assert r.returncode == 1 and "UNAUTHENTICATED" in r.stderr, r.stderr
        r = subprocess.run([a.cli_bin, "jobs", "--server", f"localhost:{port}", "--token", TOKEN_A],
                           capture_output=True, text=True, timeout=60)  # plaintext against TLS
        assert r.returncode == 1 and "UNAVAILABLE" in r.stderr, r.stderr
        ctx = ssl.create_default_context(cafile=P("ca.pem"))
        status, _, body = http("GET", base + "/v1/jobs", token=TOKEN_A, ctx=ctx)
        assert status == 200, (status, body)
        stop(proc)
    finally:
        if proc.poll() is None:
            proc.kill()

    proc, port, base, d = start(a.server_bin, a.work_dir, "mtls", tls + ["--tls-client-ca", P("ca.pem")], "https")
    try:
        ca = open(P("ca.pem"), "rb").read()
        good = grpc.secure_channel(f"localhost:{port}", grpc.ssl_channel_credentials(
            ca, open(P("client.key"), "rb").read(), open(P("client.pem"), "rb").read()))
        rpc.SurfelStub(good).ListJobs(pb.ListJobsRequest(), timeout=20)
        anon = grpc.secure_channel(f"localhost:{port}", grpc.ssl_channel_credentials(ca))
        try:
            rpc.SurfelStub(anon).ListJobs(pb.ListJobsRequest(), timeout=20)
            raise AssertionError("mTLS: a client without a certificate was served")
        except grpc.RpcError as e:
            assert e.code() == grpc.StatusCode.UNAVAILABLE, e.code()
        r = subprocess.run([a.cli_bin, "jobs", "--server", f"localhost:{port}", "--ca", P("ca.pem"),
                            "--cert", P("client.pem"), "--key", P("client.key")],
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        ctx = ssl.create_default_context(cafile=P("ca.pem"))
        ctx.load_cert_chain(P("client.pem"), P("client.key"))
        assert http("GET", base + "/v1/jobs", ctx=ctx)[0] == 200
        try:
            http("GET", base + "/v1/jobs", ctx=ssl.create_default_context(cafile=P("ca.pem")))
            raise AssertionError("mTLS: HTTPS without a client certificate was served")
        except (ssl.SSLError, urllib.error.URLError, ConnectionError) as e:
            print("refused as expected:", type(e).__name__)
        stop(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
    print("auth, tenancy and TLS: all checks passed")


if __name__ == "__main__":
    main()

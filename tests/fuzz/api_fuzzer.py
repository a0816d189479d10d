#!/usr/bin/python3
"""API fuzzer (issue 18, item 5): randomized and mutated protobuf messages to every gRPC method of
surfel.v1.Surfel (and grpc.health.v1.Health), and random requests to every HTTP route of --http,
against the real surfel-server. Asserts: the server never dies, no call answers INTERNAL or UNKNOWN
(HTTP: no 5xx other than 501/503 and no google.rpc.Status body with code 13 or 2), and the
server's resident memory stays under --max-rss-mb. Ends with a health check and a clean SIGTERM.

The one INTERNAL allowed: bytes that are not a protobuf message at all (Python's own protobuf
refuses them too) are answered by gRPC's generated code before any handler runs, with INTERNAL
(grpcpp/impl/codegen/proto_utils.h, GenericDeserialize); those are counted as "undecodable".

CI (ctest api_fuzzer) sends 10,000 messages; longer runs: bench/README.md (--messages, --seconds).
Messages that would be valid but costly (a 16384 x 16384 render) are kept small unless
--unbounded-costs: this is a robustness test, not a load test (item 7) or a memory-admission test
(item 2).

    api_fuzzer.py --server-bin build/bin/surfel-server --proto-dir proto --work-dir /tmp/f \\
                  [--messages 10000] [--seconds 0] [--seed 1] [--max-rss-mb 1536]
"""
import argparse
import collections
import http.client
import json
import math
import os
import random
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
import urllib.parse
import warnings

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "integration"))
from python_client import generate, sphere_ply  # noqa: E402

# ---- Values worth trying, per type -----------------------------------------------------------------

INT32 = [0, 1, -1, 2, 7, 100, 2**31 - 1, -2**31, 16384, 16385, 65535]
INT64 = INT32 + [2**63 - 1, -2**63, 2**32, 10**12]
UINT32 = [0, 1, 2, 3, 100, 2**31, 2**32 - 1]
UINT64 = UINT32 + [2**63, 2**64 - 1, 10**12]
DOUBLES = [0.0, -0.0, 1.0, -1.0, 0.5, 1e-30, -1e-30, 1e30, 1e308, -1e308, 5e-324, float("inf"),
           float("-inf"), float("nan"), 3.0, 100.0, 1e-7]
STRINGS = ["", "a", "x" * 64, "a" * 64, "0" * 64, "../../etc/passwd", "..", "/", "%00", "\u00e9\u6f22",
           "nope", "a b", "x" * 5000, "\n", "render", "ply", "id:cancel", "*", "' OR 1=1 --"]

# Fields whose valid values cost time or memory, each with its small and its refused values: the
# fuzzer stays a robustness test (see the docstring). --unbounded-costs lifts this.
COSTLY = {
    "width": [0, 1, 16, 40, -1, 16385, 2**31 - 1], "height": [0, 1, 12, 30, -1, 16385, 2**31 - 1],
    "samples_per_pixel": [0, 1, 2, -1, 1025, 2**31 - 1], "max_iterations": [0, 1, 5, -1, 2**31 - 1],
    "target": [0, 1, 2, 50, 300, 10**9, 2**64 - 1], "iterations": [0, 1, 3, -1, 10**6, 2**31 - 1],
    "max_cluster_size": [0, 1, 5, 10**9], "seed": [0, 1, 2**64 - 1],
    "spacing": [0.0, -1.0, 0.05, 0.2, 1e-30, float("nan"), float("inf")],
    "mls_h": [0.0, -1.0, 0.1, 0.3, 1e-30, float("nan"), 1e30],
    "error": [0.0, -1.0, 0.01, 0.05, float("nan"), 1e30],
    "timeout_ms": [0, 1, 50, 2000, -1, 2**63 - 1],
    "limit": [0, 1, 5, 2**32 - 1],
}


class Fuzzer:
    def __init__(self, args, pb, health_pb, stubs_module):
        self.a = args
        self.rng = random.Random(args.seed)
        self.pb = pb
        self.health_pb = health_pb
        self.cloud_ids = []
        self.job_ids = []
        self.upload_ids = []
        self.sent = 0
        self.codes = collections.Counter()
        self.per_call = collections.Counter()
        self.undecodable = 0
        self.failures = []
        self.peak_rss_mb = 0.0
        self.rss_samples = []

    # ---- Random protobuf messages (reflection over the descriptor) --------------------------------

    def scalar(self, field):
        from google.protobuf.descriptor import FieldDescriptor as F
        r = self.rng
        if not self.a.unbounded_costs and field.name in COSTLY:
            v = r.choice(COSTLY[field.name])
            if field.type in (F.TYPE_DOUBLE, F.TYPE_FLOAT):
                return float(v)
            if field.type in (F.TYPE_UINT32, F.TYPE_FIXED32):
                return v if 0 <= v < 2**32 else 2**32 - 1
            if field.type in (F.TYPE_UINT64, F.TYPE_FIXED64):
                return v if 0 <= v < 2**64 else 0
            if field.type in (F.TYPE_INT32, F.TYPE_SINT32, F.TYPE_SFIXED32):
                return max(-2**31, min(2**31 - 1, int(v)))
            return max(-2**63, min(2**63 - 1, int(v)))
        t = field.type
        if t in (F.TYPE_DOUBLE, F.TYPE_FLOAT):
            v = r.choice(DOUBLES) if r.random() < 0.7 else r.uniform(-10, 10)
            if t == F.TYPE_FLOAT and math.isfinite(v) and abs(v) > 3e38:
                v = math.copysign(float("inf"), v)
            return v
        if t in (F.TYPE_INT32, F.TYPE_SINT32, F.TYPE_SFIXED32):
            return r.choice(INT32) if r.random() < 0.8 else r.randint(-2**31, 2**31 - 1)
        if t in (F.TYPE_INT64, F.TYPE_SINT64, F.TYPE_SFIXED64):
            return r.choice(INT64) if r.random() < 0.8 else r.randint(-2**63, 2**63 - 1)
        if t in (F.TYPE_UINT32, F.TYPE_FIXED32):
            return r.choice(UINT32)
        if t in (F.TYPE_UINT64, F.TYPE_FIXED64):
            return r.choice(UINT64)
        if t == F.TYPE_BOOL:
            return r.random() < 0.5
        if t == F.TYPE_ENUM:
            values = [v.number for v in field.enum_type.values]
            return r.choice(values) if r.random() < 0.8 else r.choice([-1, 99, 2**31 - 1, -2**31])
        if t == F.TYPE_STRING:
            return self.some_string()
        if t == F.TYPE_BYTES:
            return self.some_file()
        raise AssertionError(f"unhandled field type {t} of {field.full_name}")

    def some_string(self):
        r = self.rng
        known = self.cloud_ids + self.job_ids + self.upload_ids
        if known and r.random() < 0.45:
            s = r.choice(known)
            return s if r.random() < 0.8 else s[:-1] + r.choice("0af-Z")
        if r.random() < 0.7:
            return r.choice(STRINGS)
        return "".join(chr(r.choice([r.randint(32, 126), r.randint(0x80, 0x7ff), r.randint(1, 31)]))
                       for _ in range(r.randint(1, 40)))

    def some_file(self):
        r = self.rng
        choice = r.random()
        if choice < 0.3:
            return self.mutate_bytes(self.good_ply)
        if choice < 0.5:
            return b"ply\nformat ascii 1.0\nelement vertex %d\nproperty float x\nproperty float y\n" \
                   b"property float z\nend_header\n" % r.choice([0, 1, 2, 3, 2**31, 2**63]) + \
                   b"0 0 0\n" * r.randint(0, 3)
        if choice < 0.7:
            return "".join(f"{r.choice(DOUBLES)} {r.uniform(-1, 1)} {r.uniform(-1, 1)}\n"
                           for _ in range(r.randint(0, 8))).encode()
        if choice < 0.8:
            return b""
        return bytes(r.getrandbits(8) for _ in range(r.randint(1, 300)))

    def fill(self, msg, depth):
        from google.protobuf.descriptor import FieldDescriptor as F
        r = self.rng
        for field in msg.DESCRIPTOR.fields:
            if r.random() < (0.35 if depth else 0.6):
                continue
            if field.label == F.LABEL_REPEATED:
                container = getattr(msg, field.name)
                for _ in range(r.choice([0, 1, 2, 3, 9, 10])):
                    if field.type == F.TYPE_MESSAGE:
                        if depth < 4:
                            self.fill(container.add(), depth + 1)
                    else:
                        container.append(self.scalar(field))
            elif field.type == F.TYPE_MESSAGE:
                if depth < 4:
                    sub = getattr(msg, field.name)
                    sub.SetInParent()
                    self.fill(sub, depth + 1)
            else:
                setattr(msg, field.name, self.scalar(field))

    def mutate_message(self, msg):
        """A copy of a valid message with a few of its fields (at any depth) replaced."""
        from google.protobuf.descriptor import FieldDescriptor as F
        out = type(msg)()
        out.CopyFrom(msg)
        for _ in range(self.rng.randint(1, 3)):
            node = out
            for _ in range(4):
                fields = [f for f in node.DESCRIPTOR.fields]
                field = self.rng.choice(fields)
                if field.label == F.LABEL_REPEATED:
                    container = getattr(node, field.name)
                    if field.type == F.TYPE_MESSAGE:
                        self.fill(container.add(), 1)
                    else:
                        container.append(self.scalar(field))
                    break
                if field.type == F.TYPE_MESSAGE:
                    node = getattr(node, field.name)
                    node.SetInParent()
                    continue
                setattr(node, field.name, self.scalar(field))
                break
        return out

    def mutate_bytes(self, data):
        r = self.rng
        b = bytearray(data)
        for _ in range(r.randint(1, 6)):
            op = r.random()
            if not b or op < 0.25:
                b[r.randint(0, len(b)):r.randint(0, len(b))] = bytes(r.getrandbits(8) for _ in range(r.randint(1, 8)))
            elif op < 0.5:
                i = r.randrange(len(b))
                b[i] ^= 1 << r.randrange(8)
            elif op < 0.7:
                i = r.randrange(len(b))
                b[i] = r.choice([0, 0xff, 0x7f, 0x80, 0x08, 0x0a, 0x12])
            elif op < 0.85:
                del b[r.randrange(len(b)):][:r.randint(1, 16)]
            else:
                i = r.randrange(len(b))
                b[i:i] = b[i:i + r.randint(1, 32)]  # duplicate a run
        return bytes(b)

    # ---- Checks -----------------------------------------------------------------------------------

    def fail(self, what, detail):
        self.failures.append(f"{what}: {detail}")
        print(f"api-fuzz: FAILURE {what}: {detail}"[:2000], file=sys.stderr)

    def check_status(self, call, code, details, request_desc, parsed_locally=True):
        import grpc
        self.codes[f"grpc {code.name}"] += 1
        if code in (grpc.StatusCode.INTERNAL, grpc.StatusCode.UNKNOWN):
            if code == grpc.StatusCode.INTERNAL and not parsed_locally:
                self.undecodable += 1
                return
            self.fail(f"{call} answered {code.name}", f"{details!r} for {request_desc}")
        elif code == grpc.StatusCode.UNAVAILABLE:
            self.fail(f"{call} answered UNAVAILABLE", f"{details!r} (server alive: {self.alive()})")

    def alive(self):
        return self.server.poll() is None

    def sample_rss(self):
        try:
            with open(f"/proc/{self.server.pid}/status") as f:
                for line in f:
                    if line.startswith("VmRSS:"):
                        mb = int(line.split()[1]) / 1024
                        self.peak_rss_mb = max(self.peak_rss_mb, mb)
                        self.rss_samples.append(mb)
                        if mb > self.a.max_rss_mb:
                            self.fail("server RSS", f"{mb:.0f} MiB > --max-rss-mb {self.a.max_rss_mb}")
        except OSError:
            pass

    # ---- gRPC ---------------------------------------------------------------------------------------

    def grpc_calls(self):
        """(name, kind, request descriptor, path) for every method of both services."""
        from google.protobuf import descriptor_pb2
        calls = []
        for module, service in [(self.pb, "Surfel"), (self.health_pb, "Health")]:
            fdp = descriptor_pb2.FileDescriptorProto.FromString(module.DESCRIPTOR.serialized_pb)
            sd = module.DESCRIPTOR.services_by_name[service]
            for m in next(s for s in fdp.service if s.name == service).method:
                md = sd.methods_by_name[m.name]
                kind = ("stream" if m.client_streaming else "unary") + "_" + ("stream" if m.server_streaming else "unary")
                calls.append((m.name, kind, md.input_type, f"/{sd.full_name}/{m.name}"))
        return calls

    def seeds(self, name):
        """Valid requests of a method, for mutation."""
        pb = self.pb
        cid = self.rng.choice(self.cloud_ids) if self.cloud_ids else "0" * 64
        jid = self.rng.choice(self.job_ids) if self.job_ids else "job"
        specs = [pb.JobSpec(render=pb.RenderJob(cloud_id=cid, width=16, height=12)),
                 pb.JobSpec(simplify=pb.SimplifyJob(cloud_id=cid, target=50)),
                 pb.JobSpec(resample=pb.ResampleJob(cloud_id=cid, target=400, iterations=2)),
                 pb.JobSpec(resample=pb.ResampleJob(cloud_id=cid, method=pb.ResampleJob.MLS)),
                 pb.JobSpec(boolean=pb.BooleanJob(cloud_id_a=cid, cloud_id_b=cid, op=pb.BooleanJob.UNION,
                                                  transform_b=pb.Similarity(translation=pb.Vec3(x=0.5))))]
        return {
            "QueryUpload": [pb.QueryUploadRequest(upload_id=self.rng.choice(self.upload_ids or ["u1"]))],
            "GetCloud": [pb.GetCloudRequest(cloud_id=cid)],
            "DeleteCloud": [pb.DeleteCloudRequest(cloud_id="f" * 64)],  # never a live one: keeps seeds
            "Submit": [pb.SubmitRequest(spec=s) for s in specs],
            "Watch": [pb.WatchRequest(job_id=jid, include_result=True)],
            "Download": [pb.DownloadRequest(job_id=jid)],
            "Cancel": [pb.CancelRequest(job_id=jid)],
            "GetJob": [pb.GetJobRequest(job_id=jid)],
            "ListJobs": [pb.ListJobsRequest(limit=5)],
            "Check@health": [self.health_pb.HealthCheckRequest(service="surfel.v1.Surfel")],
            "Watch@health": [self.health_pb.HealthCheckRequest(service="")],
        }.get(name, [])

    def make_request(self, name, descriptor, cls):
        """(bytes, parsed locally, description): a seed mutated, a random message, or raw bytes."""
        r = self.rng.random()
        seeds = self.seeds(name)
        if seeds and r < 0.45:
            msg = self.mutate_message(self.rng.choice(seeds)) if self.rng.random() < 0.8 else self.rng.choice(seeds)
        elif r < 0.85:
            msg = cls()
            self.fill(msg, 0)
        else:
            base = (self.rng.choice(seeds) if seeds else cls()).SerializeToString()
            raw = self.mutate_bytes(base) if base or self.rng.random() < 0.5 else bytes(
                self.rng.getrandbits(8) for _ in range(self.rng.randint(1, 64)))
            try:
                with warnings.catch_warnings():  # "Unexpected end-group tag": C++ refuses those
                    warnings.simplefilter("error")
                    ok = cls.FromString(raw).SerializeToString() is not None
            except Exception:
                ok = False
            return raw, ok, f"raw bytes {raw[:200]!r}"
        return msg.SerializeToString(), True, f"{name} {str(msg)[:400]!r}"

    def fuzz_grpc_once(self, calls, classes):
        import grpc
        name, kind, descriptor, path = self.rng.choice(calls)
        cls = classes[descriptor.full_name]
        if name == "DeleteCloud" and self.rng.random() < 0.9:
            # Mostly unknown ids: deleting the seeds' clouds would leave little to fuzz jobs with.
            req = cls(cloud_id=self.rng.choice(["f" * 64, "", "x", "../x", "0" * 63 + "g"]))
            data, ok, desc = req.SerializeToString(), True, f"DeleteCloud {req}"
        elif kind == "stream_unary":  # Upload
            self.fuzz_upload(path, cls)
            return
        else:
            seed_key = name if path.startswith("/surfel.") else name + "@health"
            data, ok, desc = self.make_request(seed_key, descriptor, cls)
        self.per_call[f"grpc {name}"] += 1
        self.sent += 1
        try:
            if kind == "unary_unary":
                reply = self.channel.unary_unary(path)(data, timeout=10)
                if name == "Submit":
                    job = self.pb.Job.FromString(reply)
                    self.job_ids.append(job.id)
                    if self.rng.random() < 0.7:
                        self.cancel(job.id)
                self.codes["grpc OK"] += 1
            else:
                stream = self.channel.unary_stream(path)(data, timeout=self.rng.choice([0.05, 0.1, 0.3]))
                for _ in stream:
                    pass
                self.codes["grpc OK"] += 1
        except grpc.RpcError as e:
            if e.code() == grpc.StatusCode.DEADLINE_EXCEEDED and kind == "unary_stream":
                self.codes["grpc DEADLINE_EXCEEDED (client's)"] += 1
                return
            if (path.startswith("/grpc.health.") and e.code() == grpc.StatusCode.INTERNAL
                    and e.details() == "could not parse request" and len(self.last_service(data)) > 200):
                # gRPC's DefaultHealthCheckService refuses a service name over 200 bytes with
                # INTERNAL (kMaxServiceNameLength, default_health_check_service.cc): libgrpc++'s
                # answer, not ours. Counted apart; docs/testing.md.
                self.codes["grpc INTERNAL from gRPC's health service (name > 200 bytes)"] += 1
                return
            self.check_status(name, e.code(), e.details(), desc, ok)

    def last_service(self, data):
        try:
            return self.health_pb.HealthCheckRequest.FromString(data).service
        except Exception:
            return ""

    def cancel(self, job_id):
        import grpc
        self.sent += 1
        self.per_call["grpc Cancel"] += 1
        try:
            self.stub.Cancel(self.pb.CancelRequest(job_id=job_id), timeout=10)
            self.codes["grpc OK"] += 1
        except grpc.RpcError as e:
            self.check_status("Cancel", e.code(), e.details(), job_id)

    def fuzz_upload(self, path, cls):
        """A random sequence of upload messages: good, shifted offsets, bad ids, odd names, no finish."""
        import grpc
        r = self.rng
        data = self.some_file() if r.random() < 0.6 else sphere_ply(r.choice([1, 2, 3, 40, 200]))
        upload_id = r.choice([f"fz-{r.getrandbits(32):08x}", self.some_string(), ""] +
                             (self.upload_ids[-3:] if self.upload_ids else []))
        chunk = r.choice([1, 7, 64, 1024, 65536])
        messages = []
        offset = 0
        for i in range(0, max(len(data), 1), chunk):
            m = cls(upload_id=upload_id if (i == 0 or r.random() < 0.2) else "",
                    filename=(r.choice(["a.ply", "b.xyz", "c.txt", "", "../../x.ply", "noext", "x" * 300])
                              if i == 0 else ""),
                    write_offset=offset if r.random() < 0.9 else r.choice([-1, offset + 1, 2**62, 0]),
                    data=data[i:i + chunk])
            offset += len(data[i:i + chunk])
            messages.append(m)
            if len(messages) >= 40:
                break
        if r.random() < 0.85:
            messages[-1].finish_write = True
        if r.random() < 0.2:
            messages.append(self.mutate_message(messages[-1]))
        self.per_call["grpc Upload"] += 1
        self.sent += len(messages)
        self.upload_ids.append(upload_id) if upload_id else None
        try:
            cloud = self.stub.Upload(iter(messages), timeout=20)
            self.codes["grpc OK"] += 1
            if cloud.id and cloud.id not in self.cloud_ids:
                self.cloud_ids.append(cloud.id)
        except grpc.RpcError as e:
            self.check_status("Upload", e.code(), e.details(), f"{len(messages)} messages, first {messages[0]}"[:400])

    # ---- HTTP ---------------------------------------------------------------------------------------

    ROUTES = [("POST", "/v1/clouds"), ("GET", "/v1/clouds/{id}"), ("DELETE", "/v1/clouds/{id}"),
              ("POST", "/v1/jobs"), ("GET", "/v1/jobs"), ("GET", "/v1/jobs/{id}"), ("POST", "/v1/jobs/{id}:cancel"),
              ("GET", "/v1/jobs/{id}/events"), ("GET", "/v1/jobs/{id}/result"), ("GET", "/"), ("GET", "/index.html"),
              ("GET", "/three/three.module.js"), ("OPTIONS", "/v1/jobs"), ("GET", "/healthz")]

    def some_id(self):
        r = self.rng
        s = self.some_string()
        if r.random() < 0.8:
            return urllib.parse.quote(s, safe="")
        # Unescaped where http.client lets it through (printable ASCII), escaped elsewhere.
        return "".join(c if 33 <= ord(c) < 127 else urllib.parse.quote(c, safe="") for c in s)

    def http_request(self):
        r = self.rng
        method, template = r.choice(self.ROUTES)
        if r.random() < 0.15:
            method = r.choice(["GET", "POST", "DELETE", "PUT", "PATCH", "HEAD", "OPTIONS"])
        path = template.replace("{id}", self.some_id())
        if r.random() < 0.1:
            path = r.choice(["/v1", "/v1/", "/v1/jobs/", "//v1/jobs", "/v1/jobs/a/b/c", "/../../etc/passwd",
                             "/v1/clouds/" + "x" * 3000, "/%2e%2e/%2e%2e/", "/v1/jobs:cancel"])
        query = []
        if r.random() < 0.4:
            for _ in range(r.randint(1, 3)):
                key = r.choice(["limit", "state", "filename", "include_result", "x", "limit"])
                value = r.choice(["", "-1", "abc", "5", "18446744073709551616", "QUEUED", "RUNNING", "a.ply",
                                  "../x.ply", "%00", "1e9"])
                query.append(f"{key}={urllib.parse.quote(value)}")
        if query:
            path += "?" + "&".join(query)
        headers = {}
        if r.random() < 0.5:
            headers["Content-Type"] = r.choice(["application/json", "application/octet-stream", "text/plain",
                                                "multipart/form-data; boundary=x", "nonsense"])
        if r.random() < 0.2:
            headers["Range"] = r.choice(["bytes=0-10", "bytes=-5", "bytes=99999999-", "bytes=5-1", "bytes=a-b",
                                         "items=0-1", "bytes=0-1,3-4"])
        if r.random() < 0.1:
            headers["Last-Event-ID"] = r.choice(["0", "-1", "abc", "999999999999999999999"])
        if r.random() < 0.1:
            headers["Origin"] = r.choice(["http://evil.example", "null", ""])
        body = None
        if method in ("POST", "PUT", "PATCH") or r.random() < 0.05:
            body = self.http_body(template)
        return method, path, headers, body

    def http_body(self, template):
        r = self.rng
        from google.protobuf import json_format
        if template == "/v1/clouds":
            return self.some_file() if r.random() < 0.7 else sphere_ply(r.choice([1, 3, 50]))
        choice = r.random()
        if choice < 0.45:
            spec = self.mutate_message(r.choice(self.seeds("Submit")).spec)
            text = json_format.MessageToJson(spec)
        elif choice < 0.65:
            spec = self.pb.JobSpec()
            self.fill(spec, 0)
            try:
                text = json_format.MessageToJson(spec)
            except Exception:  # NaN and friends print fine; anything else: send the text form
                text = str(spec)
        elif choice < 0.75:
            text = "[" * r.choice([10, 1000, 100000]) + "]" * r.choice([0, 10])
        elif choice < 0.85:
            text = json.dumps({"render": {"cloudId": self.some_string(), "width": r.choice(["12", 1.5, None, [], {}]),
                               "unknownField": 1}})
        else:
            base = json_format.MessageToJson(r.choice(self.seeds("Submit")).spec)
            return self.mutate_bytes(base.encode())
        return text.encode("utf-8", "surrogatepass")

    def fuzz_http_once(self):
        method, path, headers, body = self.http_request()
        self.per_call["http " + method] += 1
        self.sent += 1
        conn = http.client.HTTPConnection("127.0.0.1", self.http_port,
                                          timeout=0.3 if "/events" in path else self.rng.choice([0.5, 2]))
        desc = f"{method} {path[:200]} {headers} body={body[:100] if body else None!r}"
        try:
            conn.request(method, path, body=body, headers=headers)
            reply = conn.getresponse()
            streaming = reply.getheader("Content-Type", "").startswith("text/event-stream")
            data = b"" if streaming else reply.read(1 << 20)
            self.codes[f"http {reply.status}"] += 1
            if reply.status >= 500 and reply.status not in (501, 503):
                self.fail(f"HTTP {reply.status}", f"{desc} -> {data[:300]!r}")
            elif data.startswith(b"{") and reply.getheader("Content-Type", "").startswith("application/json"):
                try:
                    status = json.loads(data)
                except ValueError:
                    status = None
                if isinstance(status, dict) and set(status) >= {"code", "message"} and status["code"] in (2, 13):
                    self.fail(f"HTTP status body code {status['code']}", f"{desc} -> {data[:300]!r}")
        except (socket.timeout, TimeoutError):
            self.codes["http client timeout"] += 1  # an event stream, or a slow job: not the server's fault
        except (ConnectionError, http.client.HTTPException) as e:
            self.codes[f"http {type(e).__name__}"] += 1
            if not self.alive():
                self.fail("HTTP connection", f"{e!r}: the server died on {desc}")
        finally:
            conn.close()

    def fuzz_raw_http_once(self):
        """Bytes that are barely HTTP: bad request lines, huge headers, broken chunked bodies."""
        r = self.rng
        self.sent += 1
        self.per_call["http raw"] += 1
        payload = r.choice([
            b"GET / HTTP/1.1\r\n\r\n", b"\x00\x01\x02garbage\r\n\r\n", b"GET /v1/jobs HTTP/9.9\r\nHost: x\r\n\r\n",
            b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Length: 99999999\r\n\r\n{",
            b"POST /v1/clouds HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\nabc\r\n",
            b"POST /v1/clouds HTTP/1.1\r\nHost: x\r\nContent-Length: -1\r\n\r\n",
            b"GET /v1/jobs HTTP/1.1\r\nHost: x\r\nX: " + b"a" * 70000 + b"\r\n\r\n",
            b"GET /" + b"a" * 20000 + b" HTTP/1.1\r\n\r\n",
            b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Length: 5\r\n\r\n{\"a\"",
        ])
        payload = self.mutate_bytes(payload) if r.random() < 0.4 else payload
        try:
            with socket.create_connection(("127.0.0.1", self.http_port), timeout=1) as s:
                s.sendall(payload)
                head = s.recv(64)
                if head.startswith(b"HTTP/1.1 5") and not head.startswith((b"HTTP/1.1 501", b"HTTP/1.1 503")):
                    self.fail("raw HTTP answered 5xx", f"{payload[:200]!r} -> {head!r}")
                self.codes["http raw answered" if head else "http raw closed"] += 1
        except (socket.timeout, TimeoutError, ConnectionError):
            self.codes["http raw timeout/reset"] += 1
        if not self.alive():
            self.fail("raw HTTP", f"the server died on {payload[:200]!r}")

    # ---- The run ------------------------------------------------------------------------------------

    def run(self):
        import grpc
        from surfel.v1 import surfel_pb2_grpc
        from health_check import health_pb2_grpc
        a = self.a
        shutil.rmtree(a.work_dir, ignore_errors=True)
        os.makedirs(a.work_dir)
        port_file, http_port_file = os.path.join(a.work_dir, "port"), os.path.join(a.work_dir, "http-port")
        log = open(os.path.join(a.work_dir, "server.log"), "w")
        self.server = subprocess.Popen(
            [a.server_bin, "--port", "0", "--port-file", port_file, "--data-dir", os.path.join(a.work_dir, "data"),
             "--http", "127.0.0.1:0", "--http-port-file", http_port_file, "--log-level", "warn",
             "--workers", "2", "--max-queued", "32", "--max-upload-mb", "4", "--max-points", "200000"],
            stdout=log, stderr=log)
        try:
            for _ in range(3000):
                if os.path.exists(http_port_file) and os.path.exists(port_file):
                    break
                if not self.alive():
                    sys.exit("api-fuzz: surfel-server exited during start:\n" + open(log.name).read()[-3000:])
                time.sleep(0.01)
            time.sleep(0.05)
            self.port, self.http_port = int(open(port_file).read()), int(open(http_port_file).read())
            self.channel = grpc.insecure_channel(f"127.0.0.1:{self.port}")
            self.stub = surfel_pb2_grpc.SurfelStub(self.channel)
            self.health = health_pb2_grpc.HealthStub(self.channel)
            self.good_ply = sphere_ply(300)
            self.cloud_ids.append(self.stub.Upload(iter([self.pb.UploadRequest(
                upload_id="seed", filename="seed.ply", data=self.good_ply, finish_write=True)]), timeout=30).id)
            self.stub.Submit(self.pb.SubmitRequest(spec=self.pb.JobSpec(
                simplify=self.pb.SimplifyJob(cloud_id=self.cloud_ids[0], target=100))), timeout=10)
            from google.protobuf import message_factory
            classes = {}
            calls = self.grpc_calls()
            for _, _, descriptor, _ in calls:
                classes[descriptor.full_name] = message_factory.GetMessageClass(descriptor) \
                    if hasattr(message_factory, "GetMessageClass") else \
                    message_factory.MessageFactory().GetPrototype(descriptor)
            self._classes = classes
            print(f"api-fuzz: {len(calls)} gRPC methods ({', '.join(c[0] for c in calls)}), "
                  f"{len(self.ROUTES)} HTTP routes; seed {a.seed}; {a.messages} messages"
                  + (f" or {a.seconds} s" if a.seconds else ""))
            start = time.monotonic()
            last_rss = 0
            while self.sent < a.messages or (a.seconds and time.monotonic() - start < a.seconds):
                x = self.rng.random()
                if x < 0.55:
                    self.fuzz_grpc_once(calls, classes)
                elif x < 0.97:
                    self.fuzz_http_once()
                else:
                    self.fuzz_raw_http_once()
                if self.sent - last_rss >= 100:
                    last_rss = self.sent
                    self.sample_rss()
                    if not self.alive():
                        self.fail("server", f"exited with {self.server.returncode} after {self.sent} messages")
                        break
                    if len(self.job_ids) > 200:
                        self.job_ids = self.job_ids[-100:]
                    if len(self.upload_ids) > 200:
                        self.upload_ids = self.upload_ids[-100:]
                if len(self.failures) >= 20:
                    break
            elapsed = time.monotonic() - start
            # Still serving, and it stops cleanly.
            if self.alive():
                try:
                    status = self.health.Check(self.health_pb.HealthCheckRequest(service="surfel.v1.Surfel"),
                                               timeout=30).status
                    if status != self.health_pb.HealthCheckResponse.SERVING:
                        self.fail("health", f"status {status} after the run")
                    self.stub.ListJobs(self.pb.ListJobsRequest(limit=1000), timeout=30)
                except grpc.RpcError as e:
                    self.fail("after the run", f"{e.code()}: {e.details()}")
                self.sample_rss()
                self.server.send_signal(signal.SIGTERM)
                try:
                    rc = self.server.wait(timeout=60)
                    if rc != 0:
                        self.fail("SIGTERM", f"exit status {rc}")
                except subprocess.TimeoutExpired:
                    self.fail("SIGTERM", "the server did not stop within 60 s")
            else:
                self.fail("server", f"dead at the end (exit status {self.server.returncode})")
            print(f"api-fuzz: {self.sent} messages in {elapsed:.1f} s ({self.sent / max(elapsed, 1e-9):.0f}/s); "
                  f"peak server RSS {self.peak_rss_mb:.0f} MiB (limit {a.max_rss_mb}); "
                  f"{len(self.cloud_ids)} clouds and {len(self.job_ids)} jobs made")
            print("api-fuzz: answers: " + ", ".join(f"{k} {v}" for k, v in sorted(self.codes.items())))
            print("api-fuzz: calls: " + ", ".join(f"{k} {v}" for k, v in sorted(self.per_call.items()) if v))
            print(f"api-fuzz: undecodable protobuf payloads (gRPC's own INTERNAL before any handler): "
                  f"{self.undecodable}")
            if self.failures:
                tail = open(log.name).read()[-4000:]
                print("api-fuzz: server log tail:\n" + tail, file=sys.stderr)
                print(f"api-fuzz: FAILED ({len(self.failures)} failures)", file=sys.stderr)
                return 1
            print("api-fuzz: 0 crashes, 0 INTERNAL or UNKNOWN from the service, RSS bounded: passed")
            return 0
        finally:
            if self.server.poll() is None:
                self.server.kill()
                self.server.wait()


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--server-bin", required=True)
    ap.add_argument("--proto-dir", required=True)
    ap.add_argument("--work-dir", required=True)
    ap.add_argument("--messages", type=int, default=None, help="messages to send (default 10000)")
    ap.add_argument("--seconds", type=float, default=0, help="run at least this long (bench); 0 = by count")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--max-rss-mb", type=float, default=1536, help="the server's RSS must stay below this")
    ap.add_argument("--unbounded-costs", action="store_true",
                    help="let valid but costly options through (exercises admission control, item 2)")
    a = ap.parse_args()
    if a.messages is None:
        a.messages = 0 if a.seconds else 10000
    generate(a.proto_dir, os.path.join(a.work_dir + "-gen"))
    from surfel.v1 import surfel_pb2
    from health_check import health_pb2
    return Fuzzer(a, surfel_pb2, health_pb2, None).run()


if __name__ == "__main__":
    sys.exit(main())

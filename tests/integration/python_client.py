#!/usr/bin/python3
"""A client nobody on the team wrote: Python grpcio (Debian's python3-grpcio) with stubs generated
from proto/surfel/v1/surfel.proto by grpc_tools, against the real surfel-server.

Checks: health (SERVING), upload -> simplify -> PLY counted, upload -> render -> EXR bytes,
a malformed upload -> INVALID_ARGUMENT (and the server still serves), NOT_FOUND for unknown ids,
SIGTERM -> exit 0.
"""
import argparse
import math
import os
import shutil
import signal
import struct
import subprocess
import sys
import time


def generate(proto_dir, out_dir):
    from grpc_tools import protoc
    os.makedirs(out_dir, exist_ok=True)
    # The standard health proto, under a module path that does not shadow the grpc package (the
    # service keeps its name grpc.health.v1.Health: that comes from the proto's package).
    health_dir = os.path.join(out_dir, "src", "health_check")
    os.makedirs(health_dir, exist_ok=True)
    shutil.copy("/usr/share/grpc-proto/grpc/health/v1/health.proto", health_dir)
    args = ["protoc", f"-I{proto_dir}", f"-I{os.path.join(out_dir, 'src')}",
            f"--python_out={out_dir}", f"--grpc_python_out={out_dir}",
            "surfel/v1/surfel.proto", "health_check/health.proto"]
    if protoc.main(args) != 0:
        sys.exit("protoc failed")
    for d in ["surfel", "surfel/v1", "health_check"]:
        open(os.path.join(out_dir, d, "__init__.py"), "a").close()
    sys.path.insert(0, out_dir)


def sphere_ply(n):
    """An ASCII PLY of n points on the unit sphere (Fibonacci lattice)."""
    lines = ["ply", "format ascii 1.0", f"element vertex {n}",
             "property float x", "property float y", "property float z", "end_header"]
    golden = math.pi * (3 - math.sqrt(5))
    for i in range(n):
        z = 1 - 2 * (i + 0.5) / n
        r = math.sqrt(1 - z * z)
        lines.append(f"{r * math.cos(golden * i):.6f} {r * math.sin(golden * i):.6f} {z:.6f}")
    return ("\n".join(lines) + "\n").encode()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--server-bin", required=True)
    ap.add_argument("--proto-dir", required=True)
    ap.add_argument("--work-dir", required=True)
    a = ap.parse_args()
    shutil.rmtree(a.work_dir, ignore_errors=True)
    generate(a.proto_dir, os.path.join(a.work_dir, "gen"))

    import grpc
    from health_check import health_pb2, health_pb2_grpc
    from surfel.v1 import surfel_pb2 as pb, surfel_pb2_grpc as rpc

    port_file = os.path.join(a.work_dir, "port")
    server = subprocess.Popen([a.server_bin, "--port", "0", "--data-dir", os.path.join(a.work_dir, "data"),
                               "--port-file", port_file, "--log-level", "warn"])
    try:
        for _ in range(1000):
            if os.path.exists(port_file):
                break
            time.sleep(0.01)
        port = int(open(port_file).read())
        channel = grpc.insecure_channel(f"127.0.0.1:{port}")
        stub = rpc.SurfelStub(channel)

        health = health_pb2_grpc.HealthStub(channel)
        for service in ["", "surfel.v1.Surfel"]:
            status = health.Check(health_pb2.HealthCheckRequest(service=service)).status
            assert status == health_pb2.HealthCheckResponse.SERVING, (service, status)

        def upload(name, data, chunk=64 * 1024):
            def requests():
                for off in range(0, max(len(data), 1), chunk):
                    yield pb.UploadRequest(upload_id=name.replace(".", "-"), filename=name, write_offset=off,
                                           data=data[off:off + chunk], finish_write=off + chunk >= len(data))
            return stub.Upload(requests())

        cloud = upload("sphere.ply", sphere_ply(3000))
        assert cloud.points == 3000, cloud
        assert cloud.format == "ply-ascii", cloud.format
        assert list(cloud.attributes) == [], cloud.attributes  # positions only

        def run(spec):
            job = stub.Submit(pb.SubmitRequest(spec=spec))
            result, data, failed = None, b"", None
            for ev in stub.Watch(pb.WatchRequest(job_id=job.id, include_result=True)):
                kind = ev.WhichOneof("event")
                if kind == "finished":
                    result = ev.finished
                elif kind == "result_chunk":
                    data += ev.result_chunk.data
                elif kind == "failed":
                    failed = ev.failed
            assert failed is None, failed
            return result, data

        result, data = run(pb.JobSpec(simplify=pb.SimplifyJob(cloud_id=cloud.id, target=250,
                                                              method=pb.SimplifyJob.HIERARCHICAL)))
        header = data[:data.index(b"end_header")].decode()
        assert "element vertex 250" in header, header
        assert result.media_type == "application/ply" and result.points == 250, result

        result, data = run(pb.JobSpec(render=pb.RenderJob(cloud_id=cloud.id, width=32, height=24)))
        assert result.media_type == "image/x-exr", result
        assert struct.unpack("<I", data[:4])[0] == 20000630, "not an OpenEXR file"  # EXR magic
        assert len(data) == result.size_bytes

        try:
            upload("broken.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n")
            raise AssertionError("malformed upload accepted")
        except grpc.RpcError as e:
            assert e.code() == grpc.StatusCode.INVALID_ARGUMENT, e.code()
            assert "broken.ply" in e.details(), e.details()

        jobs = stub.ListJobs(pb.ListJobsRequest()).jobs  # still serving
        assert len(jobs) == 2 and all(j.state == pb.SUCCEEDED for j in jobs), jobs

        for call, req in [(stub.GetJob, pb.GetJobRequest(job_id="nope")),
                          (stub.GetCloud, pb.GetCloudRequest(cloud_id="nope"))]:
            try:
                call(req)
                raise AssertionError("unknown id answered")
            except grpc.RpcError as e:
                assert e.code() == grpc.StatusCode.NOT_FOUND, e.code()

        server.send_signal(signal.SIGTERM)
        assert server.wait(timeout=30) == 0
        print("python grpcio client: all checks passed")
    finally:
        if server.poll() is None:
            server.kill()


if __name__ == "__main__":
    main()

#!/usr/bin/python3
"""The wait after the last byte of an upload: from the moment gRPC takes the last UploadRequest
(finish_write) from the client's iterator to the Cloud answer; and the whole upload, from the
first UploadRequest taken to the answer. For each LABEL=SERVER-BINARY, a
fresh surfel-server on a fresh data dir per round (nothing deduplicated), rounds interleaved,
median and min. The client is Python grpcio (Debian's python3-grpcio, stubs generated from
proto/ with grpc_tools) sending 256 KiB chunks as fast as gRPC takes them, or with --pace-ms=MS
between chunks (a client slower than the server's writer: nothing queued at the last byte).
usage: bench/upload_after_last_byte.py FILE ROUNDS [--pace-ms=MS] label=path/to/surfel-server [label=...]"""
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CHUNK = 256 << 10


def stubs(out_dir):
    from grpc_tools import protoc
    if protoc.main(["protoc", f"-I{ROOT}/proto", f"--python_out={out_dir}", f"--grpc_python_out={out_dir}",
                    "surfel/v1/surfel.proto"]) != 0:
        sys.exit("protoc failed")
    for d in ["surfel", "surfel/v1"]:
        open(os.path.join(out_dir, d, "__init__.py"), "a").close()
    sys.path.insert(0, out_dir)


PACE_S = 0.0


def one(server_bin, data, pb, pb_grpc, grpc):
    d = tempfile.mkdtemp(prefix="upl-")
    port_file = d + "/port"
    srv = subprocess.Popen([server_bin, "--port", "0", "--port-file", port_file, "--data-dir", d + "/d",
                            "--log-level", "warn"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        while not os.path.exists(port_file) or not open(port_file).read().strip():
            time.sleep(0.001)
        channel = grpc.insecure_channel("127.0.0.1:" + open(port_file).read().strip())
        stub = pb_grpc.SurfelStub(channel)
        last, first = [], []

        def requests():
            first.append(time.perf_counter())
            for off in range(0, len(data), CHUNK):
                final = off + CHUNK >= len(data)
                r = pb.UploadRequest(upload_id="bench", filename="f.ply", write_offset=off,
                                     data=data[off:off + CHUNK], finish_write=final)
                if PACE_S and off:
                    time.sleep(PACE_S)
                if final:
                    last.append(time.perf_counter())
                yield r
        cloud = stub.Upload(requests(), timeout=120)
        answered = time.perf_counter()
        assert cloud.points > 0 and not cloud.deduplicated, cloud
        channel.close()
        return (answered - last[0]) * 1000, (answered - first[0]) * 1000
    finally:
        srv.send_signal(signal.SIGTERM)
        srv.wait()
        shutil.rmtree(d)


def main():
    global PACE_S
    path, rounds = sys.argv[1], int(sys.argv[2])
    args = sys.argv[3:]
    if args and args[0].startswith("--pace-ms="):
        PACE_S = float(args.pop(0).split("=", 1)[1]) / 1000
    bins = [a.split("=", 1) for a in args]
    out = tempfile.mkdtemp(prefix="upl-stubs-")
    stubs(out)
    import grpc
    from surfel.v1 import surfel_pb2 as pb, surfel_pb2_grpc as pb_grpc
    data = open(path, "rb").read()
    ms = {label: [] for label, _ in bins}
    whole = {label: [] for label, _ in bins}
    for _, b in bins:
        one(b, data, pb, pb_grpc, grpc)  # warm-up
    for _ in range(rounds):
        for label, b in bins:
            after_last, total = one(b, data, pb, pb_grpc, grpc)
            ms[label].append(after_last)
            whole[label].append(total)
    print(f"{os.path.basename(path)}: {len(data)} bytes, {rounds} rounds, pace {PACE_S * 1000:g} ms, "
          f"load {os.getloadavg()[0]:.2f}")
    for label, v in ms.items():
        print(f"{label}: last byte -> answer median {statistics.median(v):.1f} ms, min {min(v):.1f} ms "
              f"({' '.join(f'{x:.0f}' for x in v)}); whole upload median {statistics.median(whole[label]):.1f} ms, "
              f"min {min(whole[label]):.1f} ms")
    shutil.rmtree(out)


if __name__ == "__main__":
    main()

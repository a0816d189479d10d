#!/usr/bin/python3
"""POST /v1/clouds streams its body to disk: 1 GiB sent chunked (no Content-Length) to a real
surfel-server whose --max-upload-mb is 1024 goes through the HTTP front and the upload session
piece by piece while the server's RSS grows by less than 64 MiB; the byte past the limit is
refused with 429 and the part file removed. (An accepted upload is then parsed, which reads the
file: that memory belongs to the parser, the same for gRPC, not to the transport.)"""
import argparse
import os
import sys
import threading
import time
import urllib.error
import urllib.request

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from surfel_http import Server  # noqa: E402


def rss_mib(pid):
    for line in open(f"/proc/{pid}/status"):
        if line.startswith("VmRSS"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--server-bin", required=True)
    ap.add_argument("--work-dir", required=True)
    a = ap.parse_args()
    server = Server(a.server_bin, a.work_dir, ["--max-upload-mb", "1024"])
    try:
        before = rss_mib(server.proc.pid)
        peak = [before]
        done = threading.Event()

        def sample():
            while not done.is_set():
                peak[0] = max(peak[0], rss_mib(server.proc.pid))
                time.sleep(0.02)
        threading.Thread(target=sample, daemon=True).start()

        block = b"0 0 0\n" * (1 << 16)  # 384 KiB of XYZ
        total = (1 << 30) + len(block)

        def body():
            for _ in range(0, total, len(block)):
                yield block
        start = time.monotonic()
        req = urllib.request.Request(server.base + "/v1/clouds?filename=big.xyz", data=body(), method="POST")
        try:
            urllib.request.urlopen(req, timeout=300)
            raise AssertionError("an upload over --max-upload-mb was accepted")
        except urllib.error.HTTPError as e:
            assert e.code == 429, (e.code, e.read())
            assert b"exceeds the limit of 1073741824 bytes" in e.read()
        seconds = time.monotonic() - start
        done.set()
        growth = peak[0] - before
        print(f"1 GiB streamed in {seconds:.1f} s ({1024 / seconds:.0f} MiB/s); "
              f"server RSS {before:.0f} MiB -> peak {peak[0]:.0f} MiB (+{growth:.1f})")
        assert growth < 64, f"the server's RSS grew by {growth:.0f} MiB while streaming"
        uploads = os.path.join(a.work_dir, "data", "uploads")
        assert not os.path.isdir(uploads) or os.listdir(uploads) == [], os.listdir(uploads)
    except BaseException:
        print("server log:\n" + server.read_log())
        raise
    finally:
        server.stop()
    print("streaming upload test passed")


if __name__ == "__main__":
    main()

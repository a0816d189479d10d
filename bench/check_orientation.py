#!/usr/bin/python3
"""Acceptance check of `surfel normals` orientation (issue 14, item 0), as a user runs it.

For every `<name>_mesh.ply` in the data directory, runs `surfel normals <name>.ply` and reports the
share of normals that agree (dot > 0) with the mesh's area-weighted outward vertex normals (the
cloud is the mesh's vertices, in order). Exit status 1 when a model is under --min (default 99 %).

  /usr/bin/python3 bench/check_orientation.py --surfel BUILD/bin/surfel [--data ../shared/data]
"""
import argparse
import os
import subprocess
import sys
import tempfile

import numpy as np


def read_ply(path):
    """Binary little-endian PLY with float vertex properties and an optional uchar/int face list."""
    with open(path, "rb") as f:
        data = f.read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    elements, current = [], None
    for line in data[:end].decode("ascii").splitlines():
        words = line.split()
        if words[0] == "element":
            current = [words[1], int(words[2]), []]
            elements.append(current)
        elif words[0] == "property":
            current[2].append(words[1:])
    offset, vertices, faces = end, None, None
    for name, count, props in elements:
        if name == "vertex":
            assert all(p[0] == "float" for p in props), path
            dtype = np.dtype([(p[1], "<f4") for p in props])
            vertices = np.frombuffer(data, dtype, count, offset)
            offset += count * dtype.itemsize
        elif name == "face":
            assert props[0][:3] == ["list", "uchar", "int"], path
            dtype = np.dtype([("n", "u1"), ("v", "<i4", 3)])
            faces = np.frombuffer(data, dtype, count, offset)
            assert (faces["n"] == 3).all(), path
            faces = faces["v"]
            offset += count * dtype.itemsize
    return vertices, faces


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    ap = argparse.ArgumentParser()
    ap.add_argument("--surfel", required=True)
    ap.add_argument("--data", default=os.path.join(here, "..", "..", "shared", "data"))
    ap.add_argument("--min", type=float, default=99.0, help="least share outward per model, percent")
    ap.add_argument("args", nargs="*", help="extra arguments for `surfel normals`")
    a = ap.parse_args()
    models = sorted(n[: -len("_mesh.ply")] for n in os.listdir(a.data) if n.endswith("_mesh.ply"))
    worst = 100.0
    with tempfile.TemporaryDirectory() as tmp:
        for m in models:
            mv, faces = read_ply(os.path.join(a.data, m + "_mesh.ply"))
            p = np.stack([mv["x"], mv["y"], mv["z"]], 1).astype(np.float64)
            t0, t1, t2 = p[faces[:, 0]], p[faces[:, 1]], p[faces[:, 2]]
            cross = np.cross(t1 - t0, t2 - t0)
            volume = np.einsum("ij,ij->i", t0, np.cross(t1, t2)).sum() / 6.0
            ref = np.zeros_like(p)
            for k in range(3):
                np.add.at(ref, faces[:, k], cross)
            out = os.path.join(tmp, m + ".ply")
            subprocess.run([a.surfel, "normals", os.path.join(a.data, m + ".ply"), "-o", out, "--quiet"] + a.args,
                           check=True, stdout=subprocess.DEVNULL)
            v, _ = read_ply(out)
            assert len(v) == len(p) and np.array_equal(v["x"], mv["x"]), m
            n = np.stack([v["nx"], v["ny"], v["nz"]], 1).astype(np.float64)
            valid = np.linalg.norm(ref, axis=1) > 0
            share = 100.0 * (np.einsum("ij,ij->i", n, ref)[valid] > 0).mean()
            worst = min(worst, share)
            print(f"{m:10s} {valid.sum():7d} points  {share:6.2f} % outward  (mesh signed volume {volume:.3g})")
    return 0 if worst >= a.min else 1


if __name__ == "__main__":
    sys.exit(main())

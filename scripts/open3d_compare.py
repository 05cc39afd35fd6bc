#!/usr/bin/env python3
"""Compare sdf-geom's signed distance with Open3D's RaycastingScene on the same NGLOD epoch points.

One run does both, on the same machine and the same points:
  1. runs sdf-geom's `epoch` example, which samples the NGLOD epoch mix (1e5 uniform + 2e5
     near-surface + 2e5 surface points, normalised box), times `signed_distance_batch` on it and
     exports the points and our distances as .npy;
  2. times Open3D's `RaycastingScene.compute_signed_distance` on exactly those points (mesh normalised
     the same way: bounding-box centre, longest half-extent 1);
  3. compares the values (distance difference, sign agreement off the surface).

Usage (Open3D from pip, in a virtual environment outside the repository):
  python3 -m venv /tmp/o3dvenv && /tmp/o3dvenv/bin/pip install open3d numpy
  cargo build --release -p sdf-geom --example epoch
  /tmp/o3dvenv/bin/python scripts/open3d_compare.py ../shared/meshes/stanford-bunny.obj [--reps 3]
"""

import argparse
import os
import re
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np
import open3d as o3d


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mesh")
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--threads", type=int, default=0, help="threads for both sides (0: all cores)")
    ap.add_argument("--epoch-bin", default=os.path.join(os.path.dirname(__file__), "..", "target", "release", "examples", "epoch"))
    args = ap.parse_args()

    work = tempfile.mkdtemp(prefix="o3d-compare-")
    pts_path = os.path.join(work, "points.npy")
    ours_path = os.path.join(work, "ours.npy")

    # 1. sdf-geom (its own process, all cores via rayon).
    env = dict(os.environ)
    if args.threads > 0:
        env["RAYON_NUM_THREADS"] = str(args.threads)
    out = subprocess.run(
        [args.epoch_bin, args.mesh, "--export", pts_path, "--out", ours_path, "--reps", str(args.reps)],
        check=True, capture_output=True, text=True, env=env,
    ).stdout
    print("---- sdf-geom (epoch example) ----")
    print(out.strip())
    m = re.search(r"epoch 5e5 signed: ([0-9.]+) s", out)
    ours_s = float(m.group(1)) if m else float("nan")
    m = re.search(r"epoch CPU time: ([0-9.]+) s", out)
    ours_cpu = float(m.group(1)) if m else float("nan")

    # 2. Open3D on the same points.
    pts = np.load(pts_path).astype(np.float32)
    ours = np.load(ours_path)
    legacy = o3d.io.read_triangle_mesh(args.mesh)
    v = np.asarray(legacy.vertices, dtype=np.float64)
    f = np.asarray(legacy.triangles, dtype=np.int64)
    used = v[np.unique(f)]
    lo, hi = used.min(0), used.max(0)
    center = (lo + hi) / 2
    scale = 1.0 / ((hi - lo).max() / 2)
    vn = ((v - center) * scale).astype(np.float32)
    tmesh = o3d.t.geometry.TriangleMesh()
    tmesh.vertex.positions = o3d.core.Tensor(vn)
    tmesh.triangle.indices = o3d.core.Tensor(f.astype(np.int32))
    t0 = time.perf_counter()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(tmesh)
    q = o3d.core.Tensor(pts)
    scene.compute_distance(q[:16])  # builds the BVH
    build_s = time.perf_counter() - t0
    best = float("inf")
    best_cpu = float("inf")
    theirs = None
    for _ in range(args.reps):
        r0 = resource.getrusage(resource.RUSAGE_SELF)
        t0 = time.perf_counter()
        theirs = scene.compute_signed_distance(q, nthreads=args.threads).numpy()
        best = min(best, time.perf_counter() - t0)
        r1 = resource.getrusage(resource.RUSAGE_SELF)
        best_cpu = min(best_cpu, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime))
    print("---- Open3D", o3d.__version__, "RaycastingScene.compute_signed_distance ----")
    print(f"scene build + first query: {build_s * 1e3:.1f} ms")
    print(f"epoch CPU time: {best_cpu:.2f} s (all threads)")
    print(f"epoch 5e5 signed: {best:.3f} s (best of {args.reps}), {len(pts) / best / 1e6:.2f} M points/s")

    # 3. Agreement.
    diff = np.abs(np.abs(theirs) - np.abs(ours))
    off = np.abs(ours) > 1e-4
    agree = np.mean((theirs[off] < 0) == (ours[off] < 0))
    print("---- comparison ----")
    print(f"|distance| max abs difference: {diff.max():.2e} (mean {diff.mean():.2e})")
    print(f"sign agreement off the surface (|d| > 1e-4): {agree * 100:.3f}% of {off.sum()} points")
    threads = args.threads if args.threads > 0 else os.cpu_count()
    print(f"speed-up sdf-geom / Open3D: {best / ours_s:.2f}x wall, {best_cpu / ours_cpu:.2f}x CPU time  ({threads} threads each)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

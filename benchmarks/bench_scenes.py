"""Scene generation and per-frame ground-truth distances: how long a generated scene takes, and
our warp distance queries against libigl's on the frame of a handshake where the bodies are closest.

- signed distances of all vertices of body A to body B: libigl (``igl.signed_distance``,
  pseudonormal; rebuilds its tree each call, the baseline) against our warp ``MeshDistance`` (BVH
  refit per frame) unbanded and within the 5 cm band the scenes use, and the full ``PairDistance``
  both ways with the body-part broad phase; median of ``--repeats`` runs each, in this process,
  with the ratio to libigl;
- generation seconds per scene type (one run each: a generation is deterministic and long).

    .venv/bin/python benchmarks/bench_scenes.py [--fps 15] [--types handshake,hug] [--repeats 7]

Writes ``benchmarks/results/scenes.json`` (``--out`` elsewhere). No goals: the figures back the
choice of warp over libigl for the ground truth and tell how long a scene takes.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from results_file import Table, write_results


def median_seconds(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--types", default="handshake,high_five,push,pat_on_back,hug,dance_turn")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", type=Path, default=None, help="results file (default benchmarks/results/scenes.json)")
    args = ap.parse_args()

    import igl

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.body.topology import collision_faces
    from dualhuman_builder.geometry.distance import MeshDistance, get_pair_distance
    from dualhuman_builder.sim.scenes import SceneParams, make_scene

    model = get_body_model()
    faces = model.faces.cpu().numpy()
    closed = faces[collision_faces(faces, model.num_vertices)]
    timings = {}
    for kind in args.types.split(","):
        t0 = time.perf_counter()
        sc = make_scene(SceneParams(type=kind, seed=0, fps=args.fps))
        timings[kind] = (time.perf_counter() - t0, sc.sequence.num_frames)
        if kind == "handshake":
            handshake = sc
    if "handshake" not in timings:
        handshake = make_scene(SceneParams(type="handshake", seed=0, fps=args.fps))
    gap = np.stack([np.nan_to_num(d.astype(np.float32), nan=np.inf) for d in handshake.distances]).min(axis=(0, 2))
    f = int(np.argmin(gap))
    va, vb = (a.vertices()[f].astype(np.float64) for a in handshake.sequence.actors)
    closed64 = closed.astype(np.int64)
    mesh = MeshDistance(closed, model.num_vertices)
    pair = get_pair_distance()

    def with_igl():
        igl.signed_distance(va, vb, closed64, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)

    def with_warp():
        mesh.update(vb)
        mesh.query(va, 1.0)

    def with_warp_band():
        mesh.update(vb)
        mesh.query(va, 0.05)

    def with_pair():
        pair(va, vb, 0.05)

    t_igl, t_warp, t_band, t_pair = (median_seconds(fn, args.repeats) for fn in (with_igl, with_warp, with_warp_band, with_pair))
    print(f"signed distances, {model.num_vertices} vertices of A to B (handshake frame {f}), median of {args.repeats}:")
    print(f"  libigl signed_distance      {1000 * t_igl:8.1f} ms   1.0x")
    print(f"  warp BVH refit + query, 1 m band  {1000 * t_warp:8.1f} ms   {t_igl / t_warp:.1f}x")
    print(f"  warp BVH refit + query, 5 cm band {1000 * t_band:8.1f} ms   {t_igl / t_band:.1f}x")
    print(f"  PairDistance both ways, 5 cm band + broad phase {1000 * t_pair:6.1f} ms   {t_igl / t_pair:.1f}x (of one direction by libigl)")
    print(f"scene generation at {args.fps:g} fps, seed 0 (one run each):")
    for kind, (seconds, frames) in timings.items():
        print(f"  {kind:12s} {seconds:7.1f} s  {frames:4d} frames  {1000 * seconds / frames:6.0f} ms/frame")

    methods = {"igl": t_igl, "warp_1m": t_warp, "warp_5cm": t_band, "pair_distance": t_pair}
    figures = {
        "distances": {"frame": f, "vertices": int(model.num_vertices), "repeats": args.repeats,
                      **{k: {"ms": 1000 * t, "x_igl": t_igl / t} for k, t in methods.items()}},
        "generation": {kind: {"seconds": seconds, "frames": frames, "ms_per_frame": 1000 * seconds / frames}
                       for kind, (seconds, frames) in timings.items()},
    }  # fmt: skip
    labels = {"igl": "`igl.signed_distance` (pseudonormal, unbounded)", "warp_1m": "warp BVH refit + query, 1 m band",
              "warp_5cm": "warp BVH refit + query, 5 cm band (what the scenes use)",
              "pair_distance": "`PairDistance`, both directions, 5 cm band + body-part broad phase"}  # fmt: skip
    tables = [Table(f"signed distances, one handshake frame, {model.num_vertices} vertices of A to B "
                    f"(median of {args.repeats})", ["method", "ms", "x libigl"],
                    [[labels[k], f"distances.{k}.ms", f"distances.{k}.x_igl"] for k in methods]),
              Table(f"scene generation at {args.fps:g} fps, seed 0", ["scene type", "seconds", "frames", "ms/frame"],
                    [[k, f"generation.{k}.seconds", f"generation.{k}.frames", f"generation.{k}.ms_per_frame"]
                     for k in timings])]  # fmt: skip
    path = write_results("scenes", figures, params={"fps": args.fps, "types": args.types.split(","),
                                                    "repeats": args.repeats},
                         tables=tables, out=args.out)  # fmt: skip
    print(f"wrote {path}")

if __name__ == "__main__":
    main()

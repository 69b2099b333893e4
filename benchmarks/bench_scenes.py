"""Scene generation against the generator before any speed work, side by side in the same run, and
our warp distance queries against libigl's on the frame of a handshake where the bodies are closest.

- generation, per case (type and fps, seed 0): the baseline generator (commit ``3ebb27f``, its
  package extracted with ``git archive`` into a temporary folder) and today's, each in a fresh
  process on one torch thread with the same modules imported before the clock starts, one case
  after the other, alternating; seconds (wall and the process's CPU), the ratio baseline/today,
  and whether today's scene meets the quality contract. The goal (issue 39): the hug at 30 fps
  >= 10x faster. The machine's load average is recorded before and after, since a loaded machine
  slows both sides;
- signed distances of all vertices of body A to body B: libigl (``igl.signed_distance``,
  pseudonormal; rebuilds its tree each call) against our warp ``MeshDistance`` (BVH refit per
  frame) unbanded and within the 5 cm band the scenes use, and the full ``PairDistance`` both ways
  with the body-part broad phase; median of ``--repeats`` runs each, with the ratio to libigl.

    .venv/bin/python benchmarks/bench_scenes.py [--cases hug@30,handshake@15] [--repeats 7] [--baseline 3ebb27f]

Writes ``benchmarks/results/scenes.json`` (``--out`` elsewhere).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from results_file import Goal, Table, write_results

ROOT = Path(__file__).resolve().parents[1]
#: The generator before any speed work (issue 39's baseline).
BASELINE_COMMIT = "3ebb27f"
CASES = "hug@30,hug@15,handshake@15,high_five@15,push@15,pat_on_back@15,dance_turn@15"
#: Issue 39: a scene (the 5-second hug at 30 fps) at least this many times faster than the baseline.
GOAL_SPEEDUP = 10.0

#: Run in a fresh process (``PYTHONPATH`` picks the generator): one scene, timed from after the
#: body model and the generator's lazily imported modules are loaded; prints one JSON line.
_CHILD = r"""
import json, sys, time
import torch
torch.set_num_threads(1)
import roma, scipy.ndimage  # noqa: F401  (the generator imports them lazily; loaded before the clock)
import dualhuman_builder
from dualhuman_builder.body.model import get_body_model
from dualhuman_builder.sim import scenes
import dualhuman_builder.sim.quality, dualhuman_builder.geometry.distance  # noqa: F401
kind, fps = sys.argv[1], float(sys.argv[2])
model = get_body_model()
c0, t0 = time.process_time(), time.perf_counter()
sc = scenes.make_scene(scenes.SceneParams(type=kind, seed=0, fps=fps), model=model)
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
print(json.dumps({"seconds": wall, "cpu_seconds": cpu, "frames": sc.sequence.num_frames, "package": dualhuman_builder.__file__,
                  "generator_version": getattr(scenes, "GENERATOR_VERSION", None), "draws": sc.stats.get("draws"),
                  "contract_failures": scenes.contract_failures(sc.stats),
                  "max_penetration_mm": 1000 * sc.stats["max_penetration_m"]}))
"""


def median_seconds(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def generate_in_child(path: Path, kind: str, fps: float) -> dict:
    """One scene made in a fresh process whose ``dualhuman_builder`` comes from ``path``."""
    env = dict(os.environ, PYTHONPATH=str(path), OMP_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", _CHILD, kind, repr(fps)], env=env, cwd=tempfile.gettempdir(),
                         capture_output=True, text=True, check=False)  # fmt: skip
    if out.returncode:
        raise RuntimeError(f"generating {kind} at {fps:g} fps from {path} failed:\n{out.stderr[-3000:]}")
    result = json.loads(out.stdout.strip().splitlines()[-1])
    if not result["package"].startswith(str(path)):
        raise RuntimeError(f"the child imported {result['package']}, not the package under {path}")
    return result


def generation(cases: list[tuple[str, float]], baseline: str) -> dict:
    """Each case made by the baseline and by today's generator, alternating, in fresh processes."""
    out = {"load_before": list(os.getloadavg())}
    with tempfile.TemporaryDirectory(prefix="bench-scenes-baseline-") as tmp:
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", baseline, "dualhuman_builder"], capture_output=True,
                                 check=True).stdout  # fmt: skip
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        for kind, fps in cases:
            old = generate_in_child(Path(tmp), kind, fps)
            new = generate_in_child(ROOT, kind, fps)
            key = f"{kind}@{fps:g}"
            out[key] = {"baseline": old, "today": new, "speedup": old["seconds"] / new["seconds"],
                        "speedup_cpu": old["cpu_seconds"] / new["cpu_seconds"], "contract_met": not new["contract_failures"]}
            print(f"  {key:16s} baseline {old['seconds']:6.1f} s ({old['cpu_seconds']:6.1f} s CPU)   today "
                  f"{new['seconds']:6.1f} s ({new['cpu_seconds']:6.1f} s CPU)   {out[key]['speedup']:5.1f}x "
                  f"({out[key]['speedup_cpu']:.1f}x CPU)   contract {'met' if not new['contract_failures'] else new['contract_failures']}",
                  flush=True)  # fmt: skip
    out["load_after"] = list(os.getloadavg())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default=CASES, help="type@fps, comma-separated (seed 0 each)")
    ap.add_argument("--baseline", default=BASELINE_COMMIT, help="the commit whose generator is the baseline")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--skip-distances", action="store_true", help="only the generation timings")
    ap.add_argument("--out", type=Path, default=None, help="results file (default benchmarks/results/scenes.json)")
    args = ap.parse_args()
    cases = [(c.split("@")[0], float(c.split("@")[1])) for c in args.cases.split(",")]

    print(f"scene generation, seed 0, one torch thread, baseline {args.baseline} against today (fresh process each):")
    gen = generation(cases, args.baseline)
    print(f"load average before {gen['load_before'][0]:.2f}, after {gen['load_after'][0]:.2f}")
    figures = {"generation": gen}
    keys = [f"{k}@{f:g}" for k, f in cases]
    tables = [Table(f"scene generation, seed 0, one torch thread: baseline ({args.baseline}) against today, "
                    "each in a fresh process", ["case", "baseline s", "today s", "x faster", "x faster (CPU s)", "contract met"],
                    [[k, f"generation.{k}.baseline.seconds", f"generation.{k}.today.seconds", f"generation.{k}.speedup",
                      f"generation.{k}.speedup_cpu", f"generation.{k}.contract_met"] for k in keys])]  # fmt: skip
    goals = [Goal(f"generation.{k}.speedup", ">=", GOAL_SPEEDUP, "x", label=f"{k}: faster than {args.baseline}")
             for k in keys if k == "hug@30"]  # fmt: skip
    goals += [Goal(f"generation.{k}.contract_met", ">=", 1, label=f"{k}: today's scene meets the quality contract") for k in keys]

    if not args.skip_distances:
        figures["distances"] = distances(args.repeats)
        labels = {"igl": "`igl.signed_distance` (pseudonormal, unbounded)", "warp_1m": "warp BVH refit + query, 1 m band",
                  "warp_5cm": "warp BVH refit + query, 5 cm band (what the scenes use)",
                  "pair_distance": "`PairDistance`, both directions, 5 cm band + body-part broad phase"}  # fmt: skip
        d = figures["distances"]
        tables.append(Table(f"signed distances, one handshake frame, {d['vertices']} vertices of A to B "
                            f"(median of {args.repeats})", ["method", "ms", "x libigl"],
                            [[labels[k], f"distances.{k}.ms", f"distances.{k}.x_igl"] for k in labels]))  # fmt: skip
    path = write_results("scenes", figures, params={"cases": keys, "baseline": args.baseline, "repeats": args.repeats},
                         goals=goals, tables=tables, out=args.out,
                         notes="Ratios come from the same run, baseline and today alternating; a loaded machine "
                               "slows both (the load average is in figures.generation).")  # fmt: skip
    print(f"wrote {path}")


def distances(repeats: int) -> dict:
    """libigl against warp on the closest frame of a handshake (15 fps, seed 0)."""
    import igl
    import torch

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.body.topology import collision_faces
    from dualhuman_builder.geometry.distance import MeshDistance, get_pair_distance
    from dualhuman_builder.sim.scenes import SceneParams, make_scene

    torch.set_num_threads(1)
    model = get_body_model()
    faces = model.faces.cpu().numpy()
    closed = faces[collision_faces(faces, model.num_vertices)]
    handshake = make_scene(SceneParams(type="handshake", seed=0, fps=15.0), model=model)
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

    t_igl, t_warp, t_band, t_pair = (median_seconds(fn, repeats) for fn in (with_igl, with_warp, with_warp_band, with_pair))
    print(f"signed distances, {model.num_vertices} vertices of A to B (handshake frame {f}), median of {repeats}:")
    print(f"  libigl signed_distance      {1000 * t_igl:8.1f} ms   1.0x")
    print(f"  warp BVH refit + query, 1 m band  {1000 * t_warp:8.1f} ms   {t_igl / t_warp:.1f}x")
    print(f"  warp BVH refit + query, 5 cm band {1000 * t_band:8.1f} ms   {t_igl / t_band:.1f}x")
    print(f"  PairDistance both ways, 5 cm band + broad phase {1000 * t_pair:6.1f} ms   {t_igl / t_pair:.1f}x (of one direction by libigl)")
    methods = {"igl": t_igl, "warp_1m": t_warp, "warp_5cm": t_band, "pair_distance": t_pair}
    return {"frame": f, "vertices": int(model.num_vertices), "repeats": repeats,
            **{k: {"ms": 1000 * t, "x_igl": t_igl / t} for k, t in methods.items()}}  # fmt: skip


if __name__ == "__main__":
    main()

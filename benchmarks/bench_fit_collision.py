"""The collision term as the fitter calls it: one hug fit's collision calls, recorded, then replayed
through fresh terms with different exact bands.

    .venv/bin/python benchmarks/bench_fit_collision.py                 # ~5 min on 2 cores
    .venv/bin/python benchmarks/bench_fit_collision.py --frames 48 --calls 40

A fit of the first ``--frames`` frames of bench_fit's hug (30 fps, ground-truth segments, six
trackers per actor) records the bodies of its first ``--calls`` collision calls (L-BFGS evaluations
and the checks between rounds, with their frame keys, so the sign reuse works as in the fit). Each
setting replays them in order through a new :class:`CollisionTerm`; printed: seconds (median of
``--runs``), and the largest difference of any frame's deepest penetration from the first setting
(every band is exact, so it should read 0; a non-zero value found the flood-fill sign conflict fixed
on 2026-11-23).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def record(model, frames: int, calls: int) -> list:
    from dataclasses import replace

    from bench_fit import inputs
    from dualhuman_builder.fit import collision
    from dualhuman_builder.fit.fitter import FitConfig, fit_actors

    inp = [replace(a, seg_rot=a.seg_rot[:frames], pelvis=a.pelvis[:frames], valid=a.valid[:frames],
                   trk_pos=a.trk_pos[:frames], trk_valid=a.trk_valid[:frames], ankles=a.ankles[:frames])
           for a in inputs(model, frames / 30.0 / 60.0 + 1e-9, 30.0)]  # fmt: skip
    out = []
    call, pen = collision.CollisionTerm.__call__, collision.CollisionTerm.penetration

    def keep(kind, va, vb, keys):
        if len(out) < calls:
            out.append((kind, *(torch.as_tensor(np.asarray(v.detach() if torch.is_tensor(v) else v, np.float32))
                                for v in (va, vb)), list(keys)))  # fmt: skip

    def rec_call(self, va, vb, keys=None, points=None):
        keep("call", va, vb, keys)
        return call(self, va, vb, keys, points)

    def rec_pen(self, va, vb, keys=None):
        keep("pen", va, vb, keys)
        return pen(self, va, vb, keys)

    collision.CollisionTerm.__call__, collision.CollisionTerm.penetration = rec_call, rec_pen
    try:
        fit_actors(model, inp, 30.0, FitConfig(collision=True))
    finally:
        collision.CollisionTerm.__call__, collision.CollisionTerm.penetration = call, pen
    return out


def replay(faces, calls: list, **kw) -> tuple[float, np.ndarray]:
    from dualhuman_builder.geometry.collision import CollisionTerm

    ct = CollisionTerm(faces, **kw)
    depths = []
    t = time.perf_counter()
    for kind, a, b, keys in calls:
        if kind == "call":
            r = ct(a, b, keys=keys, points=lambda body, f, v, ab=(a, b): ab[body][f, v])
            depths.append(r.max_depth_m.numpy())
        else:
            depths.append(ct.penetration(a, b, keys=keys)["max_depth_m"])
    return time.perf_counter() - t, np.concatenate(depths)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=96)
    ap.add_argument("--calls", type=int, default=90)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    from dualhuman_builder.body.model import get_body_model

    model = get_body_model()
    calls = record(model, args.frames, args.calls)
    n = sum(c[1].shape[0] for c in calls)
    print(f"recorded {len(calls)} collision calls of a {args.frames}-frame hug fit ({n} frame pairs)")
    faces = model.faces.cpu().numpy()
    base = None
    for band in (0.01, 0.02, 0.03, 0.04):
        kw = {"band_m": band, "pad_m": 0.01}
        runs = [replay(faces, calls, **kw) for _ in range(args.runs)]
        sec = statistics.median(r[0] for r in runs)
        depth = runs[0][1]
        base = depth if base is None else base
        print(f"band {100 * band:.0f} cm: {sec:6.2f} s ({1000 * sec / n:.2f} ms per frame pair), "
              f"max |depth - band 1 cm| {1000 * np.abs(depth - base).max():.3f} mm")


if __name__ == "__main__":
    main()

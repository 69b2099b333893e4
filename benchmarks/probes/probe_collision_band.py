"""Probe: the width of the collision term's exact band. One hug fit's collision calls, recorded,
then replayed through fresh terms with bands of 1 to 4 cm (decision record 0020).

    .venv/bin/python benchmarks/probes/probe_collision_band.py                 # ~5 min on 2 cores
    .venv/bin/python benchmarks/probes/probe_collision_band.py --frames 48 --calls 40

A fit of the first ``--frames`` frames of bench_fit's hug (30 fps, ground-truth segments, six
trackers per actor, in this process) records the bodies of its first ``--calls`` calls that locate
contacts (``linearise``: the checks that hold contacts through a pass; ``penetration``: the measured
depths; ``__call__``: evaluations located exactly), with their frame keys, so that the sign reuse
works as in the fit. Each setting replays them in order through a new :class:`CollisionTerm`;
printed: seconds (median of
``--runs``), and the largest difference of any frame's deepest penetration from the first setting
(every band is exact, so it must read 0: the goal).

Writes ``benchmarks/results/probe_collision_band.json`` (``--out`` elsewhere).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: bench_fit, results_file

from results_file import Goal, Table, write_results  # noqa: E402

BANDS_M = (0.01, 0.02, 0.03, 0.04)


def record(model, frames: int, calls: int) -> list:
    from dataclasses import replace

    from bench_fit import inputs
    from dualhuman_builder.fit.fitter import FitConfig, fit_actors
    from dualhuman_builder.geometry import collision

    inp = [replace(a, seg_rot=a.seg_rot[:frames], pelvis=a.pelvis[:frames], valid=a.valid[:frames],
                   trk_pos=a.trk_pos[:frames], trk_valid=a.trk_valid[:frames], ankles=a.ankles[:frames])
           for a in inputs(model, frames / 30.0 / 60.0 + 1e-9, 30.0)]  # fmt: skip
    out = []
    term = collision.CollisionTerm
    call, pen, lin = term.__call__, term.penetration, term.linearise

    def keep(kind, va, vb, keys, **kw):
        if len(out) < calls:
            out.append((kind, *(torch.as_tensor(np.asarray(v.detach() if torch.is_tensor(v) else v, np.float32))
                                for v in (va, vb)), None if keys is None else list(keys), kw))  # fmt: skip

    def rec_call(self, va, vb, keys=None, points=None):
        keep("call", va, vb, keys)
        return call(self, va, vb, keys, points)

    def rec_pen(self, va, vb, keys=None):
        keep("pen", va, vb, keys)
        return pen(self, va, vb, keys)

    def rec_lin(self, va, vb, keys=None, margin_m=0.005):
        keep("lin", va, vb, keys, margin_m=margin_m)
        return lin(self, va, vb, keys, margin_m)

    term.__call__, term.penetration, term.linearise = rec_call, rec_pen, rec_lin
    try:
        fit_actors(model, inp, 30.0, FitConfig(collision=True), workers=1)  # in this process, where the calls are recorded
    finally:
        term.__call__, term.penetration, term.linearise = call, pen, lin
    return out


def replay(faces, calls: list, **kw) -> tuple[float, np.ndarray]:
    from dualhuman_builder.geometry.collision import CollisionTerm

    ct = CollisionTerm(faces, **kw)
    depths = []
    t = time.perf_counter()
    for kind, a, b, keys, kw in calls:
        if kind == "call":
            r = ct(a, b, keys=keys, points=lambda body, f, v, ab=(a, b): ab[body][f, v])
            depths.append(r.max_depth_m.numpy())
        elif kind == "lin":
            depths.append(np.asarray(ct.linearise(a, b, keys=keys, **kw).max_depth_m))
        else:
            depths.append(np.asarray(ct.penetration(a, b, keys=keys)["max_depth_m"]))
    return time.perf_counter() - t, np.concatenate(depths)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=96)
    ap.add_argument("--calls", type=int, default=90)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None,
                    help="results file (default benchmarks/results/probe_collision_band.json)")
    args = ap.parse_args()
    from dualhuman_builder.body.model import get_body_model

    model = get_body_model()
    calls = record(model, args.frames, args.calls)
    if not calls:
        raise SystemExit(f"the fit of the first {args.frames} frames located no contacts: raise --frames")
    n = sum(c[1].shape[0] for c in calls)
    print(f"recorded {len(calls)} collision calls of a {args.frames}-frame hug fit ({n} frame pairs)")
    faces = model.faces.cpu().numpy()
    base = None
    rows = []
    for band in BANDS_M:
        kw = {"band_m": band, "pad_m": 0.01}
        runs = [replay(faces, calls, **kw) for _ in range(args.runs)]
        sec = statistics.median(r[0] for r in runs)
        depth = runs[0][1]
        base = depth if base is None else base
        diff_mm = float(1000 * np.abs(depth - base).max())
        rows.append({"band_cm": 100 * band, "seconds": sec, "ms_per_frame_pair": 1000 * sec / n,
                     "runs_s": [r[0] for r in runs], "max_depth_difference_mm": diff_mm})  # fmt: skip
        print(f"band {100 * band:.0f} cm: {sec:6.2f} s ({1000 * sec / n:.2f} ms per frame pair), "
              f"max |depth - band 1 cm| {diff_mm:.3f} mm")
    figures = {"recorded": {"frames": args.frames, "calls": len(calls), "frame_pairs": n}, "bands": rows,
               "max_depth_difference_mm": max(r["max_depth_difference_mm"] for r in rows)}  # fmt: skip
    table = Table(f"{len(calls)} collision calls of a {args.frames}-frame hug fit ({n} frame pairs) replayed, median "
                  f"of {args.runs}", ["band", "seconds", "ms per frame pair", "max depth difference from 1 cm, mm"],
                  [[f"{r['band_cm']:g} cm", f"bands.{k}.seconds", f"bands.{k}.ms_per_frame_pair",
                    f"bands.{k}.max_depth_difference_mm"] for k, r in enumerate(rows)])  # fmt: skip
    path = write_results("probe_collision_band", figures,
                         params={"frames": args.frames, "calls": args.calls, "runs": args.runs, "pad_m": 0.01},
                         goals=[Goal("max_depth_difference_mm", "<=", 0.0, "mm",
                                     label="every band gives every frame's deepest penetration identically")],
                         tables=[table], out=args.out)  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

"""Probe: which tracker offsets the fit should read, on the tuning seeds (decision record 0027).

    .venv/bin/python benchmarks/probes/probe_tracker_offsets.py --keep TAKES      # ~3 min on 2 cores with kept takes

Per take (``--types`` x ``--seeds`` x both presets; tune on seeds 1 and 2, never on the held-out ones of
``bench_fit_accuracy.py``), sync and fuse once, then the fit with the trackers' offsets taken as:
sync's (``sigma_suit_skeleton_m`` 0), weighed a fixed 40 % and 61 % of the way to the protocol site
(61 %: ``FitConfig.sigma_suit_skeleton_m`` 25 mm for every tracker), the site alone, weighed by the take's
own measure of its suit's skeleton (``measured``, the default: :mod:`dualhuman_builder.fit.mounts`), and the
simulated truth (an oracle: what the fit gives when the offsets are right, which no estimator has). Printed and written per variant:
MPJPE, PA-MPJPE and root error (mm) against the scene's truth. Takes are recorded in real time into
``--keep DIR`` when missing there (``DIR/<type>-<seed>[-realistic]/``).

Writes ``benchmarks/results/probe_tracker_offsets.json`` (``--out`` elsewhere).
"""

from __future__ import annotations

import argparse
import copy
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: results_file

from results_file import Table, write_results  # noqa: E402

SITE_M = 0.02
#: variant -> (sigma_suit_skeleton_m, whether the take's shape calibration measures it); the oracle
#: ``truth`` reads the simulated offsets, with sync's weighing off
VARIANTS = {"sync": (0.0, False), "weighed_40": (SITE_M * (0.4 / 0.6) ** 0.5, False), "weighed_61": (0.025, False),
            "site": (10.0, False), "measured": (0.025, True), "truth": (0.0, False)}


def take_files(keep: Path, typ: str, seed: int, preset: str, fps: float):
    """The kept recording and scene of one take, recorded first when missing."""
    from dualhuman_builder.evaluation.fit import record_simulated_take
    from dualhuman_builder.sim.scenes import Scene

    name = f"{typ}-{seed}" + ("" if preset == "ideal" else f"-{preset}")
    d = keep / name
    take, scene = d / f"{name}.mcap", d / f"{typ}-{seed}.scene.npz"
    if not (take.is_file() and scene.is_file()):
        record_simulated_take(typ, seed, d, fps=fps, preset=preset)
    return take, Scene.load(scene)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--types", nargs="+", default=["hug", "handshake"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[1])
    ap.add_argument("--presets", nargs="+", default=["realistic", "ideal"])
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--keep", type=Path, required=True)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.capture.log.reader import read_columns
    from dualhuman_builder.evaluation.fit import evaluate_take_fit
    from dualhuman_builder.fit.fitter import FitConfig, fit_actors, inputs_from_fused
    from dualhuman_builder.fit.fuse import fuse_actor
    from dualhuman_builder.fit.process import TakeFit, calibrate_shapes, shape_dict, skeleton_rms
    from dualhuman_builder.sim.studio import simulate_studio
    from dualhuman_builder.sync.timeline import synchronise

    model = get_body_model()
    figures: dict = {}
    for preset in args.presets:
        for typ in args.types:
            for seed in args.seeds:
                take, scene = take_files(args.keep, typ, seed, preset, args.fps)
                sync = synchronise(read_columns(take), fps=args.fps)
                fused = [fuse_actor(a, sync.times_s, args.fps) for a in sync.actors]
                shapes = calibrate_shapes(model, fused)
                studio = simulate_studio(scene.sequence, seed=seed, preset=preset)
                row = {}
                for name, (sigma, measured) in VARIANTS.items():
                    fz = copy.deepcopy(fused)
                    if name == "truth":
                        for k, f in enumerate(fz):
                            st = studio.trackers[k]
                            for j, s in enumerate(f.serials):
                                f.trk_offset[j] = st.mount_translation[st.serials.index(s)]
                    cfg = FitConfig(sigma_suit_skeleton_m=sigma)
                    inputs = inputs_from_fused(fz, {k: shape_dict(v) for k, v in shapes.items()},
                                               skeleton_rms=skeleton_rms(shapes) if measured else None)  # fmt: skip
                    fit = fit_actors(model, inputs, args.fps, cfg, None, 1)
                    ev = evaluate_take_fit(TakeFit(sync, fz, shapes, fit), scene, seed, model=model, contacts=False,
                                           preset=preset)  # fmt: skip
                    row[name] = {k: round(float(ev[k]), 2) for k in ("mpjpe_mm", "pa_mpjpe_mm", "root_mm")}
                    print(f"{typ}-{seed} {preset:9s} {name:11s} " + "  ".join(f"{k} {v:6.1f}" for k, v in row[name].items()),
                          flush=True)  # fmt: skip
                figures.setdefault(preset, {})[f"{typ}-{seed}"] = row
    cols = [f"{p} {t}" for p in args.presets for t in figures[args.presets[0]]]
    rows = [[f"{v}: MPJPE / root (mm)"] + [f"{p}.{t}.{v}.mpjpe_mm" for p in args.presets for t in figures[p]]
            for v in VARIANTS]  # fmt: skip
    rows += [[f"{v}: root (mm)"] + [f"{p}.{t}.{v}.root_mm" for p in args.presets for t in figures[p]] for v in VARIANTS]
    path = write_results("probe_tracker_offsets", figures,
                         params={"types": args.types, "seeds": args.seeds, "presets": args.presets, "fps": args.fps,
                                 "variants": {k: {"sigma_suit_skeleton_m": v[0], "measured": v[1]} for k, v in VARIANTS.items()}},
                         tables=[Table("Fit error by the tracker offsets it reads (tuning seeds)", ["variant", *cols], rows)],
                         out=args.out)  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

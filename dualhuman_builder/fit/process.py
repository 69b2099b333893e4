"""From a recorded take to two fitted bodies in one call: sync -> fuse -> shape calibration -> fit.

The workspace stages (``dualhuman sync``, ``fuse``, ``fit``) run the same steps one at a time and
keep each result as an artifact; :func:`process_take` is the in-memory path the tests and the
benchmark use.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from dualhuman_builder.fit.fitter import FitConfig, FitResult


@dataclass
class TakeFit:
    """Everything :func:`process_take` made of one take, step by step."""

    sync: object  # SyncResult
    fused: list  # FusedActor per actor
    shapes: dict  # actor -> ShapeCalibration (or a registered shape dict)
    fit: FitResult


def calibrate_shapes(model, fused: list, known: dict | None = None, statures: dict | None = None,
                     genders: dict | None = None) -> dict:  # fmt: skip
    """One phenotype per actor: ``known[actor]`` when given (a registered shape), else solved from the
    fused skeleton's segment offsets (:func:`~dualhuman_builder.fit.calibrate.calibrate_shape`)."""
    from dualhuman_builder.fit.calibrate import calibrate_shape

    out = {}
    for f in fused:
        name = f.skeleton.actor
        if known and known.get(name):
            out[name] = dict(known[name])
            continue
        sk = f.skeleton
        out[name] = calibrate_shape(model, sk.orientations, sk.positions, sk.orientation_valid.all(1),
                                    stature_m=(statures or {}).get(name), gender=(genders or {}).get(name))  # fmt: skip
    return out


def shape_dict(cal) -> dict:
    """The phenotype dict of a :class:`~dualhuman_builder.fit.calibrate.ShapeCalibration` (or of a
    registered shape, already a dict)."""
    return cal if isinstance(cal, dict) else cal.shape


def skeleton_rms(shapes: dict) -> dict[str, float]:
    """Actor name -> the RMS (m) of the suit's segment lengths against the calibrated shape, for the
    actors of ``shapes`` (:func:`calibrate_shapes`) whose shape was calibrated (a registered one has none)."""
    return {k: v.rms_mm / 1000 for k, v in shapes.items() if not isinstance(v, dict)}


def process_take(take: str | Path | dict, fps: float = 30.0, use_trackers: bool = True, config: FitConfig = FitConfig(),
                 known_shapes: dict | None = None, statures: dict | None = None, genders: dict | None = None,
                 model=None, progress: Callable[[str], None] | None = None, workers: int | None = None,
                 mounts_from=None) -> TakeFit:  # fmt: skip
    """Run the whole path on a take file (or its :func:`read_columns`); the fit on ``workers``
    processes (:func:`~dualhuman_builder.fit.fitter.fit_actors`). ``mounts_from``: the
    :class:`~dualhuman_builder.sync.timeline.SyncResult` of the studio day's calibration take, whose
    tracker mounts carry over (:func:`~dualhuman_builder.sync.timeline.synchronise`)."""
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.capture.log.reader import read_columns
    from dualhuman_builder.fit.fitter import fit_actors, inputs_from_fused
    from dualhuman_builder.fit.fuse import fuse_actor
    from dualhuman_builder.sync.timeline import synchronise

    say = progress or (lambda _m: None)
    model = model or get_body_model()
    columns = read_columns(take) if not isinstance(take, dict) else take
    sync = synchronise(columns, fps=fps, use_trackers=use_trackers, progress=say, mounts_from=mounts_from)
    fused = [fuse_actor(a, sync.times_s, fps) for a in sync.actors]
    shapes = calibrate_shapes(model, fused, known_shapes, statures, genders)
    say("shapes: " + ", ".join(f"{k} {getattr(v, 'stature_m', 0):.3f} m" for k, v in shapes.items()))
    inputs = inputs_from_fused(fused, {k: shape_dict(v) for k, v in shapes.items()}, skeleton_rms=skeleton_rms(shapes))
    fit = fit_actors(model, inputs, fps, config, say, workers)
    return TakeFit(sync, fused, shapes, fit)

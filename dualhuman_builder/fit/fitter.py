"""Fit stage entry point: both actors' anny bodies over a take, jointly, with an SDF collision term
(:func:`fit_actors`).

Per frame the pose starts from a closed-form retarget of the fused segment orientations onto the anny
bones (:meth:`~dualhuman_builder.fit.skeleton.BodyRig.retarget`); then both actors are refined together
over windows of frames by L-BFGS on the skeleton energy (:mod:`~dualhuman_builder.fit.energy`) plus,
where the bodies touch, the collision term (:mod:`~dualhuman_builder.fit.collision_rounds`). The take's
windows are grouped into independent segments (:func:`~dualhuman_builder.fit.layout.layout`), fitted in
this process or in worker processes (:mod:`~dualhuman_builder.fit.workers`) by the window solver
(:class:`~dualhuman_builder.fit.segment.SegmentFitter`), cross-faded where they meet and mended where the
blend passes through the partner (:mod:`~dualhuman_builder.fit.seams`). With ``FitConfig.solver = "take"`` the whole take
is one problem instead, with a per-frame collision schedule (:class:`~dualhuman_builder.fit.take.TakeFitter`). The design and its reasons:
``docs/design/fit-collision.md``; the settings: :class:`~dualhuman_builder.fit.config.FitConfig`.

This module keeps the fit's public names importable from one place: :class:`FitConfig`,
:class:`ActorInput`, :class:`FitResult`, :class:`FitError`, :func:`fit_actors`,
:func:`inputs_from_fused`, :func:`layout`, :func:`stance_mask`, :func:`fit_workers`,
:func:`collision_threads`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from dualhuman_builder.children import available_memory, cpu_count
from dualhuman_builder.fit.actors import stance_mask
from dualhuman_builder.fit.config import SOLVERS, TAKE_STEPS, FitConfig, config_dict
from dualhuman_builder.fit.inputs import ActorInput, FitError, inputs_from_fused
from dualhuman_builder.fit.layout import SegmentAnswer, cross_fade, layout
from dualhuman_builder.fit.seams import apply_seams, fit_seam
from dualhuman_builder.fit.segment import SegmentFitter
from dualhuman_builder.fit.take import TakeFitter
from dualhuman_builder.fit.workers import fit_in_workers

#: what one more fitting process may need (its peak resident memory on the 1-minute benchmark hug,
#: ``benchmarks/bench_fit.py``, rounded up)
WORKER_BYTES = 2 << 30


@dataclass
class FitResult:
    """``sequence``: the fitted :class:`~dualhuman_builder.tracks.InteractionSequence` (a list of
    :class:`~dualhuman_builder.tracks.BodyTrack` for one actor); ``frames``: per-frame series ``(T,)``
    for the report, by name with units; ``summary``: headline numbers (see :func:`fit_actors`);
    ``valid (T,)``: frames with suit data for every actor."""

    sequence: object
    frames: dict = field(default_factory=dict)
    summary: dict = field(default_factory=dict)
    valid: np.ndarray | None = None


def fit_actors(model, inputs: list[ActorInput], fps: float, cfg: FitConfig = FitConfig(),
               progress: Callable[[str], None] | None = None, workers: int | None = None) -> FitResult:  # fmt: skip
    """Fit one or two actors over the whole timeline (``fps`` frames per second; see the module
    docstring), with torch's CPU threads set to ``cfg.torch_threads`` meanwhile.

    The window solver fits the take's segments on ``workers`` processes, this one included (None:
    :func:`fit_workers`; 1: all in this process); the others are started as ``python -m
    dualhuman_builder.fit.workers``. The answer does not depend on it. ``progress`` gets one line per
    window and collision pass (from any worker, one line at a time).

    The summary holds the frame count and timing, ``collision_frames`` (frames the skeleton pass left
    in contact), ``collision_rounds_used``, the collision passes undone (``collision_diverged``,
    ``collision_worsened``), the exact fallbacks (``collision_exact_frames``,
    ``collision_exact_windows``, ``collision_held_stalled``, ``collision_energy_refits``), ``segments``,
    ``processes``, ``seams_fitted_again``, ``worker_peak_rss_mb`` and, with the collision term, the
    deepest penetration (mm) and penetrating share before and after it. Raises :class:`FitError` on
    inputs it cannot fit."""
    threads = torch.get_num_threads()
    if cfg.torch_threads > 0:
        torch.set_num_threads(int(cfg.torch_threads))
    try:
        return _fit_actors(model, inputs, fps, cfg, progress, workers)
    finally:
        torch.set_num_threads(threads)


def _fit_actors(model, inputs: list[ActorInput], fps: float, cfg: FitConfig, progress, workers: int | None) -> FitResult:
    say = progress or (lambda _m: None)
    T = _frame_count(inputs)
    if cfg.solver not in SOLVERS:
        raise FitError(f"unknown fit solver {cfg.solver!r}; choose one of {', '.join(SOLVERS)}")
    if cfg.take_step not in TAKE_STEPS:
        raise FitError(f"unknown take solver step {cfg.take_step!r}; choose one of {', '.join(TAKE_STEPS)}")
    t_start = time.perf_counter()
    if cfg.solver == "take":
        inputs, offsets = _offsets_on_body(inputs, cfg, say)
        fitter = TakeFitter(model, inputs, fps, cfg, threads=collision_threads(1))
        segments, n_workers, fitted = [[(0, 0, T)]], 1, [fitter.fit(say)]
        joined, seams, worker_mb = cross_fade(fitted, T), [], None
    else:
        segments = layout(T, cfg)
        fitter, n_workers, fitted, joined, seams, worker_mb, offsets = _fit_windows(model, inputs, fps, cfg, segments, workers, say)
    tracks, frames = _tracks_and_frames(model, fitter, joined, fps)
    valid = np.logical_and.reduce([a.valid.cpu().numpy() for a in fitter.acts])
    seq = _interaction(tracks)
    seconds = time.perf_counter() - t_start  # everything: the segments, the seams, the outputs and diagnostics
    summary = {"frames": T, "fit_seconds": round(seconds, 3), "frame_pairs_per_s": round(T / max(seconds, 1e-9), 2),
               **_collision_counts(fitted), "segments": len(segments), "processes": n_workers,
               "seams_fitted_again": seams, "worker_peak_rss_mb": None if worker_mb is None else round(worker_mb),
               **({"tracker_offset_change_mm": offsets} if offsets else {})}  # fmt: skip
    if fitter.collide is not None:
        summary.update(max_penetration_before_mm=round(float(joined["pen_before"].max() * 1000), 3),
                       max_penetration_after_mm=round(float(joined["pen_after"].max() * 1000), 3),
                       penetrating_share_before=float(joined["share_before"].max()),
                       penetrating_share_after=float(joined["share_after"].max()))  # fmt: skip
    return FitResult(seq if seq is not None else tracks, frames, summary, valid)


def _fit_windows(model, inputs: list[ActorInput], fps: float, cfg: FitConfig, segments: list, workers: int | None, say) -> tuple:
    """The window solver over ``segments`` (:func:`layout`), on ``workers`` processes (see
    :func:`fit_actors`): the fitter, the processes used, the answers fitted (the segments'
    and the seams' windows fitted again: a pass there can diverge or stall too), the joined corrections
    (:func:`~dualhuman_builder.fit.layout.cross_fade`, seams applied), the seams fitted again, the
    largest worker's peak RSS (MB, None in this process) and the tracker offsets' changes."""
    n_windows = sum(len(seg) for seg in segments)
    n_workers = fit_workers(len(segments), cfg) if workers is None else max(1, min(int(workers), len(segments)))
    if n_workers > 1 and not _workers_build_it(model):
        say(f"fit: {n_workers} workers asked for, but the body model is not the toolkit's float32 anny; fitting in this process")
        n_workers = 1
    inputs, offsets = _offsets_on_body(inputs, cfg, say)
    fitter = SegmentFitter(model, inputs, fps, cfg, threads=collision_threads(n_workers))
    if n_workers > 1:
        say(f"fit: {len(segments)} segments of up to {max(1, int(cfg.segment_windows))} windows, on {n_workers} processes")
        parts, seams_done, worker_mb = fit_in_workers(fitter, inputs, fps, segments, n_windows, n_workers, say)
    else:
        parts = [fitter.segment(seg, n_windows, say) for seg in segments]
        seams_done, worker_mb = [fit_seam(fitter, p, q, say) for p, q in zip(parts, parts[1:])], None
    joined = cross_fade(parts, _frame_count(inputs))
    seams = apply_seams(joined, seams_done)
    fitted = parts + [s.fixed for s in seams_done if s is not None and s.fixed is not None]
    return fitter, n_workers, fitted, joined, seams, worker_mb, offsets


def _offsets_on_body(inputs: list[ActorInput], cfg: FitConfig, say) -> tuple[list[ActorInput], dict]:
    """Each actor's tracker offsets on anny (:func:`~dualhuman_builder.fit.mounts.offsets_on_body`), and per
    actor each offset's change (mm)."""
    from dualhuman_builder.fit.mounts import offsets_on_body

    out, report = [], {}
    for inp in inputs:
        new, change = offsets_on_body(inp, cfg)
        out.append(new)
        if change:
            report[inp.name] = change
            say(f"fit: {inp.name}'s tracker offsets on the body: {', '.join(f'{v:.0f}' for v in change)} mm from sync's")
    return out, report


def _frame_count(inputs: list[ActorInput]) -> int:
    """The take's frame count ``T``; :class:`FitError` unless there are actors, all with ``T >= 2``
    frames."""
    if not inputs:
        raise FitError("nothing to fit: no actors")
    T = len(inputs[0].seg_rot)
    if any(len(i.seg_rot) != T for i in inputs):
        raise FitError("actors have different frame counts; run them through one sync")
    if T < 2:
        raise FitError(f"the take has {T} frame(s) on the timeline; fitting needs at least 2")
    return T


def _interaction(tracks: list):
    """The :class:`~dualhuman_builder.tracks.InteractionSequence` of two tracks; None for one."""
    from dualhuman_builder.tracks import InteractionSequence

    return InteractionSequence(tuple(tracks)) if len(tracks) == 2 else None


def _collision_counts(fitted: list[SegmentAnswer]) -> dict:
    """The summary's collision entries, over the segments' and the seams' answers ``fitted``."""
    return {"collision_frames": int(sum(p.collided for p in fitted)), "collision_rounds_used": int(max(p.rounds for p in fitted)),
            "collision_diverged": [x for p in fitted for x in p.diverged], "collision_worsened": [x for p in fitted for x in p.worsened],
            "collision_exact_frames": [x for p in fitted for x in p.exact_frames],
            "collision_exact_windows": [x for p in fitted for x in p.exact_windows],
            "collision_held_stalled": [x for p in fitted for x in p.stalled],
            "collision_energy_refits": [x for p in fitted for x in p.energy_refits]}  # fmt: skip


def _tracks_and_frames(model, fitter: SegmentFitter, joined: dict, fps: float) -> tuple[list, dict]:
    """The fitted :class:`~dualhuman_builder.tracks.BodyTrack` per actor from the joined corrections
    (:func:`~dualhuman_builder.fit.layout.cross_fade`'s dict, seams applied), and the report's per-frame
    series ``(T,)``: each actor's mean orientation change (deg), hand opening and tracker residual (mm),
    then the penetration depth (mm) without and with the collision term."""
    from dualhuman_builder.tracks import BodyTrack

    dev, cfg = fitter.dev, fitter.cfg
    deltas, dtransl, openings = ([torch.as_tensor(x, device=dev) for x in joined[key]] for key in ("delta", "dtransl", "opening"))
    tracks, frames = [], {}
    for k, a in enumerate(fitter.acts):
        with torch.no_grad():
            rot = a.rotations(deltas[k], slice(None))
            transl = a.transl0 + dtransl[k]
            pose = a.rig.local_pose(rot, openings[k]).cpu().numpy()
            ang = np.degrees(deltas[k].norm(dim=-1).mean(-1).cpu().numpy())
            frames[f"orientation change (deg)/{a.name}"] = np.where(a.valid.cpu().numpy(), ang, np.nan)
            o = openings[k]  # per frame the opening farthest from relaxed, with its sign (< 0: curled)
            frames[f"hand opening (0 relaxed, 1 flat)/{a.name}"] = o.gather(1, o.abs().argmax(1, keepdim=True))[:, 0].cpu().numpy()
            if len(a.trk_seg):
                posed = a.rig.pose(rot, transl, False)
                seg_frame = rot[:, a.trk_seg] @ a.rig.seg_frame[a.trk_seg]
                site = posed.heads[:, a.trk_bone] + (seg_frame @ a.trk_off[None, :, :, None])[..., 0]
                r = (site - a.trk_pos).norm(dim=-1).cpu().numpy() * 1000
                tv = a.trk_valid.cpu().numpy()
                with np.errstate(invalid="ignore"):
                    frames[f"tracker residual (mm)/{a.name}"] = np.where(tv.any(1), (r * tv).sum(1) / np.maximum(tv.sum(1), 1), np.nan)
        shape = a.rig.shape.cpu().numpy()
        meta = {"fit": {"collision": fitter.collide is not None, "trackers": int(len(a.trk_seg)), "config": config_dict(cfg)}}
        tracks.append(BodyTrack.from_model(model, pose, transl.cpu().numpy(), shape, fps, actor=a.name, meta=meta))
    if fitter.collide is not None:
        frames["penetration depth (mm)/without collision term"] = joined["pen_before"] * 1000
        frames["penetration depth (mm)/with collision term"] = joined["pen_after"] * 1000
    return tracks, frames


def fit_workers(segments: int, cfg: FitConfig, cpus: int | None = None, available_bytes: int | None = None) -> int:
    """Processes a fit of ``segments`` segments runs on when the caller does not say (this one
    included): one per CPU, one per segment at most, and no more than leave :data:`WORKER_BYTES`
    of available memory to each; 1 on a GPU (``cfg.device`` other than ``cpu``: one device, and the
    fit's work already runs in parallel there)."""
    if torch.device(cfg.device).type != "cpu" or segments <= 1:
        return 1
    if cpus is None:
        cpus = cpu_count()
    if available_bytes is None:
        available_bytes = available_memory()
    by_memory = max(1, int(available_bytes // WORKER_BYTES)) if available_bytes else cpus
    return max(1, min(cpus, segments, by_memory))


def collision_threads(processes: int, cpus: int | None = None) -> int:
    """The collision term's query threads in each of a fit's ``processes`` (this one included): the CPUs
    shared out among them, at least 1 and at most 8. More threads than CPUs only wait on each other
    (docs/decisions/0018-segments-in-worker-processes.md)."""
    return max(1, min(8, (cpu_count() if cpus is None else int(cpus)) // max(1, int(processes))))


def _workers_build_it(model) -> bool:
    """Whether worker processes build the same body model (``get_body_model(cfg.device)``: anny, float32)."""
    from dualhuman_builder.body.model import BodyModel

    return isinstance(model, BodyModel) and model.dtype == torch.float32


__all__ = ["WORKER_BYTES", "ActorInput", "FitConfig", "FitError", "FitResult", "collision_threads",
           "fit_actors", "fit_workers", "inputs_from_fused", "layout", "stance_mask"]  # fmt: skip

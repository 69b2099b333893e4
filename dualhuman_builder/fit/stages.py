"""The ``sync``, ``fuse`` and ``fit`` workspace stages of a recorded take (idempotent, crash-safe:
see :mod:`dualhuman_builder.workspace.stages`). Each runs the stage before it when that is missing
or stale.

Artifacts (under ``WS/artifacts/TAKE/_take/<stage>/``):

* ``sync``: ``sync.npz`` (:class:`~dualhuman_builder.sync.timeline.SyncResult`: every stream on the
  timeline, tracker mounts) and ``sync.json`` (clock offsets and drifts, lags, mounts, with
  uncertainties; with ``mounts_from``, which trackers kept the calibration take's mounts);
* ``fuse``: ``<actor>.skeleton.npz`` (:class:`~dualhuman_builder.tracks.SkeletonTrack`, tracker
  world) and ``fuse.json`` (per tracker: valid, rejected and bridged frames);
* ``fit``: ``bodies.npz`` (:class:`~dualhuman_builder.tracks.InteractionSequence` of the two
  fitted bodies), ``shapes.json`` (each actor's calibrated phenotype and segment-length residuals),
  ``frames.npz`` (per-frame residuals and penetration), ``report.html`` and ``report.png``.
"""

from __future__ import annotations

import json
from typing import Callable

import numpy as np

from dualhuman_builder.errors import WorkspaceError
from dualhuman_builder.fit.fitter import FitConfig

STAGE_VERSION = "4"  # 2: heading from the tracker constellation (mount sites); 3: the suit's segment misalignments; 4: the calibration take's tracker lag carried (and the fit's rounds since 3)


def _take_file(ws, take: str):
    files = [f for f in ws.take(take).files if str(f["path"]).endswith(".mcap")]
    if not files:
        raise WorkspaceError(f"take {take!r} has no recorded .mcap file to sync",
                             fix="record it with `dualhuman capture -w WS --take T ...`")  # fmt: skip
    return ws.root / files[0]["path"]


def run_sync(ws, take: str, fps: float = 30.0, use_trackers: bool = True, force: bool = False, log: Callable = print,
             take_file=None, depends_on=(), suit_chain: bool = True, mounts_from: str | None = None,
             mounts_take_file=None, mounts_depends_on=()):  # fmt: skip
    """``take_file``: read this .mcap instead of the take's registered file (the demo records its
    take as an artifact of its ``capture`` stage, named in ``depends_on``). ``suit_chain=False``:
    do not solve the suit's segment misalignments with the mounts (:func:`synchronise`).
    ``mounts_from``: the session's calibration take, synced first if needed (from
    ``mounts_take_file`` / ``mounts_depends_on`` as for ``take_file``), whose tracker mounts carry
    over; a change of its sync makes this one stale."""
    from dualhuman_builder.capture.log.reader import read_columns
    from dualhuman_builder.sync.timeline import SyncResult, synchronise

    extra: dict = {} if suit_chain else {"suit_chain": False}
    if mounts_from:
        if mounts_from == take:
            raise WorkspaceError(f"take {take!r} cannot carry the mounts of itself",
                                 fix="name the session's calibration take with --mounts-from")  # fmt: skip
        ws.take(mounts_from)  # raises a clear error for an unknown take
        run_sync(ws, mounts_from, fps=fps, log=log, take_file=mounts_take_file, depends_on=mounts_depends_on,
                 suit_chain=suit_chain)  # fmt: skip
        rec = ws.stage_record("sync", mounts_from)
        extra.update(mounts_from=mounts_from, mounts_sha256=rec["artifacts"]["sync.npz"]["sha256"])

    def compute(out):
        columns = read_columns(take_file) if take_file is not None else _read(ws, take)
        cal = SyncResult.load(ws.artifacts("sync", mounts_from)["sync.npz"]) if mounts_from else None
        sync = synchronise(columns, fps=fps, use_trackers=use_trackers, progress=log, suit_chain=suit_chain,
                           mounts_from=cal, mounts_from_take=mounts_from or "")  # fmt: skip
        sync.save(out.path("sync.npz"))
        out.path("sync.json").write_text(json.dumps(sync.report, indent=2, default=_json))
        return {"frames": int(len(sync.times_s)), "actors": [a.actor for a in sync.actors],
                "trackers": {a.actor: len(a.serials) for a in sync.actors},
                **({"mounts_from": sync.report.get("mounts_from", {})} if mounts_from else {})}  # fmt: skip

    return ws.run_stage("sync", compute, take=take, params={"fps": fps, "trackers": use_trackers, **extra},
                        depends_on=list(depends_on), version=STAGE_VERSION, force=force)  # fmt: skip


def _read(ws, take):
    from dualhuman_builder.capture.log.reader import read_columns

    return read_columns(_take_file(ws, take))


def run_fuse(ws, take: str, force: bool = False, log: Callable = print, **sync_kw):
    """Fuse each actor of ``take`` (runs sync first when needed; ``sync_kw`` go to :func:`run_sync`)."""
    from dualhuman_builder.fit.fuse import fuse_actor
    from dualhuman_builder.sync.timeline import SyncResult

    run_sync(ws, take, log=log, **sync_kw)

    def compute(out):
        sync = SyncResult.load(ws.artifacts("sync", take)["sync.npz"])
        stats = {}
        for a in sync.actors:
            f = fuse_actor(a, sync.times_s, sync.fps)
            f.skeleton.save(out.path(f"{a.actor}.skeleton.npz"))
            np.savez(out.path(f"{a.actor}.trackers.npz"), trk_pos=f.trk_pos, trk_valid=f.trk_valid,
                     trk_segment=f.trk_segment, trk_offset=f.trk_offset, serials=np.array(f.serials, dtype="U64"))  # fmt: skip
            stats[a.actor] = {"fused_with_trackers": f.fused_with_trackers, "trackers": f.stats}
            log(f"{a.actor}: fused {'with' if f.fused_with_trackers else 'WITHOUT'} trackers")
        out.path("fuse.json").write_text(json.dumps(stats, indent=2))
        return {"fused_with_trackers": {k: v["fused_with_trackers"] for k, v in stats.items()}}

    return ws.run_stage("fuse", compute, take=take, depends_on=[("sync", None)], version=STAGE_VERSION, force=force)


def load_fused(ws, take: str) -> list:
    from dualhuman_builder.fit.fuse import FusedActor
    from dualhuman_builder.sync.timeline import SyncResult
    from dualhuman_builder.tracks import SkeletonTrack

    sync = SyncResult.load(ws.artifacts("sync", take)["sync.npz"])
    arts = ws.artifacts("fuse", take)
    stats = json.loads(arts["fuse.json"].read_text())
    out = []
    for a in sync.actors:
        sk = SkeletonTrack.load(arts[f"{a.actor}.skeleton.npz"])
        with np.load(arts[f"{a.actor}.trackers.npz"], allow_pickle=False) as z:
            out.append(FusedActor(sk, tuple(str(s) for s in z["serials"]), z["trk_pos"], z["trk_valid"], z["trk_segment"],
                                  z["trk_offset"], stats[a.actor]["fused_with_trackers"], stats[a.actor]["trackers"]))  # fmt: skip
    return sync, out


def run_fit(ws, take: str, config: FitConfig = FitConfig(), force: bool = False, log: Callable = print,
            workers: int | None = None, **sync_kw):  # fmt: skip
    """Fit both actors of ``take`` (runs sync and fuse first when needed) on ``workers`` processes
    (:func:`~dualhuman_builder.fit.fitter.fit_actors`; the answer does not depend on it)."""
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.fit.fitter import fit_actors, inputs_from_fused
    from dualhuman_builder.fit.pipeline import calibrate_shapes, shape_dict
    from dualhuman_builder.fit.report import write_fit_report

    run_fuse(ws, take, log=log, **sync_kw)

    def compute(out):
        model = get_body_model()
        sync, fused = load_fused(ws, take)
        registered = {a.name: a for a in ws.actors()}
        statures = {n: a.height_m for n, a in registered.items() if a.height_m}
        from dualhuman_builder.body.shape import GENDER_VALUES

        genders = {n: GENDER_VALUES.get(a.gender) for n, a in registered.items() if a.gender in ("male", "female")}
        if len(fused) != 2:
            raise WorkspaceError(f"take {take!r} has {len(fused)} actor(s); the fit stage fits two people",
                                 fix="check the rig binds two actors to suits")  # fmt: skip
        shapes = calibrate_shapes(model, fused, None, statures, genders)
        log("shapes: " + ", ".join(f"{k} {v.stature_m:.3f} m (segment lengths within {v.rms_mm:.1f} mm RMS)" for k, v in shapes.items()))
        res = fit_actors(model, inputs_from_fused(fused, {k: shape_dict(v) for k, v in shapes.items()}), sync.fps, config, log, workers)
        seq = res.sequence
        seq.save(out.path("bodies.npz"))
        out.path("shapes.json").write_text(json.dumps({k: v.as_dict() for k, v in shapes.items()}, indent=2))
        np.savez(out.path("frames.npz"), valid=res.valid, **{k.replace("/", "|"): v for k, v in res.frames.items()})
        without = [f.skeleton.actor for f in fused if not f.fused_with_trackers]
        summary = {**res.summary, "fitted_without_trackers": without}
        series: dict = {}
        for key, v in res.frames.items():
            title, label = key.split("/", 1)
            series.setdefault(title, {})[label] = v
        for f in fused:
            if len(f.serials):
                series.setdefault("Tracker valid", {}).update({s: f.trk_valid[:, k].astype(float) for k, s in enumerate(f.serials)})
        write_fit_report(out.path("report.html"), take=take, fps=sync.fps, series=series, sync=sync.report,
                         summary=summary, png_path=out.path("report.png"))  # fmt: skip
        log(f"fit: {res.summary['frames']} frames at {res.summary['frame_pairs_per_s']} frame pairs/s"
            + (f"; max penetration {res.summary.get('max_penetration_before_mm', 0):.1f} mm without the collision term, "
               f"{res.summary.get('max_penetration_after_mm', 0):.1f} mm with it" if config.collision else ""))  # fmt: skip
        for where in res.summary.get("collision_diverged", []):
            log(f"WARNING: the collision pass diverged ({where}) and was undone; those frames may still overlap")
        for where in res.summary.get("collision_worsened", []):
            log(f"WARNING: a collision pass left the bodies deeper in each other ({where}) and was undone")
        if res.summary.get("collision_exact_frames"):
            log(f"fit: held contacts stalled in {len(res.summary['collision_exact_frames'])} frame(s) "
                f"({', '.join(map(str, res.summary['collision_exact_frames']))}); their contacts were located at every "
                "evaluation from then on")
        if res.summary.get("collision_exact_windows"):
            log(f"fit: held contacts did not settle {len(res.summary['collision_exact_windows'])} window(s) "
                f"({', '.join(res.summary['collision_exact_windows'])}); fitted again with exact contacts")
        if without:
            log(f"WARNING: fitted without trackers: {without} (the suit's position drift remains)")
        return summary

    params = {k: getattr(config, k) for k in config.__dataclass_fields__}
    return ws.run_stage("fit", compute, take=take, params=params, depends_on=[("fuse", None)],
                        version=STAGE_VERSION, force=force)  # fmt: skip


def _json(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)

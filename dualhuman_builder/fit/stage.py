"""The ``fuse`` and ``fit`` workspace stages of a take (idempotent, crash-safe: see
:mod:`dualhuman_builder.workspace.runner`). Each runs the stage before it when that is missing or
stale (``fuse`` runs :func:`~dualhuman_builder.sync.stage.run_sync`).

Artifacts (under ``WS/artifacts/TAKE/_take/<stage>/``):

* ``fuse``: ``<actor>.skeleton.npz`` (:class:`~dualhuman_builder.tracks.SkeletonTrack`, tracker
  world), ``<actor>.trackers.npz`` (the trackers' fused positions, validity, segments and offsets)
  and ``fuse.json`` (per tracker: valid, rejected and bridged frames);
* ``fit``: ``bodies.npz`` (:class:`~dualhuman_builder.tracks.InteractionSequence` of the two
  fitted bodies; :func:`load_bodies`), ``shapes.json`` (each actor's calibrated phenotype and
  segment-length residuals), ``frames.npz`` (per-frame residuals and penetration),
  ``report.html`` and ``report.png``. A take of one actor (one imported MVNX file) gets
  ``<actor>.body.npz`` (:class:`~dualhuman_builder.tracks.BodyTrack`; :func:`load_body`) in place of
  ``bodies.npz``, fitted alone (no collision term).

What the data could not give is flagged, not refused: an actor fused without trackers
(``fitted_without_trackers``), and for an imported take each actor's ``flags`` and
``unmeasured_segments`` from the sync report (``upper body``: the legs of MVN's upper-body
configuration, weight 0 in the fit's input: :attr:`~dualhuman_builder.fit.inputs.ActorInput.segment_weight`).
All of them are in the stage's summary in the catalog and at the top of ``report.html``.
"""

from __future__ import annotations

import json
from typing import Callable

import numpy as np

from dualhuman_builder.errors import WorkspaceError
from dualhuman_builder.fit.fitter import FitConfig
from dualhuman_builder.sync.stage import load_sync, run_sync
from dualhuman_builder.workspace.runner import Stage

#: Bumped whenever the same sync would fuse or fit to other numbers, so workspaces fit again.
FIT_VERSION = "5"
BODIES = "bodies.npz"
FUSE = Stage("fuse", per="take", artifacts=("{actor}.skeleton.npz", "{actor}.trackers.npz", "fuse.json"),
             reads=("sync",), command="dualhuman fuse {ws} --take {take}")  # fmt: skip
BODY = "{actor}.body.npz"
FIT = Stage("fit", per="take", artifacts=(BODIES, BODY, "shapes.json", "frames.npz", "report.html", "report.png"),
            reads=("fuse",), command="dualhuman fit {ws} --take {take}")  # fmt: skip


def run_fuse(ws, take: str, force: bool = False, log: Callable = print, **sync_kw):
    """Fuse each actor of ``take`` (runs sync first when needed; ``sync_kw`` go to :func:`run_sync`)."""
    from dualhuman_builder.fit.fuse import fuse_actor

    run_sync(ws, take, log=log, **sync_kw)

    def compute(out):
        sync = load_sync(ws, take)
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

    return ws.run_stage(FUSE, compute, take=take, depends_on=[("sync", None)], version=FIT_VERSION, force=force)


def load_fused(ws, take: str) -> tuple:
    """``(sync, fused)``: the take's :class:`~dualhuman_builder.sync.timeline.SyncResult` and a
    :class:`~dualhuman_builder.fit.fuse.FusedActor` per actor (its fuse stage must be done)."""
    from dualhuman_builder.fit.fuse import FusedActor
    from dualhuman_builder.tracks import SkeletonTrack

    sync = load_sync(ws, take)
    FUSE.artifact(ws, take, "fuse.json")  # a clear error when fuse has not run
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
    from dualhuman_builder.fit.process import calibrate_shapes, shape_dict, skeleton_rms
    from dualhuman_builder.fit.report import write_fit_report

    run_fuse(ws, take, log=log, **sync_kw)

    def compute(out):
        model = get_body_model()
        sync, fused = load_fused(ws, take)
        registered = {a.name: a for a in ws.actors()}
        statures = {n: a.height_m for n, a in registered.items() if a.height_m}
        from dualhuman_builder.body.shape import GENDER_VALUES

        genders = {n: GENDER_VALUES.get(a.gender) for n, a in registered.items() if a.gender in ("male", "female")}
        if len(fused) not in (1, 2):
            raise WorkspaceError(f"take {take!r} has {len(fused)} actors; the fit stage fits one or two people",
                                 fix="check the rig binds two actors to suits")  # fmt: skip
        shapes = calibrate_shapes(model, fused, None, statures, genders)
        log("shapes: " + ", ".join(f"{k} {v.stature_m:.3f} m (segment lengths within {v.rms_mm:.1f} mm RMS)" for k, v in shapes.items()))
        unmeasured = {a: list(v.get("unmeasured_segments", ())) for a, v in (sync.report.get("imported") or {}).items()}
        inputs = inputs_from_fused(fused, {k: shape_dict(v) for k, v in shapes.items()}, unmeasured, skeleton_rms(shapes))
        res = fit_actors(model, inputs, sync.fps, config, log, workers)
        seq = res.sequence
        if len(fused) == 2:
            seq.save(out.path(BODIES))
        else:
            seq[0].save(out.path(BODY.format(actor=fused[0].skeleton.actor)))
        out.path("shapes.json").write_text(json.dumps({k: v.as_dict() for k, v in shapes.items()}, indent=2))
        np.savez(out.path("frames.npz"), valid=res.valid, **{k.replace("/", "|"): v for k, v in res.frames.items()})
        without = [f.skeleton.actor for f in fused if not f.fused_with_trackers]
        flags = fit_flags(sync.report, fused)
        summary = {**res.summary, "fitted_without_trackers": without, "actors": len(fused), "flags": flags,
                   "unmeasured_segments": {a.name: list(a.unmeasured) for a in inputs if a.unmeasured}}  # fmt: skip
        series: dict = {}
        for key, v in res.frames.items():
            title, label = key.split("/", 1)
            series.setdefault(title, {})[label] = v
        for f in fused:
            if len(f.serials):
                series.setdefault("Tracker valid", {}).update({s: f.trk_valid[:, k].astype(float) for k, s in enumerate(f.serials)})
        write_fit_report(out.path("report.html"), take=take, fps=sync.fps, series=series, sync=sync.report,
                         summary=summary, png_path=out.path("report.png"), flags=flag_lines(sync.report, flags))  # fmt: skip
        log(f"fit: {res.summary['frames']} frames at {res.summary['frame_pairs_per_s']} frame "
            + ("pairs/s" if len(fused) == 2 else f"s/s, {fused[0].skeleton.actor} alone")
            + (f"; max penetration {res.summary.get('max_penetration_before_mm', 0):.1f} mm without the collision term, "
               f"{res.summary.get('max_penetration_after_mm', 0):.1f} mm with it" if "max_penetration_after_mm" in res.summary else ""))  # fmt: skip
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
        for a in inputs:
            if a.unmeasured:
                log(f"WARNING: {a.name}: segments no sensor measured, held by 1 % of the orientation term: {', '.join(a.unmeasured)}")
        return summary

    params = {k: getattr(config, k) for k in config.__dataclass_fields__}
    if params["solver"] == "windows":  # the solver a fit had before it could be chosen: such fits stay up to date
        del params["solver"], params["take_iterations"]
    return ws.run_stage(FIT, compute, take=take, params=params, depends_on=[("fuse", None)],
                        version=FIT_VERSION, force=force)  # fmt: skip


def fit_flags(sync_report: dict, fused: list) -> dict[str, list[str]]:
    """Each actor's flags for the fit's summary: ``no trackers`` when it was fused without them, and the
    sync report's ``flags`` of an imported take (``upper body``...); actors with none are left out."""
    from dualhuman_builder.capture.importers import FLAG_NO_TRACKERS

    out: dict[str, list[str]] = {}
    for f in fused:
        name = f.skeleton.actor
        flags = list((sync_report.get("flags") or {}).get(name, ()))
        if not f.fused_with_trackers and FLAG_NO_TRACKERS not in flags:
            flags.insert(0, FLAG_NO_TRACKERS)
        if flags:
            out[name] = flags
    return out


def flag_lines(sync_report: dict, flags: dict[str, list[str]]) -> list[str]:
    """One sentence per actor and flag, for the top of the fit report."""
    from dualhuman_builder.capture.importers import flag_notes

    imported = sync_report.get("imported") or {}
    lines = []
    for actor, fl in flags.items():
        meta = {**imported.get(actor, {}), "flags": fl}
        lines.extend(f"{actor}: {note}" for note in flag_notes(meta))
    return lines


def load_body(ws, take: str, actor: str | None = None):
    """The fitted :class:`~dualhuman_builder.tracks.BodyTrack` of ``actor`` (None: its only actor) in a take
    of one actor (its fit stage must be done)."""
    from dualhuman_builder.tracks import BodyTrack

    if actor is None:
        rec = FIT.record(ws, take)
        found = sorted(k for k in (rec or {}).get("artifacts", {}) if k.endswith(".body.npz"))
        actor = found[0][: -len(".body.npz")] if found else "?"
    return BodyTrack.load(FIT.artifact(ws, take, BODY.format(actor=actor), what=f"fitted body of {actor}"))


def load_bodies(ws, take: str):
    """The take's two fitted bodies, an :class:`~dualhuman_builder.tracks.InteractionSequence`
    (its fit stage must be done: otherwise an error that says to run ``dualhuman fit``)."""
    from dualhuman_builder.tracks import InteractionSequence

    return InteractionSequence.load(fitted_bodies(ws, take))


def fitted_bodies(ws, take: str):
    """The path of the take's ``bodies.npz``; a clear error saying to run ``dualhuman fit`` when
    its fit stage is not done, or that the take was fitted for one actor (no pair to read)."""
    rec = FIT.record(ws, take)
    if rec is not None and rec.get("status") == "done" and BODIES not in rec["artifacts"]:
        single = sorted(k for k in rec["artifacts"] if k.endswith(".body.npz"))
        if single:
            raise WorkspaceError(f"take {take!r} has one actor: its fit is {single[0]}, not a pair of bodies",
                                 path=ws.root, fix="import or record the partner's suit in the same take to fit "
                                                   "the pair; load the one body with fit.stage.load_body")  # fmt: skip
    return FIT.artifact(ws, take, BODIES, what="fitted bodies")

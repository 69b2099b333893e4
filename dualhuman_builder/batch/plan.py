"""Which stages of which takes a batch run has to do, in dependency order, and how each is run.

A task is one stage of one take (a per-sequence stage covers every sequence of the take). Its
state comes from the catalog: a stage is **done** when every run of it for the take is ``done``;
anything else (never ran, ``stale``, ``failed``, interrupted) is pending. A take's stages follow
:data:`dualhuman_builder.pipeline.STAGES`, so each waits for the one before it.

Per-sequence stages (``scene``, ``devices``, ``capture``) are re-run only from what the catalog
recorded of an earlier attempt (a simulated take cut off while it was made); a take recorded from
real devices or imported has no such runs and starts at ``sync``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.pipeline import STAGE_NAMES, STAGES

#: Stages run per sequence, from the parameters their earlier attempt recorded.
SEQUENCE_STAGES = tuple(s.name for s in STAGES if s.per == "sequence")
#: Stages a calibration take goes through (its mounts and lags serve the other takes' sync).
CALIBRATION_STAGES = (*SEQUENCE_STAGES, "sync")
#: Memory one stage task needs at most (bytes), for the pool size and Ray's ``memory`` resource:
#: a fit on one process with its body model and collision kernels stays under 2 GiB, a render holds
#: Mitsuba's scene, the others hold one take's arrays.
STAGE_MEMORY = {"scene": 2 << 30, "devices": 1 << 30, "capture": 1 << 30, "sync": 1 << 30, "fuse": 1 << 30,
                "fit": 2 << 30, "contacts": 1 << 30, "render": 2 << 30, "sheet": 1 << 30}  # fmt: skip
#: Stages that use a GPU when one is there (Mitsuba's CUDA variant); the fit runs on the CPU
#: (decision 0019), so it asks for none.
GPU_STAGES = ("render",)


@dataclass(frozen=True)
class RunOptions:
    """What a batch run does: ``takes`` (None: all), ``until`` (the last stage, None: all),
    ``stages`` (only these, None: all), ``fps`` of the timeline for sync, fuse and fit (None: the
    stages' default), ``mounts_from`` (a calibration take whose tracker mounts every other take
    uses; None: each take's own ``mounts_from`` meta, if any),
    ``retries`` (tries after the first, per stage), ``workers`` (local processes, None: sized from
    cores and memory)."""

    takes: tuple[str, ...] | None = None
    until: str | None = None
    stages: tuple[str, ...] | None = None
    fps: float | None = None
    mounts_from: str | None = None
    retries: int = 1
    workers: int | None = None

    def __post_init__(self) -> None:
        for name in ([self.until] if self.until else []) + list(self.stages or ()):
            if name not in STAGE_NAMES:
                raise DualhumanError(f"no stage named {name!r}", fix=f"the stages are {', '.join(STAGE_NAMES)}")
        if self.retries < 0:
            raise DualhumanError(f"--retries must be 0 or more, not {self.retries}", fix="pass --retries 1")

    def wanted(self) -> tuple[str, ...]:
        """The stages this run may do, in pipeline order."""
        names = STAGE_NAMES[: STAGE_NAMES.index(self.until) + 1] if self.until else STAGE_NAMES
        return tuple(n for n in names if self.stages is None or n in self.stages)


@dataclass
class Task:
    """One stage of one take; ``after``: the tasks (``(take, stage)``) that must be done first."""

    take: str
    stage: str
    after: list[tuple[str, str]] = field(default_factory=list)

    @property
    def key(self) -> tuple[str, str]:
        return (self.take, self.stage)


@dataclass
class Plan:
    """``tasks`` in dependency order; ``done`` ``{(take, stage)}`` already complete;
    ``skipped`` ``{(take, stage): reason}`` not to be run at all."""

    tasks: list[Task]
    done: set[tuple[str, str]]
    skipped: dict[tuple[str, str], str]
    takes: list[str]


def stage_state(ws, take: str, stage: str) -> str | None:
    """``done`` when every run of ``stage`` for ``take`` is done; None when there is none; else
    the state of the first run that is not done (``stale``, ``failed``, ``running``, ...)."""
    from dualhuman_builder.pipeline import stage as declared

    st = declared(stage)
    if st.per == "take":
        return st.state(ws, take)
    states = [st.state(ws, take, s.name) for s in ws.sequences(take)]
    states = [s for s in states if s is not None]
    if not states:
        return None
    return next((s for s in states if s != "done"), "done")


def take_mounts_from(ws, take: str, options: RunOptions) -> str | None:
    """The calibration take whose tracker mounts ``take``'s sync uses: ``options.mounts_from`` for
    every take, else the take's own ``mounts_from`` meta (the studio day's calibration take, which
    ``dualhuman synth`` records); None for the calibration take itself."""
    mf = options.mounts_from or ws.take(take).meta.get("mounts_from")
    return mf if isinstance(mf, str) and mf and mf != take else None


def make_plan(ws, options: RunOptions) -> Plan:
    """The pending tasks of ``options`` in ``ws``: every wanted stage of every take that is not
    done, in pipeline order per take; a take's sync waits for its calibration take's
    (:func:`take_mounts_from`), which joins the run if it was not named."""
    takes = ws.takes() if options.takes is None else list(options.takes)
    known = set(ws.takes())
    missing = [t for t in takes if t not in known]
    if missing:
        raise DualhumanError(f"no take {missing[0]!r} in this workspace", fix=f"list the takes with `dualhuman status {ws.root}`")
    mounts = {t: take_mounts_from(ws, t, options) for t in takes}
    for take, mf in mounts.items():
        if mf is not None and mf not in known:
            whose = "" if options.mounts_from else f" (take {take!r} names it as its mounts_from)"
            raise DualhumanError(f"no calibration take {mf!r} in this workspace{whose}",
                                 fix=f"list the takes with `dualhuman status {ws.root}`")  # fmt: skip
    calibrations = {mf for mf in mounts.values() if mf is not None}
    takes = [*[c for c in sorted(calibrations) if c not in takes], *takes]
    wanted = options.wanted()
    tasks, done, skipped = [], set(), {}
    for take in takes:
        calibration = bool(ws.take(take).meta.get("calibration")) or take in calibrations
        prev: tuple[str, str] | None = None
        for name in wanted:
            key = (take, name)
            state = stage_state(ws, take, name)
            if name in SEQUENCE_STAGES and state is None:
                skipped[key] = "not a simulated take: nothing to re-run"
                continue
            if calibration and name not in CALIBRATION_STAGES:
                skipped[key] = "a calibration take: only synced (its mounts serve the other takes)"
                continue
            if state == "done":
                done.add(key)
                continue
            task = Task(take, name, [prev] if prev else [])
            if name == "sync" and mounts.get(take):
                task.after.append((mounts[take], "sync"))
            tasks.append(task)
            prev = key
    # a dependency already done (or skipped) is no dependency
    pending = {t.key for t in tasks}
    for t in tasks:
        t.after = [k for k in t.after if k in pending]
    return Plan(tasks, done, skipped, takes)


def stage_call(stage: str, options: RunOptions) -> Callable[..., Any]:
    """A function ``call(ws, take, log)`` that runs ``stage`` of a take with the stages' defaults
    (``options.fps`` and ``mounts_from`` for sync, fuse and fit; one process per fit and contacts
    task, since the batch runs several tasks at once: the result does not depend on it). Returns
    the :class:`~dualhuman_builder.workspace.runner.StageResult` (the last one, for a per-sequence
    stage), or None when there was nothing to run."""
    timeline: dict[str, Any] = {} if options.fps is None else {"fps": options.fps}

    def with_mounts(ws, take: str) -> dict[str, Any]:
        mf = take_mounts_from(ws, take, options)
        return {**timeline, **({"mounts_from": mf} if mf else {})}

    if stage in SEQUENCE_STAGES:
        return lambda ws, take, log: rerun_simulated(ws, take, stage, log)
    if stage == "sync":
        from dualhuman_builder.sync.stage import run_sync

        return lambda ws, take, log: run_sync(ws, take, log=log, **with_mounts(ws, take))
    if stage == "fuse":
        from dualhuman_builder.fit.stage import run_fuse

        return lambda ws, take, log: run_fuse(ws, take, log=log, **with_mounts(ws, take))
    if stage == "fit":
        from dualhuman_builder.fit.stage import run_fit

        return lambda ws, take, log: run_fit(ws, take, log=log, workers=1, **with_mounts(ws, take))
    if stage == "contacts":
        from dualhuman_builder.contacts.stage import run_contacts

        return lambda ws, take, log: run_contacts(ws, take, log=log, workers=1)
    if stage == "render":
        from dualhuman_builder.render.stage import run_render

        return lambda ws, take, log: run_render(ws, take, log=log)
    if stage == "sheet":
        from dualhuman_builder.render.sheet import run_sheet

        return lambda ws, take, log: run_sheet(ws, take, log=log)
    raise DualhumanError(f"the batch run does not know how to run stage {stage!r}", fix="run it with its own command")


def rerun_simulated(ws, take: str, stage: str, log: Callable[[str], None]):
    """Run ``stage`` (``scene``, ``devices`` or ``capture``) of every sequence of ``take`` whose run
    is not done, with the parameters its earlier attempt recorded in the catalog; a sequence whose
    stage never ran takes the parameters from the take's meta (``device_seed``, ``preset``, ``speed``)
    and else from the runs before it (the scene's seed, ``ideal``, real time). A live recording cannot be re-run:
    a :class:`DualhumanError` says so."""
    from dualhuman_builder.capture.stage import run_capture
    from dualhuman_builder.sim.stage import (
        SCENE,
        SCENE_FILE,
        device_url,
        run_devices,
        run_scene,
    )

    meta = ws.take(take).meta
    result = None
    for seq in ws.sequences(take):
        rec = ws.stage_record(stage, take, seq.name)
        if rec is not None and rec["status"] == "done":
            continue
        scene = ws.stage_record("scene", take, seq.name)
        if scene is None:
            raise DualhumanError(f"take {take}/{seq.name} has no scene to simulate its devices from",
                                 fix=f"simulate it with `dualhuman sim take {ws.root} --take {take}`")  # fmt: skip
        if stage == "scene":
            p = dict(scene["params"])
            actors, shapes = [tuple(a) for a in p.pop("actors")], p.pop("shapes")
            result = run_scene(ws, take, seq.name, p, actors, shapes, log=log)
            continue
        params = dict(rec["params"]) if rec is not None else {"seed": meta.get("device_seed", scene["params"]["seed"])}
        if "url" in params:
            raise DualhumanError(f"the {stage} stage of {take}/{seq.name} recorded live devices ({params['url']}): "
                                 "it cannot be run again", fix="record the take again with `dualhuman capture`")  # fmt: skip
        preset = params.get("preset", meta.get("preset", "ideal"))
        if stage == "devices":
            result = run_devices(ws, take, seq.name, params["seed"], preset=preset, log=log)
        else:
            if rec is None:
                params = {**params, "speed": float(meta.get("speed", 1.0))}
                if preset != "ideal":
                    params["preset"] = preset
            url = device_url(SCENE.artifact(ws, take, SCENE_FILE, seq.name), params["seed"], preset)
            result = run_capture(ws, take, seq.name, url, speed=params["speed"], params=params,
                                 depends_on=[("scene", seq.name)], log=log)  # fmt: skip
    return result

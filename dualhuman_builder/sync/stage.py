"""The ``sync`` workspace stage of a recorded take (idempotent, crash-safe: see
:mod:`dualhuman_builder.workspace.runner`).

Artifacts (under ``WS/artifacts/TAKE/_take/sync/``): ``sync.npz``
(:class:`~dualhuman_builder.sync.timeline.SyncResult`: every stream on the timeline, tracker
mounts) and ``sync.json`` (clock offsets and drifts, lags, mounts, with uncertainties; with
``mounts_from``, which trackers kept the calibration take's mounts).

The take's recording is the ``take.mcap`` of its ``capture`` stage when it has one (a take
recorded into the workspace by that stage, e.g. a simulated one), otherwise the ``.mcap`` file
registered with the take (``dualhuman capture -w WS``), otherwise the suits of a take imported from
MVNX files (``dualhuman import WS FILE.mvnx``, :func:`imported_suits`): each file's skeleton is one
suit stream on the file's own times (an MVNX file has no host clock, so there is no clock to fit), with
no trackers and so no mounts. The report then says where the suits came from (``imported``), and each
actor's ``flags`` (``no trackers``; ``upper body`` and the ``unmeasured_segments`` of the suit's MVN
configuration) also go to its ``warnings`` and to the stage's summary in the catalog.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

import numpy as np

from dualhuman_builder.capture.stage import CAPTURE, TAKE_FILE
from dualhuman_builder.errors import WorkspaceError
from dualhuman_builder.workspace.runner import Stage

#: Bumped whenever the same recording would sync to other numbers, so workspaces sync again.
SYNC_VERSION = "4"
SYNC_FILE, REPORT_FILE = "sync.npz", "sync.json"
SYNC = Stage("sync", per="take", artifacts=(SYNC_FILE, REPORT_FILE), reads=("capture",),
             command="dualhuman sync {ws} --take {take}")  # fmt: skip


def recording(ws, take: str) -> tuple[Path, list[tuple[str, str | None]]]:
    """``(path, depends_on)``: the take's recording and the stage runs it came from (its
    ``capture`` stage, which then makes ``sync`` stale when it runs again; none for a file
    registered with the take). A :class:`WorkspaceError` saying what to run when there is none,
    or its capture stage is not done (stale, failed), or the file is gone."""
    captures = {}
    for seq in ws.sequences(take):
        state = CAPTURE.state(ws, take, seq.name)
        if state == "done":
            return _present(CAPTURE.artifact(ws, take, TAKE_FILE, seq.name), take), [("capture", seq.name)]
        if state is not None:
            captures[seq.name] = state
    files = [f for f in ws.take(take).files if str(f["path"]).endswith(".mcap")]
    if files:
        return _present(ws.root / files[0]["path"], take), []
    if captures:
        seq, state = next(iter(captures.items()))
        raise WorkspaceError(f"take {take!r} has no recording to sync: the capture stage of {take}/{seq} is {state}",
                             path=ws.root, fix=CAPTURE.how_to_run(ws, take, seq))  # fmt: skip
    raise WorkspaceError(f"take {take!r} has no recorded .mcap file to sync", path=ws.root,
                         fix=f"record it with `dualhuman capture -w {ws.root} --take {take} ...`, or register a "
                             f"recorded take file with `dualhuman import {ws.root} FILE.mcap --take {take}`")  # fmt: skip


def imported_suits(ws, take: str) -> list[dict] | None:
    """The suits of a take imported from MVNX files (its catalog ``meta["suits"]``, written by
    :func:`~dualhuman_builder.capture.importers.import_file`), in actor order: each a dict with
    ``actor`` (the take's actor in that slot, else the file's subject label made safe, else
    ``actor<i>``; unique), ``path`` (its ``skeleton.npz``), ``suit_configuration``,
    ``unmeasured_segments`` and ``flags``. None for a take that is no such import; a
    :class:`WorkspaceError` when a skeleton file is missing."""
    from dualhuman_builder.capture.importers import safe_take_name, suit_flags

    t = ws.take(take)
    suits = t.meta.get("suits")
    if t.meta.get("source_format") != "mvnx" or not isinstance(suits, list) or not suits:
        return None
    out, seen = [], set()
    for i, s in enumerate(suits):
        name = s.get("actor") or (t.actors[i] if i < len(t.actors) else "")
        if not name and s.get("subject_label"):
            name = safe_take_name(str(s["subject_label"]))
        name = name or f"actor{i}"
        while name in seen:
            name = f"{name}_{i}"
        seen.add(name)
        file = str(s.get("skeleton", ""))
        if not file or Path(file).name != file or not any(f["path"].endswith(f"/{file}") for f in t.files):
            raise WorkspaceError(f"take {take!r}: suit {i} names no skeleton file registered with the take ({file!r})",
                                 path=ws.root, fix="import the MVNX file(s) again as a new take")  # fmt: skip
        flags = suit_flags(str(s.get("suit_configuration", "")))
        out.append({**flags, **s, "actor": name, "path": _present(ws.take_dir(take) / file, take)})
    return out


def imported_columns(suits: list[dict]) -> dict:
    """The suit streams of :func:`imported_suits` as :func:`~dualhuman_builder.capture.log.reader.read_columns`
    gives a recorded take's (``suits/mvnx/<i>/SuitFrame``), so :func:`~dualhuman_builder.sync.timeline.synchronise`
    puts them on the timeline unchanged. The host time is the file's own (MVNX has no other), so a
    clock fit has nothing to correct but the file's whole-millisecond times; the sample counter counts
    the file's frame steps, so a frame missing from the file stays a gap. Samples the file marks invalid are NaN (left out of the timeline)."""
    from dualhuman_builder.capture.log.reader import ChannelColumns
    from dualhuman_builder.tracks import SkeletonTrack

    out = {}
    for i, s in enumerate(suits):
        tr = SkeletonTrack.load(s["path"])
        n = tr.num_frames
        t = np.asarray(tr.device_time_ns, dtype=np.int64)
        step = float(np.median(np.diff(t))) if n > 1 else 0.0
        counter = np.round((t - t[0]) / step).astype(np.int64) if step > 0 else np.arange(n, dtype=np.int64)
        q = np.where(np.asarray(tr.orientation_valid)[..., None], tr.orientations, np.nan)
        p = np.where(np.asarray(tr.position_valid)[..., None], tr.positions, np.nan)
        topic = f"suits/mvnx/{i}/SuitFrame"
        cols = {"character": np.full(n, i, dtype=np.int64), "sample_counter": counter, "time_code_ms": t // 1_000_000,
                "device_time_ns": t, "host_time_ns": np.asarray(tr.host_time_ns, dtype=np.int64),
                "segment_names": tuple(tr.segment_names), "orientations": q, "positions": p}  # fmt: skip
        out[topic] = ChannelColumns(topic, "mvnx", str(i), "SuitFrame", {"actor": s["actor"], "source": "mvnx"}, n, cols)
    return out


def _imported_report(report: dict, suits: list[dict]) -> list[str]:
    """Add to a sync ``report`` where an imported take's suits came from (``imported``), each actor's
    ``flags`` and a warning per flag; returns those warnings."""
    from dualhuman_builder.capture.importers import flag_notes

    report["imported"] = {s["actor"]: {"file": s["path"].name, "suit_configuration": s.get("suit_configuration", ""),
                                       "unmeasured_segments": list(s.get("unmeasured_segments", ()))} for s in suits}  # fmt: skip
    report["flags"] = {s["actor"]: list(s.get("flags", ())) for s in suits}
    added = [f"{s['actor']}: {note}" for s in suits for note in flag_notes(s)]
    report.setdefault("warnings", []).extend(added)
    return added


def _present(path: Path, take: str) -> Path:
    if not path.is_file():
        raise WorkspaceError(f"the recording of take {take!r} is missing", path=path,
                             fix="restore the file (`dualhuman status WS --verify` lists what else is missing)")  # fmt: skip
    return path


def run_sync(ws, take: str, fps: float = 30.0, use_trackers: bool = True, force: bool = False, log: Callable = print,
             suit_chain: bool = True, mounts_from: str | None = None):  # fmt: skip
    """Sync ``take`` (:func:`~dualhuman_builder.sync.timeline.synchronise`) at ``fps`` frames per
    second. ``suit_chain=False``: do not solve the suit's segment misalignments with the mounts.
    ``mounts_from``: the calibration take of the same studio day, synced first if needed, whose
    tracker mounts and lags carry over; a change of its sync makes this one stale. Everything it
    needs (the recording, the calibration take's sync) is checked before the stage starts; the
    runner publishes the new result only once it is complete."""
    from dualhuman_builder.capture.log.reader import read_columns
    from dualhuman_builder.sync.timeline import SyncResult, synchronise

    try:
        take_file, depends_on = recording(ws, take)
        suits = None
    except WorkspaceError:
        suits = imported_suits(ws, take)
        if suits is None:
            if ws.take(take).meta.get("source_format") == "bvh":
                raise WorkspaceError(f"take {take!r} was imported from a BVH file, which sync cannot read as a suit",
                                     path=ws.root, fix="import the MVN recording as MVNX (File > Export in MVN "
                                                       "Analyze/Animate), or record the take with `dualhuman capture`") from None  # fmt: skip
            raise
        take_file, depends_on = None, []
    extra: dict = {} if suit_chain else {"suit_chain": False}
    if suits is not None:
        extra["imported"] = [s["skeleton"] for s in suits]
    if mounts_from:
        if mounts_from == take:
            raise WorkspaceError(f"take {take!r} cannot carry the mounts of itself",
                                 fix="name the calibration take of the same studio day with --mounts-from")  # fmt: skip
        ws.take(mounts_from)  # raises a clear error for an unknown take
        run_sync(ws, mounts_from, fps=fps, log=log, suit_chain=suit_chain)
        rec = SYNC.record(ws, mounts_from)
        extra.update(mounts_from=mounts_from, mounts_sha256=rec["artifacts"][SYNC_FILE]["sha256"])
        depends_on = [*depends_on, ("sync", None, mounts_from)]

    def compute(out):
        columns = read_columns(take_file) if suits is None else imported_columns(suits)
        cal = SyncResult.load(SYNC.artifact(ws, mounts_from, SYNC_FILE)) if mounts_from else None
        sync = synchronise(columns, fps=fps, use_trackers=use_trackers, progress=log, suit_chain=suit_chain,
                           mounts_from=cal, mounts_from_take=mounts_from or "")  # fmt: skip
        if suits is not None:
            for note in _imported_report(sync.report, suits):
                log(f"WARNING: {note}")
        sync.save(out.path(SYNC_FILE))
        out.path(REPORT_FILE).write_text(json.dumps(sync.report, indent=2, default=_json))
        return {"frames": int(len(sync.times_s)), "actors": [a.actor for a in sync.actors],
                "trackers": {a.actor: len(a.serials) for a in sync.actors},
                **({"mounts_from": sync.report.get("mounts_from", {})} if mounts_from else {}),
                **({"flags": sync.report["flags"]} if suits is not None else {})}  # fmt: skip

    return ws.run_stage(SYNC, compute, take=take, params={"fps": fps, "trackers": use_trackers, **extra},
                        depends_on=depends_on, version=SYNC_VERSION, force=force)  # fmt: skip


def load_sync(ws, take: str):
    """The take's :class:`~dualhuman_builder.sync.timeline.SyncResult` (its sync stage must be done)."""
    from dualhuman_builder.sync.timeline import SyncResult

    return SyncResult.load(SYNC.artifact(ws, take, SYNC_FILE))


def _json(o):
    """JSON fallback for the report: numpy scalars and arrays as Python values, anything else as str."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)

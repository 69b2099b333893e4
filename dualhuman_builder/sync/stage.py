"""The ``sync`` workspace stage of a recorded take (idempotent, crash-safe: see
:mod:`dualhuman_builder.workspace.runner`).

Artifacts (under ``WS/artifacts/TAKE/_take/sync/``): ``sync.npz``
(:class:`~dualhuman_builder.sync.timeline.SyncResult`: every stream on the timeline, tracker
mounts) and ``sync.json`` (clock offsets and drifts, lags, mounts, with uncertainties; with
``mounts_from``, which trackers kept the calibration take's mounts).

The take's recording is the ``take.mcap`` of its ``capture`` stage when it has one (a take
recorded into the workspace by that stage, e.g. a simulated one), otherwise the ``.mcap`` file
registered with the take (``dualhuman capture -w WS``).
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

    take_file, depends_on = recording(ws, take)
    extra: dict = {} if suit_chain else {"suit_chain": False}
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
        columns = read_columns(take_file)
        cal = SyncResult.load(SYNC.artifact(ws, mounts_from, SYNC_FILE)) if mounts_from else None
        sync = synchronise(columns, fps=fps, use_trackers=use_trackers, progress=log, suit_chain=suit_chain,
                           mounts_from=cal, mounts_from_take=mounts_from or "")  # fmt: skip
        sync.save(out.path(SYNC_FILE))
        out.path(REPORT_FILE).write_text(json.dumps(sync.report, indent=2, default=_json))
        return {"frames": int(len(sync.times_s)), "actors": [a.actor for a in sync.actors],
                "trackers": {a.actor: len(a.serials) for a in sync.actors},
                **({"mounts_from": sync.report.get("mounts_from", {})} if mounts_from else {})}  # fmt: skip

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

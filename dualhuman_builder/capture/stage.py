"""The ``capture`` workspace stage: record a sequence's sources into the workspace as an artifact
(idempotent, crash-safe: see :mod:`dualhuman_builder.workspace.runner`).

``dualhuman capture -w WS --take T`` records a live studio and registers the file with the take;
this stage is the same recording made reproducible as a stage of a sequence: the sources (any
source URL, typically a simulated studio played on loopback transports, ``sim://SCENE.npz``) are
recorded with :func:`~dualhuman_builder.capture.recording.capture_take`, the file is checked
(:func:`~dualhuman_builder.capture.log.reader.check_take`) and its raw packets re-decoded to prove
they give the recorded samples bit for bit (:func:`~dualhuman_builder.capture.replay.verify_replay`).

Artifacts (under ``WS/artifacts/TAKE/SEQUENCE/capture/``): ``take.mcap`` and ``capture.json``
(samples per topic, losses per source, events, the check and the replay verdict).

:func:`register_take_file` registers a take file recorded earlier (``dualhuman import WS
T001.mcap``), e.g. one whose registration failed when the capture ended on a full disk.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Callable, Sequence

from dualhuman_builder.errors import DualhumanError, FormatError, WorkspaceError
from dualhuman_builder.workspace.runner import Stage

TAKE_FILE, REPORT_FILE = "take.mcap", "capture.json"
CAPTURE = Stage("capture", per="sequence", artifacts=(TAKE_FILE, REPORT_FILE), reads=("scene",),
                command="dualhuman sim take {ws} --take {take}")  # fmt: skip


def record_take(url: str, take_path: Path, *, take: str, speed: float = 1.0, log: Callable[[str], None] = print) -> dict:
    """Record the source ``url`` into ``take_path`` (a studio URL such as ``sim://`` plays at
    ``speed`` times real time), check the file, and check that re-decoding its raw packets gives
    the recorded samples bit for bit. Returns the summary written to ``capture.json``; raises
    :class:`~dualhuman_builder.errors.DualhumanError` when the recording failed."""
    from dualhuman_builder.capture.log.reader import check_take
    from dualhuman_builder.capture.replay import verify_replay
    from dualhuman_builder.capture.recording import capture_take, plan_capture

    log(f"recording {url} ({speed:g}x real time)...")
    res = capture_take(plan_capture(sources=[url]), take_path, take=take, sim_speed=speed, progress=log)
    if res.error:
        raise DualhumanError(f"the capture of {take} failed: {res.error}")
    check = check_take(take_path)
    replay = verify_replay(take_path)
    lost = {name: int(sum(st.get(k, 0) for k in ("lost", "kernel_drops", "incomplete")))
            for name, st in res.source_stats.items()}  # fmt: skip
    log(f"take: {sum(res.samples_per_topic.values())} samples, {check.messages} messages, lost {lost}, "
        f"replay {'bit-identical' if replay.identical else 'DIFFERS'}")  # fmt: skip
    return {"samples": sum(res.samples_per_topic.values()), "per_topic": dict(res.samples_per_topic), "lost": lost,
            "sources": res.source_stats, "events": res.events, "messages": check.messages, "complete": check.ok,
            "replay_identical": replay.identical, "seconds": round(res.duration_s, 2)}  # fmt: skip


def run_capture(ws, take: str, sequence: str, url: str, *, speed: float = 1.0, params: dict | None = None,
                depends_on: Sequence[tuple[str, str | None]] = (), force: bool = False,
                log: Callable[[str], None] = print):  # fmt: skip
    """The ``capture`` stage of ``take``/``sequence``: :func:`record_take` of ``url`` into the
    stage's ``take.mcap``. ``params`` (default: the URL and speed) and ``depends_on`` (e.g. the
    ``scene`` stage a ``sim://`` URL plays) decide when it is stale. Returns the StageResult."""

    def compute(out):
        summary = record_take(url, out.path(TAKE_FILE), take=take, speed=speed, log=log)
        out.path(REPORT_FILE).write_text(json.dumps(summary, indent=2))
        return {k: summary[k] for k in ("samples", "lost", "replay_identical")}

    return ws.run_stage(CAPTURE, compute, take=take, sequence=sequence,
                        params=params if params is not None else {"url": url, "speed": speed},
                        depends_on=depends_on, force=force)  # fmt: skip


#: Topics of a take file that hold no decoded samples (raw packets, body-pose transforms, status, events).
NON_SAMPLE_TOPICS = ("raw/", "tf/", "status", "events")


def register_take_file(ws, path: str | Path, *, take: str | None = None, log: Callable[[str], None] = print):
    """Register the recorded take file ``path`` (MCAP, written by ``dualhuman capture``) in ``ws``
    as take ``take`` (default: the name recorded in the file). Returns the
    :class:`~dualhuman_builder.workspace.workspace.Take`.

    The whole file is read first (:func:`~dualhuman_builder.capture.log.reader.check_take`, CRCs
    checked): a file cut off by a crash or a full disk, or with damaged chunks, is refused with the
    advice to run ``dualhuman log repair`` first. A file already in ``WS/takes/TAKE/`` (where
    ``capture -w`` records) is registered where it is; one elsewhere is copied there (atomically)
    first. The take gets the file's start time, duration, sample counts per topic, and the actors
    its bindings name that the workspace knows (the others are listed in the take's meta); its rig
    when the workspace has one of the recorded rig name. Nothing is written when a check fails."""
    from dualhuman_builder.capture.importers import safe_take_name
    from dualhuman_builder.capture.log.reader import TakeReader, check_take
    from dualhuman_builder.fileio import atomic_path

    path = Path(path)
    if not path.is_file():
        raise FormatError("no such take file", path=path, fix="check the path")
    try:
        report = check_take(path)
        reader = TakeReader(path)
        reader.load_header()
        meta = reader.take_meta()
    except DualhumanError:
        raise
    except Exception as e:  # a reader that fails otherwise must not lose the file: say what it is
        raise FormatError(f"not a readable take file ({type(e).__name__}: {e})", path=path,
                          fix="check it with `dualhuman log check FILE`") from e  # fmt: skip
    if not report.ok:
        what = "was cut off (a crash or a full disk)" if not report.complete else "has damaged parts"
        raise FormatError(f"the take file {what}: {'; '.join(report.problems[:3]) or 'no index'}", path=path,
                          fix=f"repair it first with `dualhuman log repair {path}` (the original is kept), then "
                              "register the repaired file")  # fmt: skip
    if not meta:
        raise FormatError("the file has no take metadata: it was not written by `dualhuman capture`", path=path,
                          fix="register a take file recorded with `dualhuman capture`")  # fmt: skip
    name = take or str(meta.get("name") or "") or safe_take_name(path.stem)
    folder = ws.take_dir(name)  # checks the name
    if name in ws.takes():
        raise WorkspaceError(f"take {name!r} already exists", path=ws.root, fix="choose another name with --take NAME")
    bindings = meta.get("bindings") or {}
    names = list(dict.fromkeys(b["actor"] for entities in bindings.values() for b in entities.values()
                               if isinstance(b, dict) and b.get("actor")))  # fmt: skip
    known = {a.name for a in ws.actors()}
    rig = str(meta.get("rig_name") or "")
    rigs = {r for r, _ in ws.rigs()}
    counts = {t: n for t, n in sorted(report.per_topic.items()) if not t.startswith(NON_SAMPLE_TOPICS)}
    duration = None if report.first_ns is None else (report.last_ns - report.first_ns) / 1e9
    in_place = path.resolve().parent == folder.resolve()
    dest = path if in_place else folder / path.name
    if not in_place and dest.exists():
        raise WorkspaceError(f"{dest.name} is already in the take's folder but is not this file", path=dest,
                             fix="choose another take name with --take NAME, or move that file away")  # fmt: skip
    copied, existed = False, folder.exists()
    try:
        if not in_place:
            try:
                with atomic_path(dest) as tmp:
                    shutil.copyfile(path, tmp)
            except OSError as e:
                raise WorkspaceError(f"cannot copy the take file into the workspace: {e.strerror}", path=dest,
                                     fix=f"free space on the disk of {ws.root}, or move the file to {dest} yourself "
                                         "and register it there (it is then not copied)") from e  # fmt: skip
            copied = True
            log(f"copied {path.name} to {folder}")
        return ws.add_take(name, rig=rig if rig in rigs else None, actors=[n for n in names if n in known], files=[dest],
                           start_time=meta.get("start_utc") or None, duration_s=duration, sample_counts=counts,
                           meta={"source_format": "mcap", "source_file": path.name, "registered_from": str(path.resolve()),
                                 "rig_name": rig, "simulated": meta.get("simulated") or "", "actors": names,
                                 "unregistered_actors": [n for n in names if n not in known],
                                 "sources": meta.get("sources") or []})  # fmt: skip
    except BaseException:
        if copied:
            dest.unlink(missing_ok=True)
        if not existed and folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
        raise

"""The stage runner: idempotent, crash-safe execution of one stage for one take or sequence.

``run_stage(ws, "fit", compute, take="T001", sequence="hug-1", params={...})``:

1. The **parameters hash** covers the stage name, its code ``version``, ``params`` (canonical
   JSON) and, for each stage in ``depends_on``, that run's hash and artifact checksums — so a
   changed upstream result makes downstream stages stale.
2. If the catalog has a ``done`` row with the same hash and every artifact is on disk with its
   recorded size, nothing runs (a no-op). Otherwise the row is set to ``running`` (checked and
   set in one transaction, so two processes cannot both start it), old artifacts are removed, and
   ``compute(out)`` writes its files under ``out.path(name)`` — paths inside a hidden staging
   folder.
3. Only after ``compute`` returns are the files fsynced, renamed into place one by one
   (``os.replace``, atomic) with their SHA-256 recorded, and the row set to ``done``. A crash or
   ``kill -9`` at any point leaves the row ``running`` (shown as *interrupted* once its process is
   gone), no artifact the catalog lists as complete, and at most a staging folder that the next
   run deletes. An exception sets the row to ``failed`` with the error text and re-raises.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
import os
import re
import secrets
import shutil
import socket
import traceback
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, Callable, Mapping, Sequence

from dualhuman_builder.errors import WorkspaceError
from dualhuman_builder.fileio import sha256_file
from dualhuman_builder.workspace.catalog import now_iso, transaction

STAGING_PREFIX = ".staging-"


@dataclass(frozen=True)
class Stage:
    """What a workspace stage declares about itself, so that every other part asks it the same way.

    ``name``: the catalog's stage name; ``per``: ``"take"`` (one run per take) or ``"sequence"``
    (one per sequence of a take); ``artifacts``: the files it writes (``{actor}`` stands for each
    actor's name, ``/`` for folders); ``reads``: the stages whose artifacts it reads; ``command``:
    how a user runs it, with ``{ws}``, ``{take}`` and ``{sequence}`` filled in for error messages.
    """

    name: str
    per: str
    artifacts: tuple[str, ...]
    reads: tuple[str, ...] = ()
    command: str = ""

    def __post_init__(self) -> None:
        if self.per not in ("take", "sequence"):
            raise ValueError(f"stage {self.name!r}: per must be 'take' or 'sequence', not {self.per!r}")

    def declares(self, name: str) -> bool:
        """Whether artifact ``name`` (a path relative to the stage folder) is one this stage
        declares; each ``{placeholder}`` of :attr:`artifacts` stands for one path component."""
        parts = name.split("/")
        for pattern in self.artifacts:
            pp = pattern.split("/")
            if len(pp) == len(parts) and all(fnmatch.fnmatchcase(n, re.sub(r"\{[a-z_]+\}", "*", q))
                                              for n, q in zip(parts, pp)):  # fmt: skip
                return True
        return False

    def how_to_run(self, ws, take: str, sequence: str | None = None) -> str:
        """The command that runs this stage for ``take`` (and ``sequence``)."""
        if not self.command:
            return f"run the {self.name} stage of take {take} first"
        return self.command.format(ws=ws.root, take=take, sequence=sequence or "")

    def record(self, ws, take: str, sequence: str | None = None) -> dict[str, Any] | None:
        """The catalog row of this stage's run, or None if it never ran."""
        return stage_record(ws, self.name, take, sequence)

    def done(self, ws, take: str, sequence: str | None = None) -> bool:
        """Whether this stage's run for ``take`` (``sequence``) is complete."""
        rec = self.record(ws, take, sequence)
        return rec is not None and rec["status"] == "done"

    def artifact(self, ws, take: str, name: str, sequence: str | None = None, what: str | None = None) -> Path:
        """The path of artifact ``name`` of the complete run; a :class:`WorkspaceError` that says
        which command to run when the stage has not run, failed, or did not write ``name``
        (``what`` names the artifact for a person, e.g. "fitted bodies")."""
        rec = self.record(ws, take, sequence)
        where = f"{take}/{sequence}" if sequence else take
        fix = self.how_to_run(ws, take, sequence)
        if rec is None or rec["status"] != "done":
            state = "has not run" if rec is None else f"is {rec['status']}"
            raise WorkspaceError(f"take {where!r} has no {what or name}: its {self.name} stage {state}", path=ws.root,
                                 fix=fix)  # fmt: skip
        if name not in rec["artifacts"]:
            raise WorkspaceError(f"the {self.name} stage of {where} wrote no {name}", path=ws.root,
                                 fix=f"{fix} --force")  # fmt: skip
        return ws.root / rec["artifacts"][name]["path"]


class StageOutput:
    """Where ``compute`` writes: ``out.path("bodies.npz")`` returns a path in the staging folder
    (parent folders created); every file left in the staging folder becomes an artifact."""

    def __init__(self, staging: Path, final_dir: Path):
        self.staging = staging
        self.final_dir = final_dir

    def path(self, name: str) -> Path:
        rel = PurePosixPath(name)
        if rel.is_absolute() or ".." in rel.parts or not rel.parts or rel.parts[0].startswith("."):
            raise ValueError(f"artifact name {name!r} must be a relative path inside the stage folder")
        p = self.staging.joinpath(*rel.parts)
        p.parent.mkdir(parents=True, exist_ok=True)
        return p


@dataclass
class StageResult:
    stage: str
    take: str
    sequence: str | None
    params_hash: str
    artifacts: dict[str, Path]
    summary: dict[str, Any] = field(default_factory=dict)
    skipped: bool = False  # True when it was already up to date


def params_hash(stage: str, version: str, params: Mapping[str, Any], upstream: Sequence[Mapping]) -> str:
    blob = json.dumps({"stage": stage, "version": version, "params": params, "upstream": list(upstream)},
                      sort_keys=True, separators=(",", ":"), default=str)  # fmt: skip
    return hashlib.sha256(blob.encode("utf-8")).hexdigest()


def _row(ws, stage: str, take: str, sequence: str | None):
    tid = ws._take_id(take)
    sid = ws._sequence_id(take, sequence)
    row = ws.conn.execute(
        "SELECT * FROM stage_runs WHERE take_id = ? AND IFNULL(sequence_id, 0) = IFNULL(?, 0) AND stage = ?",
        (tid, sid, stage),
    ).fetchone()
    return tid, sid, row


def _record(row) -> dict[str, Any]:
    rec = {k: row[k] for k in row.keys() if k not in ("take_name", "seq_name")}
    rec["artifacts"] = json.loads(rec.pop("artifacts_json"))
    rec["params"] = json.loads(rec.pop("params_json"))
    rec["summary"] = json.loads(rec.pop("summary_json"))
    return rec


def stage_record(ws, stage: str, take: str, sequence: str | None = None) -> dict[str, Any] | None:
    _, _, row = _row(ws, stage, take, sequence)
    return None if row is None else _record(row)


def process_alive(pid: int | None, host: str | None) -> bool:
    """Whether the process that marked a run ``running`` may still be running."""
    if pid is None:
        return False
    if host and host != socket.gethostname():
        return True  # cannot tell from here: assume it is
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def describe_run(row) -> dict[str, Any]:
    """Short status of a stage row for tables: state, hash prefix, end time, error."""
    state = row["status"]
    if state == "running" and not process_alive(row["pid"], row["host"]):
        state = "interrupted"
    return {"state": state, "hash": row["params_hash"][:8], "ended_at": row["ended_at"],
            "error": row["error"], "artifacts": len(json.loads(row["artifacts_json"]))}  # fmt: skip


def artifact_problems(ws, rec: Mapping[str, Any], verify: bool = False) -> list[str]:
    """Problems with a done run's artifacts: missing files, size (or with ``verify``, SHA-256) changes."""
    problems = []
    for name, a in rec["artifacts"].items():
        p = ws.root / a["path"]
        if not p.is_file():
            problems.append(f"{name}: missing")
        elif p.stat().st_size != a["size"]:
            problems.append(f"{name}: size changed")
        elif verify and sha256_file(p) != a["sha256"]:
            problems.append(f"{name}: SHA-256 changed")
    return problems


def _clear_dir(folder: Path) -> None:
    if folder.exists():
        for child in folder.iterdir():
            if child.is_dir() and not child.is_symlink():
                shutil.rmtree(child)
            else:
                child.unlink()


def run_stage(ws, stage: str, compute: Callable[[StageOutput], Mapping[str, Any] | None], *, take: str,
              sequence: str | None = None, params: Mapping[str, Any], depends_on: Sequence[tuple[str, str | None]] = (),
              version: str = "1", force: bool = False) -> StageResult:  # fmt: skip
    """Run one stage if it is not up to date; see the module docstring. ``compute`` may return a
    JSON-serialisable summary dict, stored in the catalog."""
    where = f"{take}/{sequence}" if sequence else take
    upstream = []
    for up_stage, up_seq in depends_on:
        up = stage_record(ws, up_stage, take, up_seq)
        if up is None or up["status"] != "done":
            raise WorkspaceError(f"stage {stage!r} of {where} needs stage {up_stage!r} of "
                                 f"{take}/{up_seq or ''}".rstrip("/") + " to be complete first",
                                 path=ws.root, fix=f"run the {up_stage} stage first")  # fmt: skip
        upstream.append({"stage": up_stage, "sequence": up_seq, "params_hash": up["params_hash"],
                         "artifacts": {n: a["sha256"] for n, a in sorted(up["artifacts"].items())}})  # fmt: skip
    h = params_hash(stage, version, params, upstream)
    final_dir = ws.artifact_dir(stage, take, sequence)
    params_json = json.dumps(params, sort_keys=True, default=str)

    with transaction(ws.conn):
        tid, sid, row = _row(ws, stage, take, sequence)
        if row is not None and not force:
            if row["status"] == "done" and row["params_hash"] == h and not artifact_problems(ws, _record(row)):
                rec = _record(row)
                return StageResult(stage, take, sequence, h, {n: ws.root / a["path"] for n, a in rec["artifacts"].items()},
                                   rec["summary"], skipped=True)  # fmt: skip
        if row is not None and row["status"] == "running" and row["pid"] != os.getpid() \
                and process_alive(row["pid"], row["host"]) and not force:  # fmt: skip
            raise WorkspaceError(f"stage {stage!r} of {where} is already running (pid {row['pid']} on {row['host']})",
                                 path=ws.root, fix="wait for it, or pass --force if that process is gone")  # fmt: skip
        values = (h, params_json, now_iso(), os.getpid(), socket.gethostname())
        if row is None:
            ws.conn.execute(
                "INSERT INTO stage_runs (take_id, sequence_id, stage, status, params_hash, params_json, started_at, pid, host) "
                "VALUES (?, ?, ?, 'running', ?, ?, ?, ?, ?)", (tid, sid, stage, *values))  # fmt: skip
        else:
            ws.conn.execute(
                "UPDATE stage_runs SET status = 'running', params_hash = ?, params_json = ?, started_at = ?, pid = ?, "
                "host = ?, ended_at = NULL, error = NULL, artifacts_json = '{}', summary_json = '{}' WHERE id = ?",
                (*values, row["id"]))  # fmt: skip
        run_id = ws.conn.execute(
            "SELECT id FROM stage_runs WHERE take_id = ? AND IFNULL(sequence_id, 0) = IFNULL(?, 0) AND stage = ?",
            (tid, sid, stage)).fetchone()["id"]  # fmt: skip

    _clear_dir(final_dir)  # old artifacts and staging folders of interrupted runs
    staging = final_dir / f"{STAGING_PREFIX}{os.getpid()}-{secrets.token_hex(4)}"
    staging.mkdir(parents=True)
    try:
        summary = compute(StageOutput(staging, final_dir))
        if summary is not None and not isinstance(summary, Mapping):
            raise TypeError(f"a stage's compute must return None or a dict summary, got {type(summary).__name__}")
        summary = dict(summary or {})
        json.dumps(summary)  # must be JSON-serialisable: fail before publishing anything
        artifacts: dict[str, dict[str, Any]] = {}
        files = sorted(p for p in staging.rglob("*") if p.is_file())
        for p in files:
            with open(p, "rb+") as f:
                os.fsync(f.fileno())
        for p in files:
            rel = p.relative_to(staging)
            dest = final_dir / rel
            dest.parent.mkdir(parents=True, exist_ok=True)
            os.replace(p, dest)
            artifacts[rel.as_posix()] = {"path": dest.relative_to(ws.root).as_posix(),
                                         "size": dest.stat().st_size, "sha256": sha256_file(dest)}  # fmt: skip
        shutil.rmtree(staging, ignore_errors=True)
    except BaseException as e:
        shutil.rmtree(staging, ignore_errors=True)
        text = "interrupted" if isinstance(e, KeyboardInterrupt) else f"{type(e).__name__}: {e}"
        tb = "".join(traceback.format_exception(e)[-3:])
        with transaction(ws.conn):
            ws.conn.execute("UPDATE stage_runs SET status = 'failed', ended_at = ?, error = ? WHERE id = ?",
                            (now_iso(), f"{text}\n{tb}", run_id))  # fmt: skip
        raise
    with transaction(ws.conn):
        ws.conn.execute("UPDATE stage_runs SET status = 'done', ended_at = ?, artifacts_json = ?, summary_json = ? "
                        "WHERE id = ?", (now_iso(), json.dumps(artifacts), json.dumps(summary), run_id))  # fmt: skip
    return StageResult(stage, take, sequence, h, {n: ws.root / a["path"] for n, a in artifacts.items()}, summary)

"""The stage runner: idempotent, crash-safe execution of one stage for one take or sequence, whose
results are published atomically and whose changes make what reads them stale.

``run_stage(ws, FIT, compute, take="T001", sequence="hug-1", params={...})``:

1. The **parameters hash** covers the stage name, its code ``version``, ``params`` (canonical
   JSON) and, for each run in ``depends_on``, that run's hash and artifact checksums. Every run in
   ``depends_on`` must be ``done``, its files present with their recorded sizes, before anything
   is touched.
2. If the catalog has a ``done`` row with the same hash and every artifact is on disk with its
   recorded size, nothing runs (a no-op). Otherwise the run is marked in flight (checked and set
   in one transaction, so two processes cannot both start it) and ``compute(out)`` writes its
   files under ``out.path(name)``: paths in a hidden staging folder beside the stage's folder
   (``.STAGE.staging-*``). The published artifacts, and their ``done`` state, stay as they are.
3. **Publication**, once ``compute`` returned: the files are fsynced and hashed, the new set is
   recorded as being published (``attempt = 'publishing'``), the stage's folder is swapped for
   the staging folder (two renames: the old folder to ``.STAGE.old-*``, the staging folder into
   its place), and the row is set to ``done`` with the new artifacts in one transaction; then the
   old folder is deleted. A run killed (``kill -9``) before publication leaves the old result
   ``done`` and a staging folder the next run deletes; one killed during it leaves the row
   *publishing* (not done, shown as interrupted), which the next writable open of the workspace
   (:func:`finish_publications`) or run of the stage completes with the new set. No mix of the
   two sets is ever marked done.
4. An exception in ``compute`` publishes nothing: the old result keeps its state, the failure is
   recorded (``attempt = 'failed'`` and ``error``; ``status = 'failed'`` when nothing was
   published before) and the exception is re-raised.
5. **Invalidation**: a run that publishes another result than the one it replaces (another
   parameters hash or other artifact contents), or a forced one, marks every run that reads it,
   directly or through others, ``stale`` with the reason. What a run reads is recorded with it:
   its :class:`Stage`'s ``reads`` (the declarations in :mod:`dualhuman_builder.pipeline`) and its
   ``depends_on``. A ``stale`` run is not done: its artifacts stay for reference until it runs again.
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
from dualhuman_builder.fileio import fsync_dir, sha256_file
from dualhuman_builder.workspace.catalog import now_iso, transaction

#: Hidden folders beside a stage's folder: ``.STAGE.staging-PID-TOKEN`` (a run's new files) and
#: ``.STAGE.old-TOKEN`` (the replaced set, while it is swapped out).
STAGING_PREFIX, OLD_PREFIX = ".staging-", ".old-"
#: States of a run whose result is published (its artifacts are in the stage's folder).
PUBLISHED = ("done", "stale")


@dataclass(frozen=True)
class Stage:
    """What a workspace stage declares about itself, so that every other part asks it the same way.

    ``name``: the catalog's stage name; ``per``: ``"take"`` (one run per take) or ``"sequence"``
    (one per sequence of a take); ``artifacts``: the files it writes (``{actor}`` stands for each
    actor's name, ``/`` for folders); ``reads``: the stages whose artifacts it reads (a new result
    of one makes this stage stale); ``command``: how a user runs it, with ``{ws}``, ``{take}`` and
    ``{sequence}`` filled in for error messages.
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
        """The catalog row of this stage's run, or None if it never ran (see :func:`stage_record`)."""
        return stage_record(ws, self.name, take, sequence)

    def state(self, ws, take: str, sequence: str | None = None) -> str | None:
        """``done``, ``stale``, ``failed``, ``running``, ``publishing``, ``interrupted``, or None
        when it never ran: the state of its published result (:func:`stage_record`)."""
        rec = self.record(ws, take, sequence)
        return None if rec is None else rec["status"]

    def done(self, ws, take: str, sequence: str | None = None) -> bool:
        """Whether this stage's run for ``take`` (``sequence``) is complete and current (not stale)."""
        return self.state(ws, take, sequence) == "done"

    def artifact(self, ws, take: str, name: str, sequence: str | None = None, what: str | None = None) -> Path:
        """The path of artifact ``name`` of the complete run; a :class:`WorkspaceError` that says
        which command to run when the stage has not run, failed, is stale, or did not write ``name``
        (``what`` names the artifact for a person, e.g. "fitted bodies")."""
        rec = self.record(ws, take, sequence)
        where = f"{take}/{sequence}" if sequence else take
        fix = self.how_to_run(ws, take, sequence)
        if rec is None or rec["status"] != "done":
            state = "has not run" if rec is None else f"is {rec['status']}"
            stale = rec is not None and rec["status"] == "stale" and rec["stale_reason"]
            why = f" ({rec['stale_reason']})" if stale else ""
            raise WorkspaceError(f"take {where!r} has no {what or name}: its {self.name} stage {state}{why}",
                                 path=ws.root, fix=fix)  # fmt: skip
        if name not in rec["artifacts"]:
            raise WorkspaceError(f"the {self.name} stage of {where} wrote no {name}", path=ws.root,
                                 fix=f"{fix} --force")  # fmt: skip
        return ws.root / rec["artifacts"][name]["path"]


class StageOutput:
    """Where ``compute`` writes: ``out.path("bodies.npz")`` returns a path in the staging folder
    (parent folders created); every file left in the staging folder becomes an artifact, published
    under ``final_dir`` once the run is complete."""

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
    #: The runs its new result made stale: ``(take, sequence or None, stage)``.
    made_stale: list[tuple[str, str | None, str]] = field(default_factory=list)


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


def _get(row, key: str, default=None):
    """``row[key]``, or ``default`` for a column a catalog not yet migrated (opened read-only) lacks."""
    return row[key] if key in row.keys() else default  # noqa: SIM118 - `in` on a sqlite3.Row looks at its values


def _in_flight(row) -> bool:
    """Whether the row's latest attempt has not ended (its process may be gone)."""
    return row["status"] == "running" or _get(row, "attempt") in ("running", "publishing")


def _record(row) -> dict[str, Any]:
    """A stage row as a dict; ``status`` is the state of its published result, except while a
    publication is under way (``publishing``) or was cut off (``interrupted``): neither is done."""
    rec = {k: row[k] for k in row.keys() if k not in ("take_name", "seq_name")}  # noqa: SIM118 - a sqlite3.Row
    rec["artifacts"] = json.loads(rec.pop("artifacts_json"))
    rec["params"] = json.loads(rec.pop("params_json"))
    rec["summary"] = json.loads(rec.pop("summary_json"))
    rec["reads"] = json.loads(rec.pop("reads_json", None) or "[]")
    rec["publish"] = json.loads(rec.pop("publish_json", None) or "null")
    rec.setdefault("attempt", None)
    rec.setdefault("stale_reason", None)
    if rec["attempt"] == "publishing":
        rec["status"] = "publishing" if process_alive(row["pid"], row["host"]) else "interrupted"
    return rec


def stage_record(ws, stage: str, take: str, sequence: str | None = None) -> dict[str, Any] | None:
    """The catalog row of a stage run as a dict (``status``, ``artifacts``, ``params``,
    ``summary``, ``reads``, ``attempt``, ``error``, ``stale_reason``, ...), or None."""
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
    """Short status of a stage row for tables: ``state`` (``done``, ``stale``, ``failed``,
    ``running``, ``interrupted``), hash prefix, end time, ``error`` (why it failed or is stale, or
    how a re-run that has not replaced the published result went: "a re-run failed (the previous
    result is kept): ..."), artifact count."""
    state, attempt, error = row["status"], _get(row, "attempt"), row["error"]
    alive = _in_flight(row) and process_alive(row["pid"], row["host"])
    kept = f"the {'stale ' if state == 'stale' else ''}previous result is kept"
    if attempt == "publishing":
        state, attempt = ("running" if alive else "interrupted"), None
        error = None if alive else "interrupted while publishing its new result: run the stage again to finish it"
    elif state == "running":
        state = "running" if alive else "interrupted"
    elif attempt == "running" and alive:
        state, error = "running", f"re-running; {kept} until it is done"
    elif attempt == "running":
        attempt, error = "interrupted", f"a re-run was interrupted ({kept})"
    elif attempt == "failed":
        error = f"a re-run failed ({kept}): {(error or '').strip()}"
    if row["status"] == "stale" and state == "stale":
        reason = _get(row, "stale_reason") or "an input changed since it ran"
        error = reason if attempt is None else f"{reason}; {error}"
    return {"state": state, "hash": row["params_hash"][:8], "ended_at": row["ended_at"], "error": error,
            "artifacts": len(json.loads(row["artifacts_json"]))}  # fmt: skip


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


def _sweep(final_dir: Path) -> None:
    """Delete the staging and replaced folders runs of this stage left beside ``final_dir`` (and
    hidden folders inside it): called only while holding the stage's run."""
    name = final_dir.name
    parent = final_dir.parent
    leftovers = [*parent.glob(f".{name}{STAGING_PREFIX}*"), *parent.glob(f".{name}{OLD_PREFIX}*")]
    if final_dir.is_dir():
        leftovers += [p for p in final_dir.iterdir() if p.name.startswith(".") and p.is_dir()]
    for p in leftovers:
        shutil.rmtree(p, ignore_errors=True)


def _dependency(dep: Sequence, take: str) -> tuple[str, str, str | None]:
    """``(take, stage, sequence)`` of a ``depends_on`` entry: ``(stage, sequence)`` of the same take,
    or ``(stage, sequence, take)`` of another."""
    if len(dep) == 2:
        return take, dep[0], dep[1]
    if len(dep) == 3:
        return dep[2], dep[0], dep[1]
    raise ValueError(f"a depends_on entry is (stage, sequence) or (stage, sequence, take), not {dep!r}")


def run_stage(ws, stage: str | Stage, compute: Callable[[StageOutput], Mapping[str, Any] | None], *, take: str,
              sequence: str | None = None, params: Mapping[str, Any], depends_on: Sequence[Sequence] = (),
              version: str = "1", force: bool = False) -> StageResult:  # fmt: skip
    """Run one stage if it is not up to date, and publish its result atomically; see the module
    docstring. ``stage``: its :class:`Stage` (whose ``reads`` are recorded) or its name;
    ``depends_on``: ``(stage, sequence)`` runs of the same take, or ``(stage, sequence, take)`` of
    another, that must be done. ``compute`` may return a JSON-serialisable summary dict, stored in
    the catalog."""
    name = stage.name if isinstance(stage, Stage) else stage
    where = f"{take}/{sequence}" if sequence else take
    deps = [_dependency(d, take) for d in depends_on]
    undeclared = sorted({s for t, s, _ in deps if t == take} - set(stage.reads)) if isinstance(stage, Stage) else []
    if undeclared:
        raise ValueError(f"stage {name!r} depends on {undeclared}, which its declaration does not read")
    upstream = []
    for up_take, up_stage, up_seq in deps:
        up = stage_record(ws, up_stage, up_take, up_seq)
        if up is None or up["status"] != "done":
            state = "never ran" if up is None else f"is {up['status']}"
            raise WorkspaceError(f"stage {name!r} of {where} needs stage {up_stage!r} of "
                                 f"{up_take}/{up_seq or ''}".rstrip("/") + f" to be complete first (it {state})",
                                 path=ws.root, fix=f"run the {up_stage} stage first")  # fmt: skip
        changed = artifact_problems(ws, up)
        if changed:
            raise WorkspaceError(f"stage {name!r} of {where} needs stage {up_stage!r} of "
                                 f"{up_take}/{up_seq or ''}".rstrip("/") + f", whose files changed on disk: "
                                 f"{', '.join(changed[:3])}", path=ws.root,
                                 fix=f"restore them, or run the {up_stage} stage again with --force "
                                     f"(`dualhuman status {ws.root} --verify` lists every change)")  # fmt: skip
        entry = {"stage": up_stage, "sequence": up_seq, "params_hash": up["params_hash"],
                 "artifacts": {n: a["sha256"] for n, a in sorted(up["artifacts"].items())}}  # fmt: skip
        upstream.append(entry if up_take == take else {**entry, "take": up_take})
    h = params_hash(name, version, params, upstream)
    reads = sorted({*(stage.reads if isinstance(stage, Stage) else ()),
                    *(s if t == take else f"{t}/{s}" for t, s, _ in deps)})  # fmt: skip
    final_dir = ws.artifact_dir(name, take, sequence)
    params_json = json.dumps(params, sort_keys=True, default=str)

    with transaction(ws.conn):
        tid, sid, row = _row(ws, name, take, sequence)
        if row is not None and row["attempt"] == "publishing" and not process_alive(row["pid"], row["host"]):
            _finish(ws, row)
            tid, sid, row = _row(ws, name, take, sequence)
        if row is not None and not force and row["status"] == "done" and row["attempt"] != "publishing" \
                and row["params_hash"] == h and not artifact_problems(ws, _record(row)):  # fmt: skip
            if row["attempt"] == "failed" or (row["attempt"] == "running" and not process_alive(row["pid"], row["host"])):
                ws.conn.execute("UPDATE stage_runs SET attempt = NULL, error = NULL WHERE id = ?", (row["id"],))
            rec = _record(row)
            return StageResult(name, take, sequence, h, {n: ws.root / a["path"] for n, a in rec["artifacts"].items()},
                               rec["summary"], skipped=True)  # fmt: skip
        if row is not None and _in_flight(row) and (row["pid"] != os.getpid() or row["host"] != socket.gethostname()) \
                and process_alive(row["pid"], row["host"]) and (not force or row["attempt"] == "publishing"):  # fmt: skip
            raise WorkspaceError(f"stage {name!r} of {where} is already running (pid {row['pid']} on {row['host']})",
                                 path=ws.root, fix="wait for it, or pass --force if that process is gone")  # fmt: skip
        me = (now_iso(), os.getpid(), socket.gethostname())
        if row is None:
            ws.conn.execute(
                "INSERT INTO stage_runs (take_id, sequence_id, stage, status, params_hash, params_json, started_at, pid, "
                "host, reads_json) VALUES (?, ?, ?, 'running', ?, ?, ?, ?, ?, ?)",
                (tid, sid, name, h, params_json, *me, json.dumps(reads)))  # fmt: skip
        elif row["status"] in PUBLISHED:  # the published result stays until the new one replaces it
            ws.conn.execute("UPDATE stage_runs SET attempt = 'running', started_at = ?, pid = ?, host = ?, error = NULL, "
                            "publish_json = NULL WHERE id = ?", (*me, row["id"]))  # fmt: skip
        else:
            ws.conn.execute(
                "UPDATE stage_runs SET status = 'running', params_hash = ?, params_json = ?, started_at = ?, pid = ?, "
                "host = ?, ended_at = NULL, error = NULL, artifacts_json = '{}', summary_json = '{}', attempt = NULL, "
                "publish_json = NULL, reads_json = ? WHERE id = ?",
                (h, params_json, *me, json.dumps(reads), row["id"]))  # fmt: skip
        run_id = ws.conn.execute(
            "SELECT id FROM stage_runs WHERE take_id = ? AND IFNULL(sequence_id, 0) = IFNULL(?, 0) AND stage = ?",
            (tid, sid, name)).fetchone()["id"]  # fmt: skip

    _sweep(final_dir)  # staging and replaced folders of runs that were killed
    staging = final_dir.parent / f".{name}{STAGING_PREFIX}{os.getpid()}-{secrets.token_hex(4)}"
    staging.mkdir(parents=True)
    publishing = False
    try:
        summary = compute(StageOutput(staging, final_dir))
        if summary is not None and not isinstance(summary, Mapping):
            raise TypeError(f"a stage's compute must return None or a dict summary, got {type(summary).__name__}")
        summary = dict(summary or {})
        json.dumps(summary)  # must be JSON-serialisable: fail before publishing anything
        artifacts: dict[str, dict[str, Any]] = {}
        for p in sorted(p for p in staging.rglob("*") if p.is_file()):
            with open(p, "rb+") as f:
                os.fsync(f.fileno())
            rel = p.relative_to(staging).as_posix()
            artifacts[rel] = {"path": (final_dir / rel).relative_to(ws.root).as_posix(), "size": p.stat().st_size,
                              "sha256": sha256_file(p)}  # fmt: skip
        for d in sorted((p for p in staging.rglob("*") if p.is_dir()), reverse=True):
            fsync_dir(d)
        fsync_dir(staging)
        publish = {"staging": staging.name, "old": f".{name}{OLD_PREFIX}{secrets.token_hex(4)}", "params_hash": h,
                   "params_json": params_json, "reads": reads, "artifacts": artifacts, "summary": summary,
                   "upstream": [[t, s, q] for t, s, q in deps], "inputs": upstream, "force": bool(force)}  # fmt: skip
        with transaction(ws.conn):
            row = ws.conn.execute("SELECT * FROM stage_runs WHERE id = ?", (run_id,)).fetchone()
            if row is None or row["pid"] != os.getpid() or row["host"] != socket.gethostname() or not _in_flight(row):
                raise WorkspaceError(f"stage {name!r} of {where} was started again by another process meanwhile; "
                                     "this run's result is dropped", path=ws.root, fix="see `dualhuman status`")  # fmt: skip
            ws.conn.execute("UPDATE stage_runs SET attempt = 'publishing', publish_json = ? WHERE id = ?",
                            (json.dumps(publish), run_id))  # fmt: skip
        publishing = True
        with transaction(ws.conn):
            rec = _finish(ws, ws.conn.execute("SELECT * FROM stage_runs WHERE id = ?", (run_id,)).fetchone())
        if rec["status"] not in PUBLISHED or rec["attempt"] is not None:
            raise WorkspaceError(f"stage {name!r} of {where}: {rec['error']}", path=ws.root,
                                 fix="run the stage again")  # fmt: skip
    except BaseException as e:
        if publishing:  # the new set is complete: finish switching it in if the catalog can still be written
            try:
                with transaction(ws.conn):
                    row = ws.conn.execute("SELECT * FROM stage_runs WHERE id = ?", (run_id,)).fetchone()
                    if row is not None and row["attempt"] == "publishing":
                        _finish(ws, row)
            except (WorkspaceError, OSError):  # left 'publishing': the next writable open or run finishes it
                pass
            raise
        shutil.rmtree(staging, ignore_errors=True)
        text = "interrupted" if isinstance(e, KeyboardInterrupt) else f"{type(e).__name__}: {e}"
        tb = "".join(traceback.format_exception(e)[-3:])
        try:
            with transaction(ws.conn):
                row = ws.conn.execute("SELECT * FROM stage_runs WHERE id = ?", (run_id,)).fetchone()
                if row is not None and row["pid"] == os.getpid() and _in_flight(row):
                    if row["status"] in PUBLISHED:  # the published result and its state stay
                        ws.conn.execute("UPDATE stage_runs SET attempt = 'failed', error = ? WHERE id = ?",
                                        (f"{text}\n{tb}", run_id))  # fmt: skip
                    else:
                        ws.conn.execute("UPDATE stage_runs SET status = 'failed', ended_at = ?, error = ? WHERE id = ?",
                                        (now_iso(), f"{text}\n{tb}", run_id))  # fmt: skip
        except WorkspaceError:
            pass  # the catalog cannot be written (a full disk): the run shows as interrupted
        raise
    return StageResult(name, take, sequence, h, {n: ws.root / a["path"] for n, a in rec["artifacts"].items()},
                       rec["summary"], made_stale=rec.get("made_stale", []))  # fmt: skip


def _names(ws, row) -> tuple[str, str | None]:
    """``(take, sequence)`` of the stage run in ``row``."""
    take = ws.conn.execute("SELECT name FROM takes WHERE id = ?", (row["take_id"],)).fetchone()["name"]
    seq = None
    if row["sequence_id"] is not None:
        seq = ws.conn.execute("SELECT name FROM sequences WHERE id = ?", (row["sequence_id"],)).fetchone()["name"]
    return take, seq


def _switch(ws, final_dir: Path, publish: Mapping[str, Any]) -> bool:
    """Swap ``final_dir`` for the staging folder of ``publish``, each step only if it is not done
    yet (so a cut-off switch is finished by calling it again); False when the new set is neither
    staged nor in place."""
    staging, old = final_dir.parent / publish["staging"], final_dir.parent / publish["old"]
    if staging.is_dir():
        if final_dir.exists():
            if old.exists():  # not made by a switch (which moves it to ``old`` first): made by hand since
                shutil.rmtree(final_dir)
            else:
                os.rename(final_dir, old)
        os.rename(staging, final_dir)
        fsync_dir(final_dir.parent)
    return all((ws.root / a["path"]).is_file() and (ws.root / a["path"]).stat().st_size == a["size"]
               for a in publish["artifacts"].values())  # fmt: skip


def _finish(ws, row) -> dict[str, Any]:
    """Complete the publication recorded in ``row`` (inside a transaction): switch the folders,
    record the new result ``done`` (``stale`` when an input changed while it ran), make what reads
    it stale when it differs from the result it replaces, delete the replaced set. A publication
    whose new files are gone is recorded as failed, with the replaced set put back."""
    publish = json.loads(row["publish_json"])
    take, seq = _names(ws, row)
    final_dir = ws.artifact_dir(row["stage"], take, seq)
    old = final_dir.parent / publish["old"]
    if not _switch(ws, final_dir, publish):
        if old.is_dir():
            shutil.rmtree(final_dir, ignore_errors=True)
            os.rename(old, final_dir)
        error = "interrupted while publishing, and its new files are gone"
        if row["status"] in PUBLISHED:
            ws.conn.execute("UPDATE stage_runs SET attempt = 'failed', error = ?, publish_json = NULL WHERE id = ?",
                            (error, row["id"]))  # fmt: skip
        else:
            ws.conn.execute("UPDATE stage_runs SET status = 'failed', attempt = NULL, error = ?, publish_json = NULL "
                            "WHERE id = ?", (error, row["id"]))  # fmt: skip
        return _record(ws.conn.execute("SELECT * FROM stage_runs WHERE id = ?", (row["id"],)).fetchone())
    new_shas = {n: a["sha256"] for n, a in publish["artifacts"].items()}
    old_shas = {n: a["sha256"] for n, a in json.loads(row["artifacts_json"]).items()}
    changed = publish["force"] or row["status"] not in PUBLISHED or row["params_hash"] != publish["params_hash"] \
        or old_shas != new_shas  # fmt: skip
    moved = _inputs_moved(ws, publish)
    status, reason = ("stale", f"{moved} changed while it ran") if moved else ("done", None)
    ws.conn.execute(
        "UPDATE stage_runs SET status = ?, stale_reason = ?, attempt = NULL, publish_json = NULL, error = NULL, "
        "params_hash = ?, params_json = ?, artifacts_json = ?, summary_json = ?, reads_json = ?, ended_at = ? "
        "WHERE id = ?",
        (status, reason, publish["params_hash"], publish["params_json"], json.dumps(publish["artifacts"]),
         json.dumps(publish["summary"]), json.dumps(publish["reads"]), now_iso(), row["id"]))  # fmt: skip
    marked = []
    if changed:
        where = f"{take}/{seq}" if seq else take
        why = f"{row['stage']} of {where} {'was run again (forced)' if publish['force'] else 'has a new result'}"
        marked = invalidate(ws, row["take_id"], row["sequence_id"], row["stage"], why)
    shutil.rmtree(old, ignore_errors=True)
    return {**_record(ws.conn.execute("SELECT * FROM stage_runs WHERE id = ?", (row["id"],)).fetchone()),
            "made_stale": marked}


def _inputs_moved(ws, publish: Mapping[str, Any]) -> str | None:
    """The first run this publication read (its ``depends_on``) whose result is no longer the one
    it started from, as "STAGE of TAKE[/SEQUENCE]"; None when all are unchanged."""
    for (up_take, up_stage, up_seq), before in zip(publish["upstream"], publish["inputs"]):
        up = stage_record(ws, up_stage, up_take, up_seq)
        now = None if up is None else {n: a["sha256"] for n, a in sorted(up["artifacts"].items())}
        if up is None or up["status"] != "done" or (up["params_hash"], now) != (before["params_hash"], before["artifacts"]):
            return f"{up_stage} of {up_take}/{up_seq}" if up_seq else f"{up_stage} of {up_take}"
    return None


def invalidate(ws, take_id: int, sequence_id: int | None, stage: str, reason: str) -> list[tuple[str, str | None, str]]:
    """Mark ``stale`` (with ``reason``) every done run that reads ``stage`` of the take
    ``take_id`` (sequence ``sequence_id``; None for a take-level stage), directly or through other
    runs, as their recorded reads say: ``STAGE`` of the same take (a per-sequence reader of a
    per-sequence stage only in the same sequence), ``TAKE/STAGE`` of another. Call inside a
    transaction. Returns ``(take, sequence, stage)`` of the runs marked."""
    rows = ws.conn.execute(
        "SELECT r.id, r.take_id, r.sequence_id, r.stage, r.status, r.reads_json, t.name AS take_name, "
        "s.name AS seq_name FROM stage_runs r JOIN takes t ON t.id = r.take_id "
        "LEFT JOIN sequences s ON s.id = r.sequence_id").fetchall()  # fmt: skip
    names = {r["take_id"]: r["take_name"] for r in rows}
    names.setdefault(take_id, ws.conn.execute("SELECT name FROM takes WHERE id = ?", (take_id,)).fetchone()["name"])
    reads = {r["id"]: set(json.loads(r["reads_json"])) for r in rows}
    changed = [(take_id, sequence_id, stage)]
    seen = {r["id"] for r in rows if (r["take_id"], r["sequence_id"], r["stage"]) == changed[0]}
    marked = []
    while changed:
        t, q, st = changed.pop()
        for r in rows:
            if r["id"] in seen:
                continue
            same_take = r["take_id"] == t and st in reads[r["id"]] and (q is None or r["sequence_id"] in (None, q))
            if not same_take and f"{names[t]}/{st}" not in reads[r["id"]]:
                continue
            seen.add(r["id"])
            changed.append((r["take_id"], r["sequence_id"], r["stage"]))
            if r["status"] == "done":
                ws.conn.execute("UPDATE stage_runs SET status = 'stale', stale_reason = ? WHERE id = ?",
                                (reason, r["id"]))  # fmt: skip
                marked.append((r["take_name"], r["seq_name"], r["stage"]))
    return marked


def finish_publications(ws) -> int:
    """Complete every publication whose process was killed mid-way (see the module docstring);
    returns how many. Called when a workspace is opened for writing."""
    pending = ws.conn.execute("SELECT id, pid, host FROM stage_runs WHERE attempt = 'publishing'").fetchall()
    n = 0
    for p in pending:
        if process_alive(p["pid"], p["host"]):
            continue
        with transaction(ws.conn):
            row = ws.conn.execute("SELECT * FROM stage_runs WHERE id = ?", (p["id"],)).fetchone()
            if row is not None and row["attempt"] == "publishing" and not process_alive(row["pid"], row["host"]):
                _finish(ws, row)
                n += 1
    return n

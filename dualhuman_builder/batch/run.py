"""The batch driver: every pending stage of every take of a workspace, on a local process pool or
a Ray cluster (:func:`run_workspace`, ``dualhuman run``).

The driver plans the tasks (:func:`~dualhuman_builder.batch.plan.make_plan`), hands each take's
stages out in order as their predecessors finish, retries a task that fails or whose worker dies
(``retries`` times), then records it failed and skips the take's later stages with the reason;
the other takes go on. One driver per workspace at a time: it holds ``WS/.run.lock`` (an
``fcntl`` lock, released by the system when the process ends, however it ends), and a second
one refuses with the holder's pid and host. Resuming after Ctrl-C or a crash is running it again:
only what the catalog records ``done`` is skipped, and the stage runner never records a partial
result as done.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import os
import socket
import sqlite3
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dualhuman_builder.batch.plan import Plan, RunOptions, make_plan
from dualhuman_builder.errors import DualhumanError, WorkspaceError

LOCK_NAME = ".run.lock"
#: The local workers' standard error, appended to by every run.
WORKER_LOG = ".run-workers.log"


@dataclass
class Outcome:
    """What became of one stage of one take: ``state`` is ``done`` (done before this run),
    ``ran`` (done by it), ``failed`` (``error`` says why), ``skipped`` (``error`` says why) or
    ``pending`` (not reached: the run was interrupted); ``tries`` it took, ``seconds`` of the last."""

    state: str
    error: str | None = None
    tries: int = 0
    seconds: float = 0.0


@dataclass
class RunSummary:
    """The outcome of every (take, stage) the run considered, the executor, the wall time."""

    outcomes: dict[tuple[str, str], Outcome] = field(default_factory=dict)
    takes: list[str] = field(default_factory=list)
    stages: list[str] = field(default_factory=list)
    executor: str = "local"
    workers: int = 0
    seconds: float = 0.0
    interrupted: bool = False

    def count(self, state: str) -> int:
        return sum(o.state == state for o in self.outcomes.values())

    @property
    def failed(self) -> list[tuple[str, str]]:
        return [k for k, o in self.outcomes.items() if o.state == "failed"]


def after_stage(ws, take: str, stage: str) -> str | None:
    """Called in the driver after each stage of a take finishes successfully: the quality gates check the
    take again and store its flags (:func:`~dualhuman_builder.quality.gates.check_take`; ``status``,
    ``review`` and ``export`` read them). A reason (text) returned would skip the take's later stages;
    the gates never stop a take, since a flagged take may still be exported with ``--include-flagged``."""
    from dualhuman_builder.quality.gates import check_take

    check_take(ws, take)
    return None


# ---------------------------------------------------------------------------------------------- lock
def lock_holder(path: Path) -> dict[str, Any]:
    """What the lock file says about the run holding it (``pid``, ``host``, ``started``); empty
    when it says nothing readable."""
    try:
        info = json.loads(Path(path).read_text() or "{}")
    except (OSError, ValueError):
        return {}
    return info if isinstance(info, dict) else {}


@contextlib.contextmanager
def workspace_lock(root: Path) -> Iterator[Path]:
    """Hold ``root/.run.lock`` for the duration; a :class:`WorkspaceError` naming the other run
    when one holds it. The lock is the file's ``flock``, which the system drops when its holder
    ends (also when it is killed), so a crashed run never blocks the next one."""
    path = Path(root) / LOCK_NAME
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            who = lock_holder(path)
            by = f" (pid {who.get('pid')} on {who.get('host')}, started {who.get('started')})" if who else ""
            raise WorkspaceError(f"another `dualhuman run` is running on this workspace{by}", path=root,
                                 fix="wait for it to finish (or stop it with Ctrl-C) and run again: it resumes "
                                     "where the other one stopped") from None  # fmt: skip
        from dualhuman_builder.workspace.catalog import now_iso

        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "started": now_iso()}).encode(), 0)
        yield path
    finally:
        os.close(fd)  # drops the lock


# ---------------------------------------------------------------------------------------------- catalog
def merge_rows(ws, rows: list) -> None:
    """Record in the catalog the ``stage_runs`` rows a shadow run changed (``[take, sequence, row]``
    each; :func:`~dualhuman_builder.batch.worker.run_in_shadow`), in one transaction."""
    from dualhuman_builder.batch.worker import ROW_KEYS
    from dualhuman_builder.workspace.catalog import transaction

    if not rows:
        return
    with transaction(ws.conn):
        for take, seq, row in rows:
            tid, sid = ws._take_id(take), ws._sequence_id(take, seq)
            cur = ws.conn.execute(f"UPDATE stage_runs SET {', '.join(f'{k} = ?' for k in ROW_KEYS)} "
                                  "WHERE take_id = ? AND IFNULL(sequence_id, 0) = IFNULL(?, 0) AND stage = ?",
                                  (*[row[k] for k in ROW_KEYS], tid, sid, row["stage"]))  # fmt: skip
            if cur.rowcount == 0:
                ws.conn.execute(f"INSERT INTO stage_runs (take_id, sequence_id, {', '.join(ROW_KEYS)}) "
                                f"VALUES (?, ?, {', '.join('?' * len(ROW_KEYS))})",
                                (tid, sid, *[row[k] for k in ROW_KEYS]))  # fmt: skip


def record_failure(ws, take: str, stage: str, why: str) -> None:
    """Record in the catalog that ``stage`` of ``take`` failed (``why``) where the stage runner
    could not: a run a dead worker left in flight, or a stage that failed before it started (its
    inputs missing) and has no run yet. A published result and its state stay (the failure is the
    latest attempt's); a failure the runner recorded keeps its own error."""
    from dualhuman_builder.pipeline import stage as declared
    from dualhuman_builder.workspace.catalog import now_iso, transaction
    from dualhuman_builder.workspace.runner import process_alive

    st = declared(stage)
    with transaction(ws.conn):
        tid = ws._take_id(take)
        rows = ws.conn.execute("SELECT id, status, attempt, pid, host FROM stage_runs WHERE take_id = ? AND stage = ?",
                               (tid, stage)).fetchall()  # fmt: skip
        if not rows and st.per == "take":
            ws.conn.execute("INSERT INTO stage_runs (take_id, sequence_id, stage, status, params_hash, params_json, "
                            "started_at, ended_at, error, pid, host, reads_json) VALUES (?, NULL, ?, 'failed', '', '{}', "
                            "?, ?, ?, ?, ?, ?)", (tid, stage, now_iso(), now_iso(), why, os.getpid(), socket.gethostname(),
                                                  json.dumps(list(st.reads))))  # fmt: skip
        for r in rows:
            in_flight = r["status"] == "running" or r["attempt"] in ("running", "publishing")
            if in_flight and process_alive(r["pid"], r["host"]):
                continue
            if r["attempt"] == "running" or (r["status"] == "stale" and r["attempt"] is None):
                ws.conn.execute("UPDATE stage_runs SET attempt = 'failed', error = ? WHERE id = ?", (why, r["id"]))
            elif r["status"] == "running":
                ws.conn.execute("UPDATE stage_runs SET status = 'failed', ended_at = ?, error = ? WHERE id = ?",
                                (now_iso(), why, r["id"]))  # fmt: skip


def catalog_bytes(ws) -> bytes:
    """A consistent copy of the catalog as one SQLite file's bytes (what a Ray task runs against)."""
    copy = sqlite3.connect(":memory:")
    try:
        ws.conn.backup(copy)
        return copy.serialize()
    finally:
        copy.close()


# ---------------------------------------------------------------------------------------------- driver
def run_workspace(root: str | Path, options: RunOptions | None = None, *, executor: str = "local",
                  address: str | None = None, on_event: Callable[..., None] | None = None,
                  after_stage: Callable[[Any, str, str], str | None] = after_stage) -> RunSummary:  # fmt: skip
    """Run every pending stage of the takes of the workspace at ``root`` as ``options`` says, on
    ``executor`` (``local``: a pool of worker processes, ``ray``: the Ray cluster at ``address``).
    ``on_event(kind, take, stage, info)`` is told ``plan`` (``info``: the :class:`Plan`),
    ``start``, ``log`` (a line), ``end`` (the :class:`Outcome`) and ``retry`` (the error).
    ``after_stage(ws, take, stage)`` is called after each stage that succeeds. Returns the
    :class:`RunSummary`; a KeyboardInterrupt stops the workers and is re-raised with the summary
    so far on the exception (``summary``)."""
    from dualhuman_builder.batch.executors import (
        LocalExecutor,
        RayExecutor,
        default_workers,
    )
    from dualhuman_builder.workspace import Workspace

    if executor not in ("local", "ray"):
        raise DualhumanError(f"no executor {executor!r}", fix="choose local or ray")
    root = Path(root)
    options = options or RunOptions()
    emit = on_event or (lambda *a: None)
    t0 = time.perf_counter()
    with Workspace.open(root) as ws, workspace_lock(root):
        plan = make_plan(ws, options)
        summary = RunSummary(takes=plan.takes, stages=list(options.wanted()), executor=executor)
        for key in plan.done:
            summary.outcomes[key] = Outcome("done")
        for key, why in plan.skipped.items():
            summary.outcomes[key] = Outcome("skipped", why)
        for t in plan.tasks:
            summary.outcomes[t.key] = Outcome("pending")
        emit("plan", None, None, plan)
        if not plan.tasks:
            summary.seconds = time.perf_counter() - t0
            return summary
        if executor == "local":
            size = min(options.workers or default_workers(), len(plan.tasks))
            pool: Any = LocalExecutor(root, size, root / WORKER_LOG)
        else:
            pool = RayExecutor(root, address, options.retries, slots=options.workers)
        summary.workers = pool.size
        try:
            _drive(ws, plan, options, pool, summary, emit, after_stage)
        except KeyboardInterrupt as e:
            summary.interrupted = True
            summary.seconds = time.perf_counter() - t0
            e.summary = summary  # type: ignore[attr-defined]
            raise
        finally:
            pool.close()
    summary.seconds = time.perf_counter() - t0
    return summary


def _drive(ws, plan: Plan, options: RunOptions, pool, summary: RunSummary, emit, after_stage) -> None:
    """The scheduling loop: submit ready tasks while the pool has room, handle what comes back."""
    tasks = {t.key: t for t in plan.tasks}
    ids = {i: t.key for i, t in enumerate(plan.tasks)}
    by_key = {k: i for i, k in ids.items()}
    waiting = [t.key for t in plan.tasks]  # in plan order
    running: set[tuple[str, str]] = set()
    opts = dataclasses.asdict(options)
    started: dict[tuple[str, str], float] = {}

    def ready(key) -> bool:
        return all(summary.outcomes[k].state in ("ran", "done") for k in tasks[key].after)

    def skip_after(take: str, stage: str, why: str) -> None:
        """Skip every task that depends, directly or not, on ``(take, stage)``."""
        blocked = [(take, stage)]
        while blocked:
            b = blocked.pop()
            for k in list(waiting):
                if b in tasks[k].after:
                    waiting.remove(k)
                    summary.outcomes[k] = Outcome("skipped", why)
                    emit("end", k[0], k[1], summary.outcomes[k])
                    blocked.append(k)

    def failed(key, error: str, seconds: float) -> None:
        out = summary.outcomes[key]
        out.seconds = seconds
        if out.tries <= options.retries:
            emit("retry", key[0], key[1], error)
            waiting.insert(0, key)
            return
        out.state, out.error = "failed", error
        record_failure(ws, key[0], key[1], error)
        emit("end", key[0], key[1], out)
        skip_after(key[0], key[1], f"{key[1]} failed")

    while waiting or running:
        while pool.free() > 0:
            key = next((k for k in waiting if ready(k)), None)
            if key is None:
                break
            waiting.remove(key)
            running.add(key)
            summary.outcomes[key].tries += 1
            started[key] = time.perf_counter()
            task = {"id": by_key[key], "take": key[0], "stage": key[1], "options": opts}
            if pool.name == "ray":
                pool.submit(task, catalog_bytes(ws))
            else:
                pool.submit(task)
            emit("start", key[0], key[1], summary.outcomes[key].tries)
        if not running:  # nothing can start: what is left waits on tasks that will not run
            for k in waiting:
                summary.outcomes[k] = Outcome("skipped", "its dependencies did not run")
            break
        for kind, tid, info in pool.poll(0.2):
            key = ids[tid]
            if kind == "log":
                emit("log", key[0], key[1], info)
            elif kind == "lost":
                running.discard(key)
                failed(key, info, time.perf_counter() - started[key])
            elif kind == "result":
                running.discard(key)
                merge_rows(ws, info.get("rows") or [])
                for line in info.get("log") or []:
                    emit("log", key[0], key[1], line)
                if not info["ok"]:
                    failed(key, info["error"], info["seconds"])
                    continue
                out = summary.outcomes[key]
                out.state, out.error, out.seconds = "ran", None, info["seconds"]
                emit("end", key[0], key[1], out)
                try:
                    stop = after_stage(ws, key[0], key[1])
                except Exception as e:  # noqa: BLE001 - a check that breaks must not stop the other takes
                    from dualhuman_builder.batch.worker import describe_error

                    stop = f"after_stage failed: {describe_error(e)}"
                if stop:
                    skip_after(key[0], key[1], str(stop))

"""What runs one task (one stage of one take) in a worker: a local pool's worker process
(``python -m dualhuman_builder.batch.worker``), or a Ray task.

A local worker reads tasks as JSON lines on its standard input and answers on the standard output
it started with (``log`` lines while the stage runs, then its ``result``); anything else that
writes to the standard output (a library's banner) goes to its standard error instead. It writes
the catalog itself, through the stage runner, like the stage commands do.

A Ray task writes no catalog on the shared filesystem: it runs the stage in a **shadow
workspace**, a local folder holding a copy of the catalog (sent by the driver) and links to the
workspace's ``takes/`` and ``artifacts/``; the stage reads its inputs and publishes its files
there as the runner always does, and the task returns the catalog rows the run changed, which the
driver records (:func:`dualhuman_builder.batch.run.merge_rows`).
"""

from __future__ import annotations

import json
import os
import sqlite3
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

#: Columns of a ``stage_runs`` row a shadow run sends back (its ids are the shadow's own).
ROW_KEYS = ("stage", "params_hash", "params_json", "status", "artifacts_json", "started_at", "ended_at", "summary_json",
            "error", "pid", "host", "attempt", "publish_json", "reads_json", "stale_reason")  # fmt: skip


#: Task kinds other than a stage: ``kind`` -> "module:function(root, task, log)" answering as
#: :func:`run_task` does (imported when first used, so the worker stands below what it runs).
TASK_KINDS = {"synth-ground-truth": "dualhuman_builder.batch.synth:ground_truth_task"}


def describe_error(e: BaseException) -> str:
    """One line for the summary table: the toolkit's message and fix, or the exception's type and text."""
    from dualhuman_builder.errors import DualhumanError

    if isinstance(e, DualhumanError):
        where = f"{e.path}: " if e.path is not None else ""
        return where + e.message + (f" (fix: {e.fix})" if e.fix else "")
    return f"{type(e).__name__}: {e}"


def answer(work: Callable[[], tuple[bool, dict[str, Any]]]) -> dict[str, Any]:
    """A task's answer: ``work()`` returns ``(ran, extra)``; the answer is ``{"ok", "ran", "error",
    "trace", "seconds"}`` plus ``extra``, or, when it raises, ``ok`` False with the error (never raises:
    the driver records a failed task, retries it and goes on with the others)."""
    t0 = time.perf_counter()
    try:
        ran, extra = work()
    except Exception as e:  # noqa: BLE001 - see the docstring
        return {"ok": False, "ran": True, "error": describe_error(e), "trace": "".join(traceback.format_exception(e)[-6:]),
                "seconds": time.perf_counter() - t0}  # fmt: skip
    return {"ok": True, "ran": ran, "error": None, "trace": None, "seconds": time.perf_counter() - t0, **extra}


def run_task(root: str | Path, task: dict[str, Any], log: Callable[[str], None]) -> dict[str, Any]:
    """Run ``task`` (``take``, ``stage``, ``options``: a :class:`~dualhuman_builder.batch.plan.RunOptions`
    as a dict) in the workspace at ``root``; a task of ``kind`` ``synth-ground-truth`` makes one
    synthetic take's files instead (:func:`~dualhuman_builder.batch.synth.ground_truth_task`). Returns ``{"ok", "ran", "error", "trace", "seconds"}``;
    ``ran`` is False when the stage was up to date. Never raises for a failed stage."""
    from dualhuman_builder.batch.plan import RunOptions, stage_call
    from dualhuman_builder.workspace import Workspace

    if task.get("kind") in TASK_KINDS:  # not a stage: files only, no catalog
        import importlib

        module, name = TASK_KINDS[task["kind"]].split(":")
        return getattr(importlib.import_module(module), name)(root, task, log)
    opts = task["options"]
    options = RunOptions(**{**opts, "takes": tuple(opts["takes"]) if opts.get("takes") else None,
                            "stages": tuple(opts["stages"]) if opts.get("stages") else None})  # fmt: skip

    def stage() -> tuple[bool, dict]:
        call = stage_call(task["stage"], options)
        with Workspace.open(root) as ws:
            res = call(ws, task["take"], log)
        return res is not None and not res.skipped, {}

    return answer(stage)


def stage_rows(catalog: Path) -> dict[tuple[str, str | None, str], dict[str, Any]]:
    """Every ``stage_runs`` row of the catalog file, by ``(take, sequence or None, stage)``."""
    conn = sqlite3.connect(f"file:{catalog}?mode=ro", uri=True)
    conn.row_factory = sqlite3.Row
    try:
        rows = conn.execute("SELECT r.*, t.name AS take_name, s.name AS seq_name FROM stage_runs r "
                            "JOIN takes t ON t.id = r.take_id LEFT JOIN sequences s ON s.id = r.sequence_id").fetchall()  # fmt: skip
        return {(r["take_name"], r["seq_name"], r["stage"]): {k: r[k] for k in ROW_KEYS} for r in rows}
    finally:
        conn.close()


def run_in_shadow(root: str | Path, catalog: bytes, task: dict[str, Any]) -> dict[str, Any]:
    """Run ``task`` against the workspace at ``root`` (a path every node sees) without writing its
    catalog: in a local shadow workspace made of ``catalog`` (the driver's copy) and links to
    ``root/takes`` and ``root/artifacts``. Returns :func:`run_task`'s answer with ``rows``: the
    ``stage_runs`` rows the run changed, ``[take, sequence, row]`` each, for the driver to record."""
    from dualhuman_builder.workspace.catalog import CATALOG_NAME

    root = Path(root)
    with tempfile.TemporaryDirectory(prefix="dualhuman-shadow-") as d:
        shadow = Path(d)
        (shadow / CATALOG_NAME).write_bytes(catalog)
        for sub in ("takes", "artifacts"):
            os.symlink(root / sub, shadow / sub, target_is_directory=True)
        before = stage_rows(shadow / CATALOG_NAME)
        lines: list[str] = []
        out = run_task(shadow, task, lines.append)
        after = stage_rows(shadow / CATALOG_NAME)
    out["rows"] = [[k[0], k[1], row] for k, row in after.items() if before.get(k) != row]
    out["log"] = lines[-20:]
    return out


def _end_with_parent(parent: int | None) -> None:
    """Get SIGINT when the driver ``parent`` dies (Linux), so that a killed driver leaves no worker
    running a stage: the stage runner records the run interrupted, and the next run does it again."""
    if parent is None:
        return
    try:
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGINT))  # PR_SET_PDEATHSIG
        if os.getppid() != parent:  # it died before the request
            os.kill(os.getpid(), signal.SIGINT)
    except (OSError, AttributeError):  # no prctl here: the worker ends when its input does
        pass


def main() -> None:
    """The local worker's loop: ``python -m dualhuman_builder.batch.worker WORKSPACE [DRIVER_PID]``."""
    root, parent = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else None
    _end_with_parent(parent)
    answer = os.fdopen(os.dup(1), "w", buffering=1, encoding="utf-8")
    os.dup2(2, 1)  # whatever else prints goes to the standard error

    def send(msg: dict[str, Any]) -> None:
        answer.write(json.dumps(msg, default=str) + "\n")

    for line in sys.stdin:
        if not line.strip():
            continue
        task = json.loads(line)

        def log(text: str, _id=task["id"]) -> None:
            send({"event": "log", "id": _id, "line": str(text)[:500]})

        send({"event": "start", "id": task["id"], "pid": os.getpid()})
        send({"event": "result", "id": task["id"], **run_task(root, task, log)})


if __name__ == "__main__":
    main()

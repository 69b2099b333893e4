"""``dualhuman synth --path ground-truth`` on worker processes: the scenes and renders of many
takes made at once by the local executor's workers (:class:`~dualhuman_builder.batch.executors.LocalExecutor`),
each loading the body model once; this process computes the contacts and writes the export, as
:func:`dualhuman_builder.sim.synth.make_synthetic` does. Workers write only their take's files
(``WS/synth/scenes/``, ``WS/synth/renders/``), never the catalog.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

from dualhuman_builder.batch.executors import LocalExecutor, default_workers
from dualhuman_builder.batch.worker import answer
from dualhuman_builder.sim.scenes import MAX_DRAWS
from dualhuman_builder.sim.synth import SynthError, SynthResult, ground_truth_files

#: A worker task (:data:`dualhuman_builder.batch.worker.TASK_KINDS`) making one take's ground-truth files
#: (:func:`ground_truth_task`).
GROUND_TRUTH_TASK = "synth-ground-truth"


def make_synthetic(workspace: str | Path, options, *, jobs: int | None = None, path: str = "full",
                   **kwargs: Any) -> SynthResult:  # fmt: skip
    """:func:`dualhuman_builder.sim.synth.make_synthetic` (same arguments), with the ground-truth
    path's scenes and renders made by ``jobs`` worker processes (None: one per CPU within the
    available memory, :func:`~dualhuman_builder.batch.executors.default_workers`; 1: in this
    process). The full path makes its takes one by one whatever ``jobs`` is (its capture plays the
    devices in real time; ``dualhuman run`` runs the stages after it at once)."""
    from dualhuman_builder.sim.synth import make_synthetic as make

    if jobs is None:
        jobs = default_workers() if path == "ground-truth" else 1
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise SynthError(f"jobs {jobs!r} must be a whole number of worker processes, at least 1", fix="pass --jobs 1 or more")
    if path == "ground-truth" and jobs > 1:
        kwargs["files"] = partial(_in_workers, jobs)
    return make(workspace, options, path=path, **kwargs)


def ground_truth_task(root: str | Path, task: dict[str, Any], log: Callable[[str], None]) -> dict[str, Any]:
    """A worker's run of :func:`ground_truth_files` (``task``: ``t``, ``shapes``, ``render``), answered as
    :func:`~dualhuman_builder.batch.worker.run_task` answers (``ok``, ``error``, ``seconds``) plus its result."""
    return answer(lambda: (True, {"made": ground_truth_files(root, task["t"], task["shapes"], log=log,
                                                            render=task.get("render"),
                                                            max_draws=task.get("max_draws", MAX_DRAWS))}))


def _in_workers(jobs: int, ws, plan: dict, actors: dict, render: dict | None, log, max_draws: int = MAX_DRAWS):
    """Yield ``(t, made)`` for every planned take in plan order, ``made`` as :func:`ground_truth_files`
    returns it, made by ``jobs`` worker processes (:class:`~dualhuman_builder.batch.executors.LocalExecutor`,
    their standard error in ``WS/synth/workers.log``, their log lines to ``log``). A worker that dies or raises makes the take
    ``failed`` with the reason; the workers are stopped on leaving (also on Ctrl-C)."""
    takes = plan["takes"]
    (ws.root / "synth").mkdir(parents=True, exist_ok=True)
    ex = LocalExecutor(ws.root, jobs, ws.root / "synth" / "workers.log")
    answers: dict[int, dict] = {}
    nxt = 0
    try:
        for k, t in enumerate(takes):
            while k not in answers:
                while nxt < len(takes) and ex.free() > 0:
                    u = takes[nxt]
                    ex.submit({"id": nxt, "kind": GROUND_TRUTH_TASK, "t": u, "render": render, "max_draws": max_draws,
                               "shapes": [actors[a][1] for a in u["actors"]]})  # fmt: skip
                    nxt += 1
                for ev in ex.poll(1.0):
                    if ev[0] == "result":
                        a = ev[2]
                        answers[ev[1]] = a["made"] if a.get("ok") else \
                            {"take": takes[ev[1]]["take"], "failed": a.get("error") or "the worker failed"}
                    elif ev[0] == "lost":
                        answers[ev[1]] = {"take": takes[ev[1]]["take"], "failed": ev[2]}
                    elif ev[0] == "log":
                        log(f"{takes[ev[1]]['take']}: {ev[2]}")
            yield t, answers.pop(k)
    finally:
        ex.close()

"""Where a batch run's tasks execute: a pool of local worker processes, or a Ray cluster.

Both take a task (a dict: ``id``, ``take``, ``stage``, ``options``) with :meth:`submit` while
:meth:`free` says a slot is open, and hand back events from :meth:`poll`:
``("start", id, pid)``, ``("log", id, line)``, ``("result", id, answer)`` (the worker's answer,
:func:`~dualhuman_builder.batch.worker.run_task`) and ``("lost", id, why)`` (its process died).
"""

from __future__ import annotations

import json
import os
import selectors
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from dualhuman_builder.batch.plan import GPU_STAGES, STAGE_MEMORY
from dualhuman_builder.children import available_memory, child_env, cpu_count
from dualhuman_builder.errors import DualhumanError

#: Memory a local worker is sized for (bytes): the most any stage task needs (:data:`STAGE_MEMORY`).
WORKER_MEMORY = max(STAGE_MEMORY.values())
#: Native thread pools of a local worker: one each, as Ray gives its tasks (a worker is one task on one CPU;
#: OpenMP and BLAS pools sized to every core spin against each other across the workers;
#: ``benchmarks/bench_run.py`` compares the executors on the same takes). A variable the user set is kept.
WORKER_THREADS_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
#: Seconds a Ray address has to accept a connection before the run gives up.
RAY_CONNECT_TIMEOUT_S = 5.0


def default_workers() -> int:
    """The local pool's size: one worker per CPU, no more than the available memory holds at
    :data:`WORKER_MEMORY` each, at least one."""
    return max(1, min(cpu_count(), (available_memory() or 8 << 30) // WORKER_MEMORY))


class LocalExecutor:
    """Up to ``workers`` worker processes (``python -m dualhuman_builder.batch.worker ROOT``, fresh
    interpreters, see :mod:`dualhuman_builder.children`), each running one task at a time and kept
    for the next. A worker that dies (killed, out of memory) loses its task, reported as ``lost``;
    a new one is started for the next task. Workers' standard error goes to ``log_path``."""

    name = "local"

    def __init__(self, root: Path, workers: int, log_path: Path):
        self.root = Path(root)
        self.size = max(1, int(workers))
        self.log = open(log_path, "ab")  # noqa: SIM115 - the workers write to it until close()
        self.sel = selectors.DefaultSelector()
        self.idle: list[subprocess.Popen] = []
        self.busy: dict[int, tuple[subprocess.Popen, int]] = {}  # pid -> (process, task id)
        self.buffers: dict[int, bytes] = {}

    def free(self) -> int:
        return self.size - len(self.busy)

    def pids(self) -> list[int]:
        """Process ids of the workers (for tests and the benchmark's memory figures)."""
        return [p.pid for p in self.idle] + [p.pid for p, _ in self.busy.values()]

    def _start(self) -> subprocess.Popen:
        proc = subprocess.Popen([sys.executable, "-m", "dualhuman_builder.batch.worker", str(self.root),
                                 str(os.getpid())],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=self.log,
                                env=child_env({k: v for k, v in WORKER_THREADS_ENV.items() if k not in os.environ}),
                                start_new_session=True)  # fmt: skip
        os.set_blocking(proc.stdout.fileno(), False)
        self.sel.register(proc.stdout, selectors.EVENT_READ, proc)
        self.buffers[proc.pid] = b""
        return proc

    def submit(self, task: dict[str, Any]) -> None:
        proc = self.idle.pop() if self.idle else self._start()
        self.busy[proc.pid] = (proc, task["id"])
        try:
            proc.stdin.write((json.dumps(task) + "\n").encode())
            proc.stdin.flush()
        except OSError:  # it died while idle: its death is seen by poll
            pass

    def poll(self, timeout: float) -> list[tuple]:
        events: list[tuple] = []
        for key, _ in self.sel.select(timeout):
            proc: subprocess.Popen = key.data
            try:
                chunk = os.read(proc.stdout.fileno(), 1 << 16)
            except BlockingIOError:
                continue
            if not chunk:
                events += self._ended(proc)
                continue
            data = self.buffers[proc.pid] + chunk
            *lines, self.buffers[proc.pid] = data.split(b"\n")
            for line in lines:
                msg = json.loads(line)
                kind = msg.pop("event")
                if kind == "log":
                    events.append(("log", msg["id"], msg["line"]))
                elif kind == "start":
                    events.append(("start", msg["id"], msg["pid"]))
                else:
                    self.busy.pop(proc.pid, None)
                    self.idle.append(proc)
                    events.append(("result", msg.pop("id"), msg))
        return events

    def _ended(self, proc: subprocess.Popen) -> list[tuple]:
        self.sel.unregister(proc.stdout)
        proc.stdout.close()
        code = proc.wait()
        if proc in self.idle:
            self.idle.remove(proc)
        held = self.busy.pop(proc.pid, None)
        if held is None:
            return []
        why = f"killed by signal {-code}" if code < 0 else f"exited with status {code}"
        return [("lost", held[1], f"its worker process (pid {proc.pid}) {why} while it ran")]

    def close(self) -> None:
        """Stop every worker: end of input for the idle ones, SIGINT for the busy ones (the stage
        runner then records the run interrupted and removes its staging folder), SIGKILL for one
        still running after 10 s."""
        procs = self.idle + [p for p, _ in self.busy.values()]
        for p in procs:
            try:
                p.stdin.close()
            except OSError:
                pass
        for p, _ in self.busy.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 10.0
        for p in procs:
            try:
                p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        self.sel.close()
        self.log.close()
        self.idle, self.busy = [], {}


def _probe(address: str) -> None:
    """A :class:`DualhumanError` unless ``address`` (``HOST:PORT`` or ``ray://HOST:PORT``) accepts
    a TCP connection within :data:`RAY_CONNECT_TIMEOUT_S`."""
    parsed = urlparse(address if "://" in address else f"tcp://{address}")
    host, port = parsed.hostname, parsed.port
    if not host or not port:
        raise DualhumanError(f"Ray address {address!r} is not HOST:PORT",
                             fix="pass the head node's address, e.g. --address 10.0.0.5:6379, or 'auto' on a node of "
                                 "the cluster")  # fmt: skip
    try:
        with socket.create_connection((host, port), timeout=RAY_CONNECT_TIMEOUT_S):
            pass
    except OSError as e:
        raise DualhumanError(f"no Ray cluster answers at {address} ({e.strerror or e})",
                             fix="start one with `ray start --head` on the head node and pass its address (printed by "
                                 "`ray start`), or leave out --address to run a Ray cluster on this machine") from None  # fmt: skip


class RayExecutor:
    """Tasks as Ray tasks on the cluster at ``address`` (None: the one already initialised in this
    process, else a new one on this machine; ``auto``: the cluster this node belongs to). Each task
    asks for one CPU, its stage's memory (:data:`STAGE_MEMORY`, capped at the largest node's) and,
    for :data:`GPU_STAGES` on a cluster with GPUs, one GPU. Ray re-runs a task whose worker or
    node died (``retries`` times); the stage then starts afresh, since nothing of the lost run was
    recorded. The workspace must be at the same path on every node."""

    name = "ray"

    def __init__(self, root: Path, address: str | None, retries: int, slots: int | None = None):
        try:
            import ray
        except ImportError:
            raise DualhumanError("the Ray executor needs Ray, which is not installed",
                                 fix="pip install 'dualhuman-builder[ray]'") from None  # fmt: skip
        self.ray = ray
        self.root = Path(root).resolve()
        self.owned = False
        if address not in (None, "auto", "local"):
            _probe(address)
        if not ray.is_initialized():
            kw: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False, "configure_logging": False}
            try:
                ray.init(address=None if address == "local" else address, **kw)
            except Exception as e:  # noqa: BLE001 - Ray raises ConnectionError, RuntimeError, TimeoutError...
                raise DualhumanError(f"cannot connect to the Ray cluster at {address or 'this machine'}: {e}",
                                     fix="check the address with `ray status --address ADDR` on the head node") from None  # fmt: skip
            self.owned = True
        resources = ray.cluster_resources()
        self.gpus = resources.get("GPU", 0) > 0
        node_memory = [n["Resources"].get("memory", 0) for n in ray.nodes() if n.get("Alive")]
        self.max_memory = int(max(node_memory)) if node_memory else None
        self.size = slots or max(1, int(resources.get("CPU", 1)))
        self.retries = retries
        self.refs: dict[Any, int] = {}
        self.started: set[int] = set()
        from dualhuman_builder.batch.worker import run_in_shadow

        self.remote = ray.remote(run_in_shadow)

    def free(self) -> int:
        return self.size - len(self.refs)

    def resources(self, stage: str) -> dict[str, Any]:
        """Ray options of a ``stage`` task."""
        memory = STAGE_MEMORY[stage] if self.max_memory is None else min(STAGE_MEMORY[stage], self.max_memory // 2)
        return {"num_cpus": 1, "memory": int(memory), "num_gpus": 1 if self.gpus and stage in GPU_STAGES else 0,
                "max_retries": self.retries, "retry_exceptions": False}  # fmt: skip

    def submit(self, task: dict[str, Any], catalog: bytes) -> None:
        ref = self.remote.options(**self.resources(task["stage"])).remote(str(self.root), catalog, task)
        self.refs[ref] = task["id"]

    def poll(self, timeout: float) -> list[tuple]:
        if not self.refs:
            time.sleep(timeout)
            return []
        # back as soon as one task ends (a slot is free), with every other one ended by then
        refs = list(self.refs)
        done, rest = self.ray.wait(refs, num_returns=1, timeout=timeout)
        if done and rest:
            done += self.ray.wait(rest, num_returns=len(rest), timeout=0)[0]
        events: list[tuple] = []
        for ref in done:
            tid = self.refs.pop(ref)
            try:
                events.append(("result", tid, self.ray.get(ref)))
            except Exception as e:  # noqa: BLE001 - the worker or its node died more often than retries allow
                events.append(("lost", tid, f"its Ray worker died while it ran: {type(e).__name__}: {str(e)[:300]}"))
        return events

    def close(self) -> None:
        for ref in list(self.refs):
            self.ray.cancel(ref, force=True)
        self.refs = {}
        if self.owned:
            self.ray.shutdown()

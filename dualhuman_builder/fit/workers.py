"""The fit's segments in worker processes (:func:`fit_in_workers`).

A fit is many small torch operations on one thread (``FitConfig.torch_threads``: 1, so that a fit
repeats exactly), so a second CPU helps only if a second process fits other frames.
:func:`~dualhuman_builder.fit.layout.layout` cuts the take into segments that do not depend on each
other; :func:`fit_in_workers` hands them out one at a time, as each process becomes free, to this
process and to ``workers - 1`` others, each started as ``python -m dualhuman_builder.fit.workers DIR``
(a fresh interpreter: no fork of a process holding torch's and warp's threads, and no re-import of the
caller's ``__main__``, so scripts without a ``__main__`` guard work;
docs/decisions/0018-segments-in-worker-processes.md). A worker takes a few seconds to start (torch,
anny's cached model, warp), while this process has already begun on the first segment.

Protocol: the job (the actors' inputs, fps, the config, the segments and the collision threads) travels
as a pickle in a temporary folder ``DIR``; a worker reads segment numbers on its stdin, one per line,
and answers on its stdout with lines ``ready``, ``msg <progress line>`` and ``done <segment> <peak kB>``
(the answer, a :class:`~dualhuman_builder.fit.layout.SegmentAnswer`, in ``DIR/part_<segment>.pkl``;
its peak resident memory so far); anything else it prints goes to its stderr, kept in
``DIR/stderr_<k>.txt``. A worker that dies leaves its segment to this process, which fits it itself
after saying why (the worker's exit status and the end of its stderr). The folder is removed
afterwards, also on failure.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import threading
from pathlib import Path
from typing import Callable

from dualhuman_builder.children import child_env, scratch_with_children

#: this process fits segments too (a test turns it off, so that the workers fit them all)
HERE_TOO = True


def fit_in_workers(fitter, inputs: list, fps: float, segments: list, n_windows: int, workers: int,
                   say: Callable[[str], None]) -> tuple[list, list, float]:  # fmt: skip
    """The :class:`~dualhuman_builder.fit.layout.SegmentAnswer` of every segment in ``segments`` (each a
    list of windows, :func:`~dualhuman_builder.fit.layout.layout`), fitted by this process's ``fitter``
    (a :class:`~dualhuman_builder.fit.segment.SegmentFitter` of ``inputs`` at ``fps``) and ``workers -
    1`` worker processes; the seams between consecutive ones (:func:`~dualhuman_builder.fit.seams.fit_seam`,
    each measured and where needed fitted again by this process as soon as both its segments are done,
    between its own segments); and the largest peak resident memory (MB, ``VmHWM``) a worker reported
    (0: none finished a segment). ``say`` gets the progress lines (from any of them, one at a time)."""
    with scratch_with_children("dualhuman-fit-") as (tmp, procs):
        run = _Dispatch(fitter, segments, n_windows, say, tmp, procs)
        run.start_workers(inputs, fps, workers)
        run.fit_here()
        run.finish()
        return run.parts, run.seams, run.peak_kb / 1024


class _Dispatch:
    """One fit's segments handed out, one at a time as each becomes free, to this process (``-1``) and
    the worker processes ``procs`` (``0 ..``), with the job in the folder ``tmp``; the seams mended by
    this process as their segments come in. ``parts[i]``: segment ``i``'s answer (None until done)."""

    def __init__(self, fitter, segments: list, n_windows: int, say: Callable[[str], None], tmp: Path, procs: list):
        self.fitter, self.segments, self.n_windows, self.say, self.tmp, self.procs = fitter, segments, n_windows, say, tmp, procs
        self.lock = threading.Lock()
        self.todo = list(range(len(segments)))
        self.parts: list = [None] * len(segments)
        self.busy: dict[int, int | None] = {}  # worker -> the segment it is fitting
        self.stopping = False
        self.peak_kb = 0
        self.seams: list = [None] * (len(segments) - 1)
        self.todo_seams = set(range(len(self.seams)))
        self.feeders: list[threading.Thread] = []
        self.killed: list[int] = []

    def tell(self, msg: str) -> None:
        """Pass a progress line on, one at a time."""
        with self.lock:
            self.say(msg)

    def take(self, k: int) -> int | None:
        """The next segment for worker ``k`` (-1: this process), None when none is left."""
        with self.lock:
            i = self.todo.pop(0) if self.todo and not self.stopping else None
            self.busy[k] = i
            return i

    def start_workers(self, inputs: list, fps: float, workers: int) -> None:
        """Write the job and start ``workers - 1`` worker processes, each with a thread that feeds it."""
        tmp = self.tmp
        with open(tmp / "job.pkl", "wb") as f:
            pickle.dump({"inputs": inputs, "fps": fps, "cfg": self.fitter.cfg, "segments": self.segments,
                         "n_windows": self.n_windows, "collision_threads": self.fitter.threads}, f)  # fmt: skip
        env = child_env()
        for k in range(workers - 1):
            with open(tmp / f"stderr_{k}.txt", "wb") as err:
                self.procs.append(subprocess.Popen([sys.executable, "-m", "dualhuman_builder.fit.workers", str(tmp)],
                                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err, env=env,
                                                   text=True))  # fmt: skip
        self.feeders = [threading.Thread(target=self._feed, args=(k, p), daemon=True) for k, p in enumerate(self.procs)]
        for t in self.feeders:
            t.start()

    def _feed(self, k: int, p: subprocess.Popen) -> None:
        """Hand worker ``k`` a segment whenever it says it is ready or done, until none is left."""
        for line in p.stdout:
            kind, _, rest = line.rstrip("\n").partition(" ")
            if kind == "msg":
                self.tell(rest)
                continue
            if kind == "done":
                i, kb = (int(x) for x in rest.split())
                self.peak_kb = max(self.peak_kb, kb)
                with open(self.tmp / f"part_{i}.pkl", "rb") as f:
                    self.parts[i] = pickle.load(f)
            if kind in ("ready", "done"):
                i = self.take(k)
                try:
                    if i is None:
                        p.stdin.close()  # the worker exits
                    else:
                        p.stdin.write(f"{i}\n")
                        p.stdin.flush()
                except OSError:  # it died meanwhile: the loop sees the end of its stdout
                    pass

    def mend_ready(self) -> None:
        """Mend the seams whose two segments are both done."""
        from dualhuman_builder.fit.seams import fit_seam

        parts = self.parts
        for j in sorted(self.todo_seams):
            if parts[j] is not None and parts[j + 1] is not None:
                self.todo_seams.discard(j)
                self.seams[j] = fit_seam(self.fitter, parts[j], parts[j + 1], self.tell)

    def fit_here(self) -> None:
        """This process fits segments too (unless :data:`HERE_TOO` is off), and mends the seams as their
        segments come in, until none is left to hand out."""
        while HERE_TOO:
            self.mend_ready()
            if (i := self.take(-1)) is None:
                break
            self.parts[i] = self.fitter.segment(self.segments[i], self.n_windows, self.tell)

    def finish(self) -> None:
        """Stop the idle workers, mend the seams as the busy ones finish, report the workers that failed
        and fit the segments they left in this process."""
        procs = self.procs
        with self.lock:
            self.stopping = HERE_TOO  # nothing left: a worker still starting up is not waited for
            idle = [k for k in range(len(procs)) if self.busy.get(k) is None] if HERE_TOO else []
        self.killed = [k for k in idle if procs[k].poll() is None]
        for k in self.killed:
            procs[k].kill()
        while any(t.is_alive() for t in self.feeders):  # the workers' last segments: mend the seams as they come
            self.mend_ready()
            for t in self.feeders:
                t.join(timeout=0.1)
        for k, p in enumerate(procs):
            if p.wait() != 0 and k not in self.killed:
                tail = (self.tmp / f"stderr_{k}.txt").read_text(errors="replace").strip()[-1500:]
                self.tell(f"WARNING: fit worker {k + 1} exited with status {p.returncode}:\n{tail}")
        lost = [i for i, part in enumerate(self.parts) if part is None]
        for i in lost:  # a worker died holding it: fit it here
            self.tell(f"fitting segment {i + 1} in this process (its worker failed)")
            self.parts[i] = self.fitter.segment(self.segments[i], self.n_windows, self.tell)
        self.mend_ready()


def _main(argv: list[str]) -> None:
    """A worker: ``argv[0]`` is the job's folder ``DIR``; fit the segments named on stdin (see the module
    docstring). The heavy imports come after stdout is redirected, so nothing they print reaches the
    protocol."""
    proto = os.fdopen(os.dup(1), "w", buffering=1)  # the protocol's lines; stray prints go to stderr
    os.dup2(2, 1)
    tmp = Path(argv[0])
    import torch

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.fit.segment import SegmentFitter

    with open(tmp / "job.pkl", "rb") as f:
        job = pickle.load(f)
    cfg = job["cfg"]
    if cfg.torch_threads > 0:
        torch.set_num_threads(int(cfg.torch_threads))
    fitter = SegmentFitter(get_body_model(cfg.device), job["inputs"], job["fps"], cfg, threads=job["collision_threads"])
    proto.write("ready\n")
    for line in sys.stdin:
        i = int(line)
        part = fitter.segment(job["segments"][i], job["n_windows"],
                              lambda m: proto.write("msg " + m.replace("\n", " ") + "\n"))  # fmt: skip
        with open(tmp / f"part_{i}.tmp", "wb") as f:
            pickle.dump(part, f)
        os.replace(tmp / f"part_{i}.tmp", tmp / f"part_{i}.pkl")
        proto.write(f"done {i} {_peak_kb()}\n")


def _peak_kb() -> int:
    """This process's peak resident memory (kB), ``VmHWM`` (unlike ``ru_maxrss``, not the parent's
    image this process was forked from before it started Python); 0 where there is no /proc."""
    try:
        with open("/proc/self/status") as f:
            return next((int(line.split()[1]) for line in f if line.startswith("VmHWM:")), 0)
    except OSError:
        return 0


if __name__ == "__main__":
    _main(sys.argv[1:])

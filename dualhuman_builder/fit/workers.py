"""The fit's segments in worker processes.

A fit spends most of its time in many small torch operations on one thread (``FitConfig.torch_threads``:
1, so that a fit repeats exactly), so a second CPU does nothing for it unless a second process fits
other frames. :func:`~dualhuman_builder.fit.fitter.layout` cuts the take into segments that do not
depend on each other; :func:`fit_in_workers` hands them out one at a time, as each process becomes
free, to this process and to ``workers - 1`` others, each started as ``python -m
dualhuman_builder.fit.workers DIR`` (a fresh interpreter: no fork of a process holding torch's and
warp's threads, and no re-import of the caller's ``__main__``, so scripts without a ``__main__``
guard work). A worker takes a few seconds to start (torch, anny's cached model, warp), while this
process has already begun on the first segment.

The job (the actors' inputs, fps, the config and the segments) travels as a pickle in a temporary
folder ``DIR``; a worker reads segment numbers on its stdin, one per line, and answers on its stdout
with lines ``ready``, ``msg <progress line>`` and ``done <segment> <peak kB>`` (the answer in
``DIR/part_<segment>.pkl``; its peak resident memory so far); anything else it prints goes to its stderr, kept in
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
    """The :class:`~dualhuman_builder.fit.fitter._Part` of every segment in ``segments``, fitted by
    this process's ``fitter`` and ``workers - 1`` worker processes; the seams between consecutive
    ones (:func:`~dualhuman_builder.fit.fitter._seam`, each measured and where needed fitted again by
    this process as soon as both its segments are done, between its own segments); and the largest
    peak resident memory (MB, ``VmHWM``) a worker reported (0: none finished a segment). ``say``
    gets the progress lines (from any of them, one at a time)."""
    from dualhuman_builder.fit.fitter import _seam

    cfg = fitter.cfg
    lock = threading.Lock()
    todo = list(range(len(segments)))
    parts: list = [None] * len(segments)
    busy: dict[int, int | None] = {}  # worker -> the segment it is fitting
    stopping = [False]
    peak_kb = [0]

    def tell(msg: str) -> None:
        with lock:
            say(msg)

    def take(k: int) -> int | None:
        """The next segment for worker ``k`` (-1: this process), None when none is left."""
        with lock:
            i = todo.pop(0) if todo and not stopping[0] else None
            busy[k] = i
            return i

    with scratch_with_children("dualhuman-fit-") as (tmp, procs):
        with open(tmp / "job.pkl", "wb") as f:
            pickle.dump({"inputs": inputs, "fps": fps, "cfg": cfg, "segments": segments, "n_windows": n_windows,
                         "collision_threads": fitter.threads}, f)  # fmt: skip
        env = child_env()
        for k in range(workers - 1):
            with open(tmp / f"stderr_{k}.txt", "wb") as err:
                procs.append(subprocess.Popen([sys.executable, "-m", "dualhuman_builder.fit.workers", str(tmp)],
                                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err, env=env,
                                              text=True))  # fmt: skip

        def feed(k: int, p: subprocess.Popen) -> None:
            """Hand worker ``k`` a segment whenever it says it is ready or done, until none is left."""
            for line in p.stdout:
                kind, _, rest = line.rstrip("\n").partition(" ")
                if kind == "msg":
                    tell(rest)
                    continue
                if kind == "done":
                    i, kb = (int(x) for x in rest.split())
                    peak_kb[0] = max(peak_kb[0], kb)
                    with open(tmp / f"part_{i}.pkl", "rb") as f:
                        parts[i] = pickle.load(f)
                if kind in ("ready", "done"):
                    i = take(k)
                    try:
                        if i is None:
                            p.stdin.close()  # the worker exits
                        else:
                            p.stdin.write(f"{i}\n")
                            p.stdin.flush()
                    except OSError:  # it died meanwhile: the loop below sees the end of its stdout
                        pass

        feeders = [threading.Thread(target=feed, args=(k, p), daemon=True) for k, p in enumerate(procs)]
        for t in feeders:
            t.start()
        seams: list = [None] * (len(segments) - 1)
        todo_seams = set(range(len(seams)))

        def mend_ready() -> None:
            """The seams whose two segments are both done."""
            for j in sorted(todo_seams):
                if parts[j] is not None and parts[j + 1] is not None:
                    todo_seams.discard(j)
                    seams[j] = _seam(fitter, parts[j], parts[j + 1], tell)

        while HERE_TOO:  # this process fits too, and mends the seams as their segments come in
            mend_ready()
            if (i := take(-1)) is None:
                break
            parts[i] = fitter.segment(segments[i], n_windows, tell)
        with lock:
            stopping[0] = HERE_TOO  # nothing left: a worker still starting up is not waited for
            idle = [k for k in range(len(procs)) if busy.get(k) is None] if HERE_TOO else []
        killed = [k for k in idle if procs[k].poll() is None]
        for k in killed:
            procs[k].kill()
        while any(t.is_alive() for t in feeders):  # the workers' last segments: mend the seams as they come
            mend_ready()
            for t in feeders:
                t.join(timeout=0.1)
        for k, p in enumerate(procs):
            if p.wait() != 0 and k not in killed:
                tail = (tmp / f"stderr_{k}.txt").read_text(errors="replace").strip()[-1500:]
                tell(f"WARNING: fit worker {k + 1} exited with status {p.returncode}:\n{tail}")
        lost = [i for i, part in enumerate(parts) if part is None]
        for i in lost:  # a worker died holding it: fit it here
            tell(f"fitting segment {i + 1} in this process (its worker failed)")
            parts[i] = fitter.segment(segments[i], n_windows, tell)
        mend_ready()
        return parts, seams, peak_kb[0] / 1024


def _main(argv: list[str]) -> None:
    proto = os.fdopen(os.dup(1), "w", buffering=1)  # the protocol's lines; stray prints go to stderr
    os.dup2(2, 1)
    tmp = Path(argv[0])
    import torch

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.fit.fitter import _Fitter

    with open(tmp / "job.pkl", "rb") as f:
        job = pickle.load(f)
    cfg = job["cfg"]
    if cfg.torch_threads > 0:
        torch.set_num_threads(int(cfg.torch_threads))
    fitter = _Fitter(get_body_model(cfg.device), job["inputs"], job["fps"], cfg, threads=job["collision_threads"])
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

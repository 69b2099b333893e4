"""Contacts of many frames in worker processes.

``igl.signed_distance`` holds the GIL for the whole call, so threads cannot share its work; long
sequences are therefore split over ``workers`` processes. Each process already keeps about two
CPUs busy (its narrow phase runs in helper threads outside the GIL), hence one worker per two CPUs
(``docs/decisions/0021-contacts-libigl-on-possible-contacts.md``).

Each worker is a fresh interpreter, ``python -m dualhuman_builder.contacts.workers``: no fork of a
process holding torch's and warp's threads, and no re-import of the caller's ``__main__`` (scripts
without a ``__main__`` guard work). Worker ``k`` of ``W`` takes frames ``k, k + W, ...``: contact
phases bunch up within a take, interleaving spreads them. It runs the kernel of
:mod:`~dualhuman_builder.contacts.frames` and imports numpy, scipy, libigl and warp but not torch;
its start-up still costs more than a few dozen frames, so short sequences stay in the calling
process (:data:`MIN_FRAMES_PER_WORKER`).

The vertices travel through ``.npy`` files in a temporary folder (memory-mapped by the workers, in
their own dtype), the topology as a pickle; each worker writes its frames' results to one ``.npz``
and prints one line per frame for progress. The folder is removed afterwards, also on failure. A
worker that fails raises :class:`RuntimeError` with its exit status and the end of its stderr.
"""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from dualhuman_builder.children import child_env, scratch_with_children
from dualhuman_builder.contacts.frames import COUNT_KEYS, compute_frames

#: Frames per worker below which a worker's start-up (a fresh interpreter importing libigl and
#: warp) costs more than it saves.
MIN_FRAMES_PER_WORKER = 48


def auto_workers(frames: int, cpus: int | None = None) -> int:
    """Processes for ``frames`` frames: one per two CPUs (each process runs its narrow phase in
    helper threads), at most 8, while each gets at least :data:`MIN_FRAMES_PER_WORKER` frames.
    ``cpus`` defaults to ``os.cpu_count()``. 1 means "in the calling process", which is always the
    answer on 2 CPUs (``docs/decisions/0021-contacts-libigl-on-possible-contacts.md``)."""
    cpus = cpus or os.cpu_count() or 1
    return max(1, min(cpus // 2, 8, frames // MIN_FRAMES_PER_WORKER))


def run_in_workers(topo, verts_a: np.ndarray, verts_b: np.ndarray, frames: np.ndarray, threshold: float, band: float,
                   workers: int, counts: dict, on_done: Callable[[], None] | None = None) -> Iterator[tuple[int, object]]:  # fmt: skip
    """Results of :func:`~dualhuman_builder.contacts.frames.compute_frames` for ``frames`` (indices
    into ``verts_a``/``verts_b`` ``(T, V, 3)`` m) computed by ``workers`` processes: yields ``(t,
    result)`` in frame order once all are done; adds the workers' query counts to ``counts``;
    ``on_done()`` is called (in this thread) as each frame finishes."""
    frames = np.asarray(frames, dtype=np.int64)
    with scratch_with_children("dualhuman-contacts-") as (tmp, procs):
        for name, v in (("verts_a", verts_a), ("verts_b", verts_b)):  # in their own dtype: same answers
            mm = np.lib.format.open_memmap(tmp / f"{name}.npy", mode="w+", dtype=v.dtype, shape=(len(frames),) + v.shape[1:])
            for i in range(0, len(frames), 256):  # in blocks: no second copy of a long take in memory
                mm[i:i + 256] = v[frames[i:i + 256]]
            mm.flush()
            del mm
        with open(tmp / "topology.pkl", "wb") as f:
            pickle.dump(topo, f)
        env = child_env()
        for k in range(workers):
            cmd = [sys.executable, "-m", "dualhuman_builder.contacts.workers", str(tmp), str(k), str(workers),
                   repr(float(threshold)), repr(float(band))]  # fmt: skip
            with open(tmp / f"stderr_{k}.txt", "wb") as err:
                procs.append(subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, env=env))
        lock, done = threading.Lock(), [0]

        def read(p):  # one line per frame done
            for _ in p.stdout:
                with lock:
                    done[0] += 1

        readers = [threading.Thread(target=read, args=(p,), daemon=True) for p in procs]
        for r in readers:
            r.start()
        reported = 0
        while True:
            alive = any(r.is_alive() for r in readers)
            with lock:
                n = done[0]
            for _ in range(n - reported):
                if on_done is not None:
                    on_done()
            reported = n
            if not alive:
                break
            time.sleep(0.1)
        for k, p in enumerate(procs):
            if p.wait() != 0:
                tail = (tmp / f"stderr_{k}.txt").read_text(errors="replace")[-2000:]
                raise RuntimeError(f"contacts worker {k + 1} of {workers} failed (exit status {p.returncode}):\n{tail}")
        out: list[tuple[int, object]] = []
        for k in range(workers):
            with np.load(tmp / f"out_{k}.npz") as z:  # each z[key] reads the array again: once each
                index, computed, labels, distances = z["index"], z["computed"], z["labels"], z["distances"]
                stats = json.loads(str(z["stats"]))
            for key, v in stats["counts"].items():
                counts[key] = counts.get(key, 0) + v
            for j, i in enumerate(index):
                if not computed[j]:
                    out.append((int(frames[i]), None))
                    continue
                frame_pairs = {(int(a), int(b)): (int(c), float(m)) for a, b, c, m in stats["pairs"][j]}
                out.append((int(frames[i]), (labels[j], distances[j], frame_pairs)))
        yield from sorted(out, key=lambda item: item[0])


def _main(argv: list[str]) -> None:
    """One worker: ``argv`` = ``[folder, k, workers, threshold_m, band_m]`` as :func:`run_in_workers`
    passes them; writes ``out_{k}.npz`` in the folder."""
    tmp, k, workers, threshold, band = Path(argv[0]), int(argv[1]), int(argv[2]), float(argv[3]), float(argv[4])
    with open(tmp / "topology.pkl", "rb") as f:
        topo = pickle.load(f)
    va = np.load(tmp / "verts_a.npy", mmap_mode="r")
    vb = np.load(tmp / "verts_b.npy", mmap_mode="r")
    index = np.arange(k, len(va), workers)
    V = topo.num_vertices
    labels = np.zeros((len(index), 2, V), dtype=bool)
    distances = np.full((len(index), 2, V), np.nan, dtype=np.float16)
    computed = np.zeros(len(index), dtype=bool)
    pairs: list[list] = [[] for _ in index]
    counts = dict.fromkeys(COUNT_KEYS, 0)
    for j, (_, result) in enumerate(compute_frames(topo, va, vb, index, threshold, band, counts)):
        if result is not None:
            labels[j], distances[j], frame_pairs = result
            computed[j] = True
            pairs[j] = [[a, b, c, m] for (a, b), (c, m) in frame_pairs.items()]
        sys.stdout.write("1\n")
        sys.stdout.flush()
    stats = json.dumps({"counts": counts, "pairs": pairs})
    np.savez(tmp / f"out_{k}.npz", index=index, labels=labels, distances=distances, computed=computed,
             stats=np.array(stats))  # fmt: skip


if __name__ == "__main__":
    _main(sys.argv[1:])

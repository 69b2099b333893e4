"""Warp CPU launches split over threads, and numpy arrays viewed as warp arrays without a copy.

warp runs CPU kernels through ctypes, which releases the GIL, so a launch split into contiguous
chunks runs in parallel on Python threads. Splitting changes which thread computes an item, never
what it computes: every kernel here writes each item's result from that item's inputs alone (or,
for kernels whose items are whole problems, a thread owns each problem).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

#: keys of the kernels launched at least once in this process (their module is loaded)
_loaded: set = set()


def cpu_view(x: np.ndarray, dtype=None) -> wp.array:
    """``x`` (C-contiguous) as a warp CPU array over the same memory, so a kernel may write into it
    (warp keeps ``x`` alive); ``dtype`` a warp type (``wp.vec3`` over a trailing axis of 3), by
    default ``x``'s own (float32, int32 or int8)."""
    dtype = dtype or {np.float32: wp.float32, np.int32: wp.int32, np.int8: wp.int8}[x.dtype.type]
    return wp.array(x, dtype=dtype, device="cpu", copy=False)


class CpuThreads:
    """Up to ``threads`` threads (the calling one included) for ctypes calls into warp.

    One instance per :class:`~dualhuman_builder.geometry.collision.CollisionTerm`; its helper
    threads start on the first split call. Not re-entrant: the term's lock serialises its users.
    """

    def __init__(self, threads: int):
        self.threads = int(threads)
        self._executor: ThreadPoolExecutor | None = None

    def run(self, fn, items: np.ndarray, min_chunk: int) -> None:
        """``fn(chunk)`` over contiguous chunks of ``items``, at least ``min_chunk`` each, the first
        chunk in this thread while the others run."""
        n_chunks = max(1, min(self.threads, len(items) // max(min_chunk, 1)))
        chunks = [c for c in np.array_split(items, n_chunks) if len(c)]
        if len(chunks) <= 1:
            if len(items):
                fn(items)
            return
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=self.threads - 1)
        futures = [self._executor.submit(fn, c) for c in chunks[1:]]
        fn(chunks[0])
        for fut in futures:
            fut.result()

    def launch(self, kernel, n: int, min_chunk: int, launch) -> None:
        """``launch(start, count)`` -- one warp CPU launch of ``kernel`` over items ``start .. start +
        count - 1`` -- over ``n`` items in threads (:meth:`run`), then wait for the device. warp loads
        a kernel's module on its first launch, which two threads must not do at once: the first
        launch in the process is one item, alone (its result is written again by the split launches)."""
        if n == 0:
            return
        if kernel.key not in _loaded:
            launch(0, 1)
            _loaded.add(kernel.key)
        self.run(lambda items: launch(int(items[0]), len(items)), np.arange(n), min_chunk)
        wp.synchronize_device("cpu")

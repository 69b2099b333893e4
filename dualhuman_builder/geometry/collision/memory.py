"""Signs remembered across calls: which query vertices provably kept their inside/outside sign.

An optimiser evaluates the collision term many times on bodies that barely move. A caller that names
its frames (``keys``) lets each (frame, direction) keep the last call's sign and a lower bound ``lb``
of ``|distance|`` per query vertex, with the bodies they were computed on. The signed distance is
1-Lipschitz in the query point, and a surface whose vertices each move by at most ``D`` stays within
``D`` of where it was, so after a move the sign of a vertex still holds where
``lb - |dq| - max|do| > 0`` (``dq`` its own move, ``do`` the obstacle's vertex moves): vertices
outside there need no query, vertices inside only their depth.

The bound is taken per part of the obstacle (``parts``, e.g. each hand's fingers and the rest): each
part's faces lie, all along the move, within the part's largest vertex move ``m_g`` of where they
were and within the box ``box_g`` of its face corners old and new. A vertex keeps its sign where
``min_g max(lb - |dq| - m_g, dist(q, box_g) - |dq|) > 0``; so a move of the fingers alone leaves the
signs far from them standing. The whole-surface bound is checked first, the parts only where it fails.

Where the pseudonormal sign is exact (a closed surface that does not cross itself) the answers equal
those of a call without keys. Where a posed body crosses itself, a vertex keeps the sign it had
before the crossing rather than a fresh, ill-defined one. Why and what it saves:
``docs/decisions/0020-collision-term-cost.md``; ``benchmarks/bench_fit.py`` measures the fit with it.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from dualhuman_builder.geometry.collision.cpu_launch import CpuThreads, cpu_view
from dualhuman_builder.geometry.collision.kernels import kept_signs, part_moves, vertex_moves
from dualhuman_builder.geometry.collision.surface import ObstacleSurface

#: remembered problems per thread below which splitting :func:`~.kernels.kept_signs` does not pay
KEPT_PER_THREAD = 8


class SignMemory:
    """Per frame key: a's and b's vertices ``(V, 3)``, signs ``(2, V)`` int8 and bounds ``(2, V)``
    float32 (row = side: 0 b's vertices against a, 1 a's against b), the last ``max_memo`` keys.

    ``surface``: the obstacle; ``parts``: optional ``(V,)`` ints, the obstacle's parts
    (:meth:`~.surface.ObstacleSurface.part_corners`); ``seed_stride``: a power of 2, how a call's
    unseen frames start from their neighbours' signs (:meth:`levels`; 1: each alone).
    Stale entries are only less useful, never wrong.
    """

    def __init__(self, surface: ObstacleSurface, parts, max_memo: int, seed_stride: int, threads: CpuThreads):
        vert, part, self.num_parts = surface.part_corners(parts)
        self._part_pairs = (vert, part)
        self._parts_wp: tuple | None = None  # the same as warp arrays (made on first use)
        self.max_memo = int(max_memo)
        if int(seed_stride) < 1 or int(seed_stride) & (int(seed_stride) - 1):
            raise ValueError(f"seed_stride must be a power of 2 (1: off), got {seed_stride!r}")
        self.seed_stride = int(seed_stride)
        self.threads = threads
        self._entries: dict = {}

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        self._entries.clear()

    def _knows(self, key, V: int) -> bool:
        return key in self._entries and self._entries[key][0].shape == (V, 3)

    def levels(self, fkeys: list, V: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """The rows of a call's frames ``fkeys`` (bodies of ``V`` vertices) in the order their signs
        are found, as ``(rows, src)`` pairs of ``(n,)`` int arrays: ``src`` the rows whose remembered
        signs each starts from (its own, or for a frame never seen, a neighbour's found just before).

        An unseen frame needs a query for every vertex near the other body's box, though its
        neighbour in the call holds nearly the same bodies. With ``seed_stride`` ``s`` the unseen
        frames at rows ``0, s, 2s ...`` are found first, with the seen ones; then those at ``s/2,
        3s/2 ...`` from the row ``s/2`` before each, and so on down to the odd rows from the row
        before. The bound of :meth:`prior` holds between any two bodies, so the answer does not
        depend on the order (the neighbour's move decides only how many signs it keeps)."""
        K = len(fkeys)
        rows = np.arange(K)
        seen = np.array([self._knows(key, V) for key in fkeys], bool)
        s = self.seed_stride
        if seen.all() or s <= 1 or K - seen.sum() < 2:
            return [(rows, rows)]
        # level of an unseen row: 0 at multiples of s, then one more for each halving of the step
        step = np.where(rows % s == 0, s, rows & -rows)
        levels = [(rows[seen | (step == s)], rows[seen | (step == s)])]
        h = s // 2
        while h >= 1:
            r = rows[~seen & (step == h)]
            if len(r):
                levels.append((r, r - h))
            h //= 2
        return levels

    def prior(self, fkeys: list, A: np.ndarray, Bv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signs ``(P, V)`` int8 (0: unknown) and their lower bounds ``(P, V)`` float32 (metres),
        problem ``p = 2k + side``, that still hold after the move from the remembered bodies of frame
        ``fkeys[k]`` to ``A[k]``, ``Bv[k]`` ``(V, 3)`` float32 (C-contiguous). Keys not remembered
        give unknown signs. Three warp kernels: :func:`~.kernels.vertex_moves`,
        :func:`~.kernels.part_moves` and :func:`~.kernels.kept_signs`."""
        K, V = A.shape[:2]
        sgn = np.zeros((2 * K, V), np.int8)
        lb = np.zeros((2 * K, V), np.float32)
        have = [k for k, key in enumerate(fkeys) if self._knows(key, V)]
        if not have:
            return sgn, lb
        n = len(have)
        entries = [self._entries[fkeys[k]] for k in have]
        rows = np.ravel([[2 * k, 2 * k + 1] for k in have]).astype(np.int32)
        a0, b0 = (np.stack([e[i] for e in entries]) for i in (0, 1))
        s0 = np.concatenate([e[2] for e in entries])  # (2n, V), rows as in `rows`
        l0 = np.concatenate([e[3] for e in entries])
        A_now = A if n == len(A) else np.ascontiguousarray(A[have])
        B_now = Bv if n == len(Bv) else np.ascontiguousarray(Bv[have])
        da, db, most, lo, hi = self._moves(A_now, a0, B_now, b0)
        whole = np.ascontiguousarray(most.max(axis=2))
        arrs = [cpu_view(A_now, wp.vec3), cpu_view(B_now, wp.vec3), cpu_view(da), cpu_view(db), cpu_view(most),
                cpu_view(lo, wp.vec3), cpu_view(hi, wp.vec3), cpu_view(whole), cpu_view(s0), cpu_view(l0),
                cpu_view(rows)]  # fmt: skip
        outs = [cpu_view(sgn), cpu_view(lb)]  # views: the kernel writes into sgn and lb
        self.threads.launch(kept_signs, 2 * n, KEPT_PER_THREAD, lambda s, k: wp.launch(
            kept_signs, dim=(k, V), inputs=[*arrs, s], outputs=outs, device="cpu"))  # fmt: skip
        return sgn, lb

    def _moves(self, A: np.ndarray, a0: np.ndarray, B: np.ndarray, b0: np.ndarray) -> tuple:
        """For ``n`` frames moved from ``a0``, ``b0`` to ``A``, ``B`` (each ``(n, V, 3)`` float32): each
        vertex's move ``da``, ``db`` ``(n, V)``, and per body and part the largest move ``most (n, 2,
        G)`` and the box ``lo``, ``hi`` ``(n, 2, G, 3)`` of its face corners old and new (metres)."""
        n, V = A.shape[:2]
        if self._parts_wp is None:
            self._parts_wp = tuple(wp.array(x, dtype=wp.int32, device="cpu") for x in self._part_pairs)
        vert, part = self._parts_wp
        G = self.num_parts
        da, db = np.empty((n, V), np.float32), np.empty((n, V), np.float32)
        most = np.zeros((n, 2, G), np.float32)
        lo, hi = np.full((n, 2, G, 3), np.inf, np.float32), np.full((n, 2, G, 3), -np.inf, np.float32)
        # views without a copy: the kernels write into da, db, most, lo and hi
        pos = [cpu_view(x, wp.vec3) for x in (A, a0, B, b0)]
        wp.launch(vertex_moves, dim=(n, V), device="cpu", inputs=pos, outputs=[cpu_view(da), cpu_view(db)])
        self.threads.launch(part_moves, n, 1, lambda s, k: wp.launch(
            part_moves, dim=(k, vert.shape[0]), device="cpu", inputs=[*pos, cpu_view(da), cpu_view(db), vert, part, s],
            outputs=[cpu_view(most), cpu_view(lo, wp.vec3), cpu_view(hi, wp.vec3)]))  # fmt: skip
        return da, db, most, lo, hi

    def remember(self, fkeys: list, A: np.ndarray, Bv: np.ndarray, sgn: np.ndarray, lb: np.ndarray) -> None:
        """Keep frame ``fkeys[k]``'s bodies ``A[k]``, ``Bv[k]``, signs ``sgn[2k:2k+2]`` and bounds
        ``lb[2k:2k+2]`` (copies), dropping the oldest keys beyond ``max_memo``."""
        for k, key in enumerate(fkeys):
            self._entries.pop(key, None)  # re-inserted last: the oldest go first
            self._entries[key] = (A[k].copy(), Bv[k].copy(), sgn[2 * k : 2 * k + 2].copy(), lb[2 * k : 2 * k + 2].copy())
        while len(self._entries) > self.max_memo:
            self._entries.pop(next(iter(self._entries)))

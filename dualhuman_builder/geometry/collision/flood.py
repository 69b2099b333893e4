"""The sign flood fill: inside/outside of far query vertices without a query each.

The distance to the obstacle is 1-Lipschitz, so an edge ``(u, w)`` of the query mesh shorter than
``lb_u + lb_w`` (lower bounds of its ends' distances to the obstacle) cannot cross the obstacle:
``u`` and ``w`` lie on the same side. Connected components of such edges therefore share one sign,
which any member whose sign is known gives to the others. Two warp kernels per call
(:func:`~.kernels.flood_union`, :func:`~.kernels.flood_signs`): a union-find forest per problem,
then its roots' signs, each thread owning whole problems.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from dualhuman_builder.geometry.collision.cpu_launch import CpuThreads, cpu_view
from dualhuman_builder.geometry.collision.kernels import flood_signs, flood_union

#: what :meth:`SignFlood.__call__` returns for a vertex: the component's members are known on both
#: sides (a sign went wrong where the obstacle crosses itself; the vertex needs a query of its own)
CONFLICT = 2
#: the first vertex of a component without a known member (its representative: query it)
REPRESENTATIVE = 3
#: codes ``<= -4`` name the representative ``r`` as ``-(4 + r)``: take its sign once it is known
FOLLOWS = -4


class SignFlood:
    """Sign flood fill over the undirected ``edges (E, 2)`` of the query mesh, on ``threads``."""

    def __init__(self, edges: np.ndarray, threads: CpuThreads):
        self.edges = edges
        self.threads = threads
        self._edges_wp: tuple | None = None  # the two columns as warp arrays, made on first use

    def __call__(self, points: np.ndarray, bound: np.ndarray, sgn: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """Fill the problems ``rows`` of ``points (P, V, 3)`` (metres), distance lower bounds ``bound
        (P, V)`` (metres) and signs ``sgn (P, V)`` (int8, C-contiguous; +1 outside, -1 inside, 0
        unknown; written in place): each vertex of unknown sign takes the sign its component's known
        members agree on. Returns, per row of ``rows`` and vertex, what the others need, ``(len(rows),
        V)`` int32: 0 (nothing), :data:`CONFLICT`, :data:`REPRESENTATIVE` or ``-(4 + r)``
        (:data:`FOLLOWS`)."""
        V = sgn.shape[1]
        if sgn.dtype != np.int8 or not sgn.flags.c_contiguous:
            raise ValueError("sgn must be a C-contiguous int8 array (it is written in place)")
        if self._edges_wp is None:
            self._edges_wp = tuple(wp.array(np.ascontiguousarray(self.edges[:, i], np.int32), dtype=wp.int32, device="cpu")
                                   for i in (0, 1))  # fmt: skip
        n = len(rows)  # (sgn is viewed, not copied: the kernels write the agreed signs into it)
        arrs = [cpu_view(np.ascontiguousarray(points, np.float32), wp.vec3), cpu_view(np.ascontiguousarray(bound, np.float32)),
                cpu_view(sgn), cpu_view(np.ascontiguousarray(rows, np.int32))]  # fmt: skip
        parent = wp.empty((n, V), dtype=wp.int32, device="cpu")
        flags = wp.empty((n, V), dtype=wp.int32, device="cpu")
        code = wp.empty((n, V), dtype=wp.int32, device="cpu")
        self.threads.launch(flood_union, n, 1, lambda s, k: wp.launch(
            flood_union, dim=k, inputs=[*arrs, *self._edges_wp, s, parent], device="cpu"))  # fmt: skip
        self.threads.launch(flood_signs, n, 1, lambda s, k: wp.launch(
            flood_signs, dim=k, inputs=[arrs[2], arrs[3], s, parent, flags, code], device="cpu"))  # fmt: skip
        return code.numpy()

"""Closest-point queries against the obstacle surface: a pool of warp BVH meshes, refit per call.

Each problem (one frame and direction; see :mod:`.kernels`) needs a BVH of its obstacle body. A
BVH build costs far more than a refit, so :class:`MeshPool` keeps one ``wp.Mesh`` per problem slot
between calls and refits it to each call's vertices. A refit keeps the tree its build made, and
which of two equally close faces a query returns depends on that tree; ``bvh_points`` (e.g. the
rest pose) makes every build start from the same points, so the answers depend only on each call's
bodies, not on which frames first built each slot.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from dualhuman_builder.geometry.collision.cpu_launch import CpuThreads
from dualhuman_builder.geometry.collision.kernels import closest_points
from dualhuman_builder.warp_runtime import init_warp

#: queries per thread below which splitting one launch across threads does not pay
MIN_CHUNK = 2048
#: BVH refits (or builds) per thread below which handing them to another thread does not pay
MESHES_PER_THREAD = 4


class MeshPool:
    """BVH meshes of ``obstacle_faces (F, 3)`` over per-problem points, queried with :meth:`query`.

    ``threads``: the term's :class:`~.cpu_launch.CpuThreads`; ``winding``: build the meshes for the
    generalised winding-number sign; ``bvh_points``: optional ``(V, 3)`` float32 points every mesh's
    BVH is built over before its first refit (used when ``V`` matches the call's bodies).
    """

    def __init__(self, obstacle_faces: np.ndarray, threads: CpuThreads, winding: bool,
                 bvh_points: np.ndarray | None = None):  # fmt: skip
        self.obstacle_faces = obstacle_faces
        self.threads = threads
        self.winding = bool(winding)
        self.bvh_points = bvh_points
        self._meshes: list[wp.Mesh] = []
        self._points: list[wp.array] = []

    def meshes(self, points: np.ndarray, only: np.ndarray | None = None) -> np.ndarray:
        """Mesh ids ``(M,)`` uint64 for the problems ``points (M, V, 3)`` float32 metres, the meshes
        of the rows ``only`` (default: all) refit to their points. Slots are made on demand, and all
        dropped when ``V`` changes."""
        init_warp()
        M, V = points.shape[:2]
        if self._meshes and self._points[0].shape[0] != V:
            self._meshes, self._points = [], []
        if M > len(self._meshes):
            self._build(points, len(self._meshes), M)
        todo = np.arange(M) if only is None else np.asarray(only)

        def refit(rows):
            for i in rows:
                self._points[i].assign(points[i])
                self._meshes[i].refit()  # a ctypes call: releases the GIL, so threads refit in parallel

        self.threads.run(refit, todo, MESHES_PER_THREAD)
        return np.array([self._meshes[i].id for i in range(M)], dtype=np.uint64)

    def _build(self, points: np.ndarray, n0: int, M: int) -> None:
        """New slots ``n0 .. M-1``, built at ``bvh_points`` (or at these rows' own points), in threads."""
        V = points.shape[1]
        idx = wp.array(self.obstacle_faces.astype(np.int32).ravel(), dtype=wp.int32, device="cpu")  # shared
        new: list = [None] * (M - n0)
        at = self.bvh_points if self.bvh_points is not None and len(self.bvh_points) == V else None

        def build(rows):
            for i in rows:
                pts = wp.array(points[i] if at is None else at, dtype=wp.vec3, device="cpu")
                new[i - n0] = (wp.Mesh(points=pts, indices=idx, support_winding_number=self.winding), pts)

        self.threads.run(build, np.arange(n0, M), MESHES_PER_THREAD)
        self._meshes += [m for m, _ in new]
        self._points += [p for _, p in new]

    def query(self, mesh_ids: np.ndarray, which: np.ndarray, points: np.ndarray, max_dist) -> tuple:
        """Closest points of ``points (N, 3)`` (metres) on meshes ``mesh_ids[which]`` within
        ``max_dist`` (scalar or ``(N,)``, metres).

        Returns ``sdist (N,)`` float32 (negative inside), ``face (N,)`` int32 (-1 where nothing lies
        within ``max_dist``) and ``bary (N, 3)`` float32, the closest point's barycentric weights.
        """
        N = len(points)
        if N == 0:
            return np.zeros(0, np.float32), np.zeros(0, np.int32), np.zeros((0, 3), np.float32)
        md = np.broadcast_to(np.asarray(max_dist, np.float32), (N,))
        winding = 1 if self.winding else 0
        arrs = [
            wp.array(mesh_ids, dtype=wp.uint64, device="cpu"),
            wp.array(which.astype(np.int32), dtype=wp.int32, device="cpu"),
            wp.array(np.ascontiguousarray(points, np.float32), dtype=wp.vec3, device="cpu"),
            wp.array(np.ascontiguousarray(md), dtype=wp.float32, device="cpu"),
        ]
        sd = wp.zeros(N, dtype=wp.float32, device="cpu")
        face = wp.zeros(N, dtype=wp.int32, device="cpu")
        bary = wp.zeros(N, dtype=wp.vec3, device="cpu")
        self.threads.launch(closest_points, N, MIN_CHUNK, lambda s, k: wp.launch(
            closest_points, dim=k, inputs=[*arrs, s, winding, sd, face, bary], device="cpu"))  # fmt: skip
        return sd.numpy().copy(), face.numpy().copy(), bary.numpy().copy()

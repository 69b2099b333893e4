"""Which vertices and faces a banded libigl query needs: chosen with warp BVHs refit per frame.

``igl.signed_distance`` rebuilds its AABB tree and its face, edge and vertex pseudonormals over the
whole mesh it is given on every call, and costs about 5 us per point that lies within the band.
:class:`NearSelector` keeps one warp BVH per body (built once at the topology's reference pose,
refit to each frame: under 1 ms) and, in one kernel, finds for every vertex ``p`` of the query body

* its unsigned distance ``d(p)`` to the other body in float32, and whether it lies within
  ``band + slack`` (the **near** vertices; only they go to libigl), and
* every face of the other body that may lie within ``d(p) + slack`` of ``p`` (a conservative
  test: the distance from ``p`` to the face's box and to its plane, both lower bounds of the
  distance to the face).

``slack`` (default 1e-5 m) is about a hundred times the float32 error of these distances (1.5e-7 m
at most on a hug's contact frame against libigl). Both bodies are moved by the surface's mean
before the float32 cast, so that error does not grow with the distance from the world origin (at
1 km a float32 coordinate alone rounds by 3e-5 m). So the selected faces hold libigl's closest face for
every near vertex and every face around its closest vertex or edge (each contains the closest
point, at distance ``d(p)``), which is all that the pseudonormal sign reads: libigl on this
sub-mesh returns what it returns on the whole mesh (``tests/test_contacts.py`` checks it to 1e-9 m
against a brute-force query). Vertices left out are farther than the band from the other surface.

Launches release the GIL (warp calls its kernels through ctypes), but running the selection of the
next frame in a second thread while libigl works gained nothing (measured on a hug): libigl holds the
GIL for each whole call, and the selection needs it between its ten or so calls into warp.
"""

from __future__ import annotations

import functools

import numpy as np

DEFAULT_SLACK_M = 1e-5


@functools.lru_cache(maxsize=1)
def _kernel():
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    wp.config.quiet = True
    wp.init()

    @wp.kernel
    def select(mesh: wp.uint64, verts: wp.array(dtype=wp.vec3), tri: wp.array(dtype=wp.vec3i),
               points: wp.array(dtype=wp.vec3), reach: float, slack: float,
               near: wp.array(dtype=wp.int32), flags: wp.array(dtype=wp.int32)):  # fmt: skip
        i = wp.tid()
        p = points[i]
        near[i] = 0
        q = wp.mesh_query_point_no_sign(mesh, p, reach)
        if q.result:
            d = wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v))
            if d <= reach:
                near[i] = 1
                r = d + slack
                box = wp.mesh_query_aabb(mesh, p - wp.vec3(r, r, r), p + wp.vec3(r, r, r))
                f = int(0)
                while wp.mesh_query_aabb_next(box, f):
                    t = tri[f]
                    a = verts[t[0]]
                    b = verts[t[1]]
                    c = verts[t[2]]
                    lo = wp.min(wp.min(a, b), c)
                    hi = wp.max(wp.max(a, b), c)
                    gap = wp.max(wp.max(lo - p, p - hi), wp.vec3(0.0, 0.0, 0.0))
                    lower = wp.length(gap)  # to the face's box
                    n = wp.cross(b - a, c - a)
                    # to its plane, unless the face is a sliver (its normal then carries rounding)
                    if wp.length(n) > 1.0e-3 * wp.length(b - a) * wp.length(c - a):
                        lower = wp.max(lower, wp.abs(wp.dot(p - a, wp.normalize(n))))
                    if lower <= r:
                        flags[f] = 1

    return wp, select


class NearSelector:
    """Warp BVHs of two bodies of one closed topology, refit per frame.

    ``faces (F, 3)`` int: the closed target mesh; ``reference_vertices (V, 3)`` metres: any pose
    of it (the BVHs are built there once and only refit afterwards). One selector serves one
    thread at a time.
    """

    def __init__(self, faces: np.ndarray, reference_vertices: np.ndarray, slack_m: float = DEFAULT_SLACK_M):
        wp, self._kernel = _kernel()
        self._wp = wp
        self.slack = float(slack_m)
        faces = np.ascontiguousarray(faces, dtype=np.int32)
        ref = np.ascontiguousarray(reference_vertices, dtype=np.float32)
        self._tri = wp.array(faces, dtype=wp.vec3i, device="cpu")
        self._points, self._meshes = [], []
        for _ in range(2):
            pts = wp.array(ref, dtype=wp.vec3, device="cpu")
            self._points.append(pts)
            self._meshes.append(wp.Mesh(points=pts, indices=wp.array(faces.ravel(), dtype=wp.int32, device="cpu")))
        self._flags = wp.zeros(len(faces), dtype=wp.int32, device="cpu")

    def select(self, target: int, points: np.ndarray, surface: np.ndarray, band: float) -> tuple[np.ndarray, np.ndarray]:
        """Refit BVH ``target`` (0 or 1) to ``surface (V, 3)`` and return ``(near, faces)``:
        indices into ``points (N, 3)`` of those that may lie within ``band`` of that surface
        (metres), and the faces (indices into ``faces``) libigl needs to answer them exactly.
        Points outside the surface's box grown by ``band`` are not looked at."""
        wp = self._wp
        origin = np.asarray(surface, dtype=np.float64).mean(axis=0)  # float32 near 0: see the module docstring
        Q = np.ascontiguousarray(surface - origin, dtype=np.float32)
        self._points[target].assign(Q)
        mesh = self._meshes[target]
        mesh.refit()
        P = np.ascontiguousarray(points - origin, dtype=np.float32)
        grow = float(band) + self.slack
        cand = np.flatnonzero(np.all((P >= Q.min(0) - grow) & (P <= Q.max(0) + grow), axis=1))
        if not len(cand):
            return cand, np.zeros(0, np.int64)
        near = wp.empty(len(cand), dtype=wp.int32, device="cpu")
        self._flags.zero_()
        wp.launch(self._kernel, dim=len(cand), device="cpu",
                  inputs=[mesh.id, self._points[target], self._tri, wp.array(P[cand], dtype=wp.vec3, device="cpu"),
                          float(band) + self.slack, self.slack, near, self._flags])  # fmt: skip
        return cand[near.numpy().astype(bool)], np.flatnonzero(self._flags.numpy())

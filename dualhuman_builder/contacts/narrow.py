"""Which vertices lie within the band, their closest faces, and the faces a banded libigl query
needs: warp BVHs refit per frame.

:class:`NearSelector` keeps one warp BVH per body (built once at the topology's reference pose,
refit to each frame: under 1 ms) and answers in two kernels:

* :meth:`~NearSelector.closest` — for every vertex ``p`` of the query body inside the other
  body's box grown by the band, its closest face of the other body and its unsigned distance
  ``d(p)`` in float32, when within ``band + slack`` (the **near** vertices);
* :meth:`~NearSelector.faces_for` — for chosen near vertices, every face of the other body that
  may lie within ``d(p) + slack`` of ``p`` (a conservative test: the distance from ``p`` to the
  face's box and to its plane, both lower bounds of the distance to the face). This walk over a
  box of half-size ``d(p)`` costs about 5 us for a vertex 4 cm away (profiled once) and is what
  the contact stage saves by sending only possible contacts to libigl.

``slack`` (default 1e-5 m) is about a hundred times the float32 error of these distances (1.5e-7 m
at most on a hug's contact frame against libigl). Both bodies are moved by the surface's mean
before the float32 cast, so that error does not grow with the distance from the world origin (at
1 km a float32 coordinate alone rounds by 3e-5 m). So the faces :meth:`~NearSelector.faces_for`
selects hold libigl's closest face for each of its vertices and every face around its closest
vertex or edge (each contains the closest point, at distance ``d(p)``), which is all that the
pseudonormal sign reads: libigl on this sub-mesh returns what it returns on the whole mesh
(``tests/test_contacts.py`` checks it to 1e-9 m against a brute-force query). Vertices left out
are farther than the band from the other surface.

Kernel launches release the GIL (warp calls them through ctypes), so :meth:`~NearSelector.closest_pair`
runs the two directions of a frame in two threads (on a hug's contact frame 42 -> 24 ms on 2
cores, timed once with a script outside the repo), and the contact stage runs the next frame's :meth:`~NearSelector.closest_pair` while
libigl and numpy finish the last frame (``contacts.compute._compute_frames``, on a second selector).
"""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor

import numpy as np

DEFAULT_SLACK_M = 1e-5


@functools.lru_cache(maxsize=1)
def _kernels():
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    wp.config.quiet = True
    wp.init()

    @wp.kernel
    def closest(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), reach: float, box_lo: wp.array(dtype=wp.vec3),
                box_hi: wp.array(dtype=wp.vec3), face: wp.array(dtype=wp.int32), dist: wp.array(dtype=float)):  # fmt: skip
        i = wp.tid()
        p = points[i]
        face[i] = -1
        grown = wp.vec3(reach, reach, reach)
        inside = int(0)
        for k in range(box_lo.shape[0]):  # the group boxes first: most points far from the surface stop here
            lo = box_lo[k] - grown
            hi = box_hi[k] + grown
            if p[0] >= lo[0] and p[1] >= lo[1] and p[2] >= lo[2] and p[0] <= hi[0] and p[1] <= hi[1] and p[2] <= hi[2]:
                inside = 1
                break
        if inside == 0:
            return
        q = wp.mesh_query_point_no_sign(mesh, p, reach)
        if q.result:
            d = wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v))
            if d <= reach:
                face[i] = q.face
                dist[i] = d

    @wp.kernel
    def gather(mesh: wp.uint64, verts: wp.array(dtype=wp.vec3), tri: wp.array(dtype=wp.vec3i),
               points: wp.array(dtype=wp.vec3), dist: wp.array(dtype=float), slack: float,
               flags: wp.array(dtype=wp.int32)):  # fmt: skip
        i = wp.tid()
        p = points[i]
        r = dist[i] + slack
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

    return wp, closest, gather


class NearSelector:
    """Warp BVHs of two bodies of one closed topology, refit per frame.

    ``faces (F, 3)`` int: the closed target mesh; ``reference_vertices (V, 3)`` metres: any pose
    of it (the BVHs are built there once and only refit afterwards); ``face_groups (F,)`` int
    (optional): a label per face, e.g. its body region; a point farther than the band from every
    group's box (of the vertices its faces use) costs no BVH query. Target 0 and 1 are the two
    bodies. One selector serves one calling thread at a time (it keeps one helper thread of its
    own for :meth:`closest_pair`).
    """

    def __init__(self, faces: np.ndarray, reference_vertices: np.ndarray, slack_m: float = DEFAULT_SLACK_M,
                 face_groups: np.ndarray | None = None):  # fmt: skip
        wp, self._closest_kernel, self._gather_kernel = _kernels()
        self._wp = wp
        self.slack = float(slack_m)
        faces = np.ascontiguousarray(faces, dtype=np.int32)
        # per group of faces, the vertices they use: the group boxes of closest()
        groups = np.zeros(len(faces), np.int64) if face_groups is None else np.asarray(face_groups, np.int64)
        members = [np.unique(faces[groups == g]) for g in np.unique(groups)]
        self._group_vertices = np.concatenate(members)
        self._group_starts = np.cumsum([0] + [len(m) for m in members[:-1]])
        ref = np.ascontiguousarray(reference_vertices, dtype=np.float32)
        self._tri = wp.array(faces, dtype=wp.vec3i, device="cpu")
        self._points, self._meshes = [], []
        for _ in range(2):
            pts = wp.array(ref, dtype=wp.vec3, device="cpu")
            self._points.append(pts)
            self._meshes.append(wp.Mesh(points=pts, indices=wp.array(faces.ravel(), dtype=wp.int32, device="cpu")))
        self._flags = [wp.zeros(len(faces), dtype=wp.int32, device="cpu") for _ in range(2)]
        self._near: list = [None, None]  # per target: the last closest()'s near points (float32, shifted), distances
        self._pool: ThreadPoolExecutor | None = None

    def closest(self, target: int, points: np.ndarray, surface: np.ndarray, band: float):
        """Refit BVH ``target`` (0 or 1) to ``surface (V, 3)`` and return ``(near, face, dist)``:
        indices into ``points (N, 3)`` of those within ``band + slack`` of that surface (metres),
        each one's closest face (int64, index into ``faces``) and unsigned distance (float32,
        metres, within ~1.5e-7 of the exact one). Points outside the surface's box grown by
        ``band`` are not looked at, nor, in the kernel, those outside every group's box (see
        the constructor) grown by ``band``."""
        wp = self._wp
        origin = np.asarray(surface, dtype=np.float64).mean(axis=0)  # float32 near 0: see the module docstring
        Q = np.ascontiguousarray(surface - origin, dtype=np.float32)
        self._points[target].assign(Q)
        mesh = self._meshes[target]
        mesh.refit()
        P = np.ascontiguousarray(points - origin, dtype=np.float32)
        grow = float(band) + self.slack
        # the boxes of the groups' vertices (numpy reduces (N, 3) along axis 0 ~20x slower than (3, N) along 1)
        QT = np.ascontiguousarray(Q.T)[:, self._group_vertices]
        lo = np.minimum.reduceat(QT, self._group_starts, axis=1).T.copy()
        hi = np.maximum.reduceat(QT, self._group_starts, axis=1).T.copy()
        PT = np.ascontiguousarray(P.T)
        cand = np.flatnonzero(np.all((PT >= lo.min(0)[:, None] - grow) & (PT <= hi.max(0)[:, None] + grow), axis=0))
        if not len(cand):
            self._near[target] = (np.zeros((0, 3), np.float32), np.zeros(0, np.float32))
            return cand, np.zeros(0, np.int64), np.zeros(0, np.float32)
        face = wp.empty(len(cand), dtype=wp.int32, device="cpu")
        dist = wp.empty(len(cand), dtype=float, device="cpu")
        wp.launch(self._closest_kernel, dim=len(cand), device="cpu",
                  inputs=[mesh.id, wp.array(P[cand], dtype=wp.vec3, device="cpu"), grow,
                          wp.array(lo, dtype=wp.vec3, device="cpu"), wp.array(hi, dtype=wp.vec3, device="cpu"),
                          face, dist])  # fmt: skip
        face, dist = face.numpy(), dist.numpy()
        ok = face >= 0
        self._near[target] = (P[cand[ok]], dist[ok])
        return cand[ok], face[ok].astype(np.int64), dist[ok]

    def closest_pair(self, A: np.ndarray, B: np.ndarray, band: float):
        """``(closest(1, A, B, band), closest(0, B, A, band))``: A's vertices against B's surface
        and B's against A's, the second in this thread while the first runs in the helper thread
        (sequentially on the first call, which loads the kernels)."""
        if self._pool is None:
            first = self.closest(1, A, B, band)
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="contacts-narrow")
            return first, self.closest(0, B, A, band)
        job = self._pool.submit(self.closest, 1, A, B, band)
        second = self.closest(0, B, A, band)
        return job.result(), second

    def faces_for(self, target: int, which: np.ndarray) -> np.ndarray:
        """The faces (indices into ``faces``) libigl needs to answer the near points ``which``
        (indices into the last :meth:`closest` of ``target``'s ``near``) exactly."""
        wp = self._wp
        P, dist = self._near[target]
        which = np.asarray(which, dtype=np.int64)
        if not len(which):
            return np.zeros(0, np.int64)
        flags = self._flags[target]
        flags.zero_()
        wp.launch(self._gather_kernel, dim=len(which), device="cpu",
                  inputs=[self._meshes[target].id, self._points[target], self._tri,
                          wp.array(P[which], dtype=wp.vec3, device="cpu"),
                          wp.array(dist[which], dtype=float, device="cpu"), self.slack, flags])  # fmt: skip
        return np.flatnonzero(flags.numpy())

    def select(self, target: int, points: np.ndarray, surface: np.ndarray, band: float) -> tuple[np.ndarray, np.ndarray]:
        """``(near, faces)``: :meth:`closest`'s near points and the faces libigl needs to answer
        all of them exactly."""
        near, _, _ = self.closest(target, points, surface, band)
        return near, self.faces_for(target, np.arange(len(near)))

"""The contacts stage's narrow phase: which vertices lie within the band of the other body, their
closest faces and signed distances, and the faces a banded libigl query needs. Warp BVHs refit per frame.

:class:`NearSelector` keeps one warp BVH per body (built once at the topology's reference pose,
refit to each frame) and answers one direction of a frame with :meth:`~NearSelector.query`, in two
kernels:

* **closest** — for every vertex ``p`` of the query body inside the other body's box grown by the
  band (and inside one of its face groups' boxes, e.g. body regions, grown by the band), its
  closest face of the other body and its unsigned distance ``d(p)`` in float32, when within
  ``band + slack`` (the **near** vertices). For a near vertex with ``d(p)`` above a given
  threshold (plus the slack) the same kernel also computes, in float64 on that face, libigl's
  pseudonormal signed distance (``pseudonormal_distance`` in :func:`_kernels`, the rule of
  :mod:`dualhuman_builder.geometry.pseudonormal`: closest point by Ericson's Voronoi regions,
  sign from the face, edge or angle-weighted vertex pseudonormal);
* **gather** — for the near vertices libigl has to answer (possible contacts: ``d(p)`` up to the
  threshold plus the slack; and those whose pseudonormal distance came out inside or undefined),
  every face of the other body that may lie within ``d(p) + slack`` of ``p`` (a conservative
  test: the distance from ``p`` to the face's box and to its plane, both lower bounds of the
  distance to the face). This walk visits a box of half-size ``d(p)``, so its cost grows with the
  distance: only possible contacts take it (``docs/decisions/0021-contacts-libigl-on-possible-contacts.md``).

``slack`` (default 1e-5 m) is far above the float32 rounding of these distances (about 1e-7 m for
bodies within a few metres of the origin). Both bodies are moved by the surface's mean before the
float32 cast, so that rounding does not grow with the distance from the world origin (at 1 km a
float32 coordinate alone rounds by 3e-5 m); the float64 signed distances use the unshifted
coordinates, as libigl does. So the faces the gather kernel selects hold libigl's closest face for
each of its vertices and every face around its closest vertex or edge (each contains the closest
point, at distance ``d(p)``), which is all that the pseudonormal sign reads: libigl on this
sub-mesh returns what it returns on the whole mesh (``tests/contacts/test_contacts.py`` checks it
to 1e-9 m against a brute-force query). Vertices left out are farther than the band from the other
surface.

Kernel launches release the GIL (warp calls them through ctypes), so :meth:`~NearSelector.query_pair`
runs the two directions of a frame in two threads, and the contacts stage runs the next frames'
:meth:`~NearSelector.query_pair` while libigl answers the current one
(:func:`dualhuman_builder.contacts.frames.compute_frames`, on other selectors). Everything of a
direction but libigl's call therefore runs in these helper threads, mostly outside the GIL.
Positions are metres in the world frame; ``benchmarks/bench_contacts.py`` measures the whole path.
"""

from __future__ import annotations

import functools
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

DEFAULT_SLACK_M = 1e-5


@functools.lru_cache(maxsize=1)
def _kernels():
    from dualhuman_builder.warp_runtime import init_warp

    wp = init_warp()

    @wp.func
    def face_normal(Q: wp.array(dtype=wp.vec3d), t: wp.vec3i):
        # as igl.per_face_normals: the unit normal of (b - a) x (c - a), zero for a degenerate face
        a = Q[t[0]]
        n = wp.cross(Q[t[1]] - a, Q[t[2]] - a)
        length = wp.length(n)
        if length > wp.float64(0.0):
            n = n / length
        return n

    @wp.func
    def pseudonormal_distance(p: wp.vec3d, f: int, Q: wp.array(dtype=wp.vec3d), tri: wp.array(dtype=wp.vec3i),
                              across: wp.array(dtype=wp.vec3i), ring_ptr: wp.array(dtype=wp.int32),
                              ring_face: wp.array(dtype=wp.int32), ring_corner: wp.array(dtype=wp.int32)):  # fmt: skip
        # pseudonormal.signed_distance_to_faces for one point: the same Voronoi regions in the same order
        zero = wp.float64(0.0)
        t = tri[f]
        a = Q[t[0]]
        b = Q[t[1]]
        c = Q[t[2]]
        ab = b - a
        ac = c - a
        d1 = wp.dot(ab, p - a)
        d2 = wp.dot(ac, p - a)
        d3 = wp.dot(ab, p - b)
        d4 = wp.dot(ac, p - b)
        d5 = wp.dot(ab, p - c)
        d6 = wp.dot(ac, p - c)
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        kind = int(0)  # 0 face, 1 edge (opposite corner `index`), 2 vertex (corner `index`)
        index = int(0)
        q = a
        if d1 <= zero and d2 <= zero:
            kind = 2
        elif d3 >= zero and d4 <= d3:
            kind = 2
            index = 1
            q = b
        elif vc <= zero and d1 >= zero and d3 <= zero:
            kind = 1
            index = 2
            q = a + (d1 / (d1 - d3)) * ab
        elif d6 >= zero and d5 <= d6:
            kind = 2
            index = 2
            q = c
        elif vb <= zero and d2 >= zero and d6 <= zero:
            kind = 1
            index = 1
            q = a + (d2 / (d2 - d6)) * ac
        elif va <= zero and d4 - d3 >= zero and d5 - d6 >= zero:
            kind = 1
            q = b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b)
        else:
            denom = va + vb + vc
            q = a + (vb / denom) * ab + (vc / denom) * ac
        n = face_normal(Q, t)
        ok = int(1)
        if kind == 1:  # the two faces' normals (igl.per_edge_normals, uniform)
            g = across[f][index]
            if g < 0:
                ok = 0  # not exactly two faces on the edge: libigl answers
            else:
                n = n + face_normal(Q, tri[g])
        if kind == 2:  # the faces around the vertex, weighted by their angles there (igl.per_vertex_normals, angle)
            n = wp.vec3d(zero, zero, zero)
            v = t[index]
            for s in range(ring_ptr[v], ring_ptr[v + 1]):
                tg = tri[ring_face[s]]
                k = ring_corner[s]
                at = Q[tg[k]]
                e1 = Q[tg[(k + 1) % 3]] - at
                e2 = Q[tg[(k + 2) % 3]] - at
                cosine = wp.dot(e1, e2) / wp.sqrt(wp.dot(e1, e1) * wp.dot(e2, e2))
                n = n + face_normal(Q, tg) * wp.acos(wp.clamp(cosine, wp.float64(-1.0), wp.float64(1.0)))
        qc = p - q
        side = wp.dot(qc, n)
        d = wp.sqrt(wp.dot(qc, qc))
        if side < zero:
            d = -d
        if ok == 0 or wp.isnan(side):
            d = wp.float64(wp.nan)
        return d

    @wp.kernel
    def closest(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), reach: float, box_lo: wp.array(dtype=wp.vec3),
                box_hi: wp.array(dtype=wp.vec3), face: wp.array(dtype=wp.int32), dist: wp.array(dtype=float),
                beyond: float, points64: wp.array(dtype=wp.vec3d), surface64: wp.array(dtype=wp.vec3d),
                tri: wp.array(dtype=wp.vec3i), across: wp.array(dtype=wp.vec3i), ring_ptr: wp.array(dtype=wp.int32),
                ring_face: wp.array(dtype=wp.int32), ring_corner: wp.array(dtype=wp.int32),
                sdist: wp.array(dtype=wp.float64)):  # fmt: skip
        i = wp.tid()
        p = points[i]
        face[i] = -1
        grown = wp.vec3(reach, reach, reach)
        inside = int(0)
        # box 0 holds all groups, then one box per group: most points far from the surface stop here
        for k in range(box_lo.shape[0]):
            lo = box_lo[k] - grown
            hi = box_hi[k] + grown
            if p[0] >= lo[0] and p[1] >= lo[1] and p[2] >= lo[2] and p[0] <= hi[0] and p[1] <= hi[1] and p[2] <= hi[2]:
                if k > 0:
                    inside = 1
                    break
            elif k == 0:
                break
        if inside == 0:
            return
        q = wp.mesh_query_point_no_sign(mesh, p, reach)
        if q.result:
            d = wp.length(p - wp.mesh_eval_position(mesh, q.face, q.u, q.v))
            if d <= reach:
                face[i] = q.face
                dist[i] = d
                sdist[i] = wp.float64(wp.nan)
                if d > beyond:
                    sdist[i] = pseudonormal_distance(points64[i], q.face, surface64, tri, across, ring_ptr,
                                                     ring_face, ring_corner)  # fmt: skip

    @wp.kernel
    def gather(mesh: wp.uint64, verts: wp.array(dtype=wp.vec3), tri: wp.array(dtype=wp.vec3i),
               points: wp.array(dtype=wp.vec3), which: wp.array(dtype=wp.int32), dist: wp.array(dtype=float),
               slack: float, flags: wp.array(dtype=wp.int32)):  # fmt: skip
        i = which[wp.tid()]
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


@dataclass(frozen=True, eq=False)
class Near:
    """One direction of a frame from :meth:`NearSelector.query`: the query points within the band
    of the other surface and what libigl still has to answer.

    ``idx (n,)`` int64: indices into the query points within ``band + slack`` (metres) of the
    surface; ``face (n,)`` int64: each one's closest face (index into ``faces``); ``dist (n,)``
    float32: its unsigned distance (rounded to float32; see the module docstring); ``signed (n,)`` float64:
    libigl's pseudonormal signed distance on that face (negative inside) where ``dist`` exceeds
    the threshold plus the slack, NaN elsewhere and where the face's edge has not exactly two
    faces; ``exact (m,)`` int64: positions into ``idx`` of the points libigl must answer (``dist``
    up to the threshold plus the slack, or ``signed`` not ``>= 0``); ``faces (k,)`` int64: the
    faces libigl needs to answer those exactly.
    """

    idx: np.ndarray
    face: np.ndarray
    dist: np.ndarray
    signed: np.ndarray
    exact: np.ndarray
    faces: np.ndarray


class NearSelector:
    """Warp BVHs of two bodies of one closed topology, refit per frame.

    ``faces (F, 3)`` int: the closed target mesh; ``reference_vertices (V, 3)`` metres: any pose
    of it (the BVHs are built there once and only refit afterwards); ``face_groups (F,)`` int
    (optional): a label per face, e.g. its body region; a point farther than the band from every
    group's box (of the vertices its faces use) costs no BVH query; ``adjacency``: the faces'
    :class:`~dualhuman_builder.geometry.pseudonormal.MeshAdjacency` (built here when not given).
    Target 0 and 1 are the two bodies. One selector serves one calling thread at a time (it keeps
    one helper thread of its own for :meth:`query_pair`).
    """

    def __init__(self, faces: np.ndarray, reference_vertices: np.ndarray, slack_m: float = DEFAULT_SLACK_M,
                 face_groups: np.ndarray | None = None, adjacency=None):  # fmt: skip
        from dualhuman_builder.geometry.pseudonormal import MeshAdjacency

        wp, self._closest_kernel, self._gather_kernel = _kernels()
        self._wp = wp
        self.slack = float(slack_m)
        faces = np.ascontiguousarray(faces, dtype=np.int32)
        ref = np.ascontiguousarray(reference_vertices, dtype=np.float32)
        V = len(ref)
        # per group of faces, the vertices they use: the group boxes of the closest kernel
        groups = np.zeros(len(faces), np.int64) if face_groups is None else np.asarray(face_groups, np.int64)
        members = [np.unique(faces[groups == g]) for g in np.unique(groups)]
        self._group_vertices = np.concatenate(members)
        self._group_starts = np.cumsum([0] + [len(m) for m in members[:-1]])
        adj = adjacency if adjacency is not None else MeshAdjacency.of(faces, V)
        as32 = functools.partial(wp.array, dtype=wp.int32, device="cpu")
        self._tri = wp.array(faces, dtype=wp.vec3i, device="cpu")
        self._across = wp.array(np.ascontiguousarray(adj.across, dtype=np.int32), dtype=wp.vec3i, device="cpu")
        self._ring = [as32(np.ascontiguousarray(a, dtype=np.int32))
                      for a in (adj.ring_ptr, adj.ring_face, adj.ring_corner)]  # fmt: skip
        self._points, self._meshes, self._surface64 = [], [], []
        for _ in range(2):
            pts = wp.array(ref, dtype=wp.vec3, device="cpu")
            self._points.append(pts)
            self._meshes.append(wp.Mesh(points=pts, indices=wp.array(faces.ravel(), dtype=wp.int32, device="cpu")))
            self._surface64.append(wp.zeros(V, dtype=wp.vec3d, device="cpu"))
        self._flags = [wp.zeros(len(faces), dtype=wp.int32, device="cpu") for _ in range(2)]
        self._buffers: list = [None, None]  # per target: the query points' arrays (reallocated when N changes)
        self._pool: ThreadPoolExecutor | None = None

    def _query_buffers(self, target: int, n: int) -> dict:
        """Target ``target``'s warp arrays for ``n`` query points (kept between calls, so a frame
        allocates nothing): points (float32, shifted; float64), closest face, distance, signed
        distance."""
        wp = self._wp
        buf = self._buffers[target]
        if buf is None or buf["face"].shape[0] != n:
            buf = self._buffers[target] = {
                "points": wp.empty(n, dtype=wp.vec3, device="cpu"),
                "points64": wp.empty(n, dtype=wp.vec3d, device="cpu"), "face": wp.empty(n, dtype=wp.int32, device="cpu"),
                "dist": wp.empty(n, dtype=float, device="cpu"), "signed": wp.empty(n, dtype=wp.float64, device="cpu")}  # fmt: skip
        return buf

    def query(self, target: int, points: np.ndarray, surface: np.ndarray, band: float,
              threshold: float | None = None) -> Near:  # fmt: skip
        """Refit BVH ``target`` (0 or 1) to ``surface (V, 3)`` (metres) and answer the query
        ``points (N, 3)`` against it: a :class:`Near`. ``threshold`` (metres): near points whose
        float32 distance exceeds it plus the slack get the float64 pseudonormal signed distance
        and leave libigl's path unless it comes out inside; None: every near point is left to
        libigl. Points outside the surface's box grown by ``band`` are not looked at, nor those
        outside every group's box (see the constructor) grown by ``band``."""
        wp = self._wp
        surface = np.ascontiguousarray(surface, dtype=np.float64)
        points = np.ascontiguousarray(points, dtype=np.float64)
        origin = surface[::64].mean(axis=0)  # float32 near 0 (module docstring); any point near the body will do
        Q = (surface - origin).astype(np.float32)
        self._points[target].assign(Q)
        mesh = self._meshes[target]
        mesh.refit()
        grow = float(band) + self.slack
        # box 0 holds all groups; then each group's (numpy reduces (N, 3) along axis 0 ~20x slower than (3, N) along 1)
        G = np.ascontiguousarray(Q.T)[:, self._group_vertices]
        lo = np.minimum.reduceat(G, self._group_starts, axis=1)
        hi = np.maximum.reduceat(G, self._group_starts, axis=1)
        lo = np.c_[lo.min(axis=1), lo].T.copy()
        hi = np.c_[hi.max(axis=1), hi].T.copy()
        buf = self._query_buffers(target, len(points))
        buf["points"].assign((points - origin).astype(np.float32))
        beyond = np.inf if threshold is None else float(threshold) + self.slack
        if threshold is not None:
            buf["points64"].assign(points)
            self._surface64[target].assign(surface)
        wp.launch(self._closest_kernel, dim=len(points), device="cpu",
                  inputs=[mesh.id, buf["points"], grow, wp.array(lo, dtype=wp.vec3, device="cpu"),
                          wp.array(hi, dtype=wp.vec3, device="cpu"), buf["face"], buf["dist"], beyond,
                          buf["points64"], self._surface64[target], self._tri, self._across, *self._ring,
                          buf["signed"]])  # fmt: skip
        face = buf["face"].numpy()
        idx = np.flatnonzero(face >= 0)
        dist = buf["dist"].numpy()[idx]
        signed = buf["signed"].numpy()[idx]
        exact = np.flatnonzero(~((dist > beyond) & (signed >= 0)))  # NaN compares False: libigl answers it
        return Near(idx, face[idx].astype(np.int64), dist, signed, exact, self._gather(target, buf, idx[exact]))

    def _gather(self, target: int, buf: dict, which: np.ndarray) -> np.ndarray:
        """The faces (indices into ``faces``) libigl needs to answer the query points ``which``
        (indices into the last query's points, all near) exactly."""
        wp = self._wp
        if not len(which):
            return np.zeros(0, np.int64)
        flags = self._flags[target]
        flags.zero_()
        wp.launch(self._gather_kernel, dim=len(which), device="cpu",
                  inputs=[self._meshes[target].id, self._points[target], self._tri, buf["points"],
                          wp.array(which.astype(np.int32), dtype=wp.int32, device="cpu"), buf["dist"], self.slack,
                          flags])  # fmt: skip
        return np.flatnonzero(flags.numpy())

    def query_pair(self, A: np.ndarray, B: np.ndarray, band: float, threshold: float | None = None):
        """``(query(1, A, B, ...), query(0, B, A, ...))``: A's vertices against B's surface and B's
        against A's, the second in this thread while the first runs in the helper thread
        (sequentially on the first call, which loads the kernels)."""
        if self._pool is None:
            first = self.query(1, A, B, band, threshold)
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="contacts-narrow")
            return first, self.query(0, B, A, band, threshold)
        job = self._pool.submit(self.query, 1, A, B, band, threshold)
        second = self.query(0, B, A, band, threshold)
        return job.result(), second

    def select(self, target: int, points: np.ndarray, surface: np.ndarray, band: float) -> tuple[np.ndarray, np.ndarray]:
        """``(near, faces)``: the query points within ``band`` (plus the slack) of ``surface`` and
        the faces libigl needs to answer all of them exactly."""
        near = self.query(target, points, surface, band)
        return near.idx, near.faces

"""Signed distance of points to a face already known to be their closest, with libigl's sign rule.

``igl.signed_distance`` (pseudonormal sign) answers a point in two steps: find the closest point
``c`` on the mesh, then take the sign of ``(p - c) . n`` with ``n`` the angle-weighted
pseudonormal of the feature ``c`` lies on (Bærentzen & Aanæs 2005): the face's normal inside a
face, the sum of the two faces' normals on an edge, the sum of the incident faces' normals weighted
by their angles at a vertex; ``>= 0`` is outside (+1). On a closed manifold mesh that sign is the
inside/outside test. When a BVH query has already named the closest face, only the second step is
left, and it is a handful of float64 array operations per point instead of libigl's per-call AABB
build and per-point tree walk:

* :func:`closest_point_on_triangles` — the closest point on each triangle and which feature it
  lies on (Ericson, *Real-Time Collision Detection*, 5.1.5: Voronoi regions of the vertices,
  edges and face, in float64);
* :func:`signed_distance_to_faces` — the signed distance (metres, negative inside), with the face
  normals libigl itself computes (``igl.per_face_normals``) and the edge and vertex pseudonormals
  built from them as ``igl.per_edge_normals`` (uniform) and ``igl.per_vertex_normals`` (angle)
  build theirs (only for the edges and vertices asked about; normalising does not change a sign).

:class:`MeshAdjacency` holds the index arrays this needs, built once per topology. The contact
stage computes the same rule inside its narrow-phase warp kernel
(:mod:`dualhuman_builder.geometry.narrow`, float64, for the vertices whose closest face it has just
found); this module is the readable reference it is tested against.
``tests/geometry/test_pseudonormal.py`` checks value and sign against ``igl.signed_distance`` of the
whole mesh on the closest faces libigl reports (a posed anny body, every feature kind), and
``tests/contacts/test_contacts.py`` the contacts built on it against the brute force.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FACE, EDGE, VERTEX = 0, 1, 2  # feature kinds


@dataclass(frozen=True, eq=False)
class MeshAdjacency:
    """Adjacency of a closed triangle mesh ``faces (F, 3)`` over ``num_vertices`` V.

    ``across (F, 3)`` int64: the face on the other side of the edge opposite corner ``x`` of face
    ``f`` (libigl's edge numbering), -1 where that edge does not have exactly two faces;
    ``ring_ptr (V + 1,)``, ``ring_face``, ``ring_corner``: per vertex, the faces around it and the
    vertex's corner in each (CSR: vertex ``v``'s are ``ring_ptr[v]:ring_ptr[v + 1]``).
    """

    across: np.ndarray
    ring_ptr: np.ndarray
    ring_face: np.ndarray
    ring_corner: np.ndarray

    @classmethod
    def of(cls, faces: np.ndarray, num_vertices: int) -> "MeshAdjacency":
        F = np.asarray(faces, dtype=np.int64)
        n, V = len(F), int(num_vertices)
        # half-edge (f, x): the edge from corner x+1 to corner x+2, i.e. opposite corner x
        a, b = F[:, [1, 2, 0]].T.ravel(), F[:, [2, 0, 1]].T.ravel()  # index x * F + f
        key = np.minimum(a, b) * V + np.maximum(a, b)
        order = np.argsort(key, kind="stable")
        k = key[order]
        start = np.flatnonzero(np.r_[True, k[1:] != k[:-1]])
        count = np.diff(np.r_[start, len(k)])
        pairs = start[count == 2]
        across = np.full(3 * n, -1, dtype=np.int64)
        h0, h1 = order[pairs], order[pairs + 1]
        across[h0], across[h1] = h1 % n, h0 % n
        corner_of = np.repeat(np.arange(3), n)
        face_of = np.tile(np.arange(n), 3)
        v = F.T.ravel()  # corner x of face f at x * F + f
        ring = np.argsort(v, kind="stable")
        ptr = np.zeros(V + 1, dtype=np.int64)
        np.cumsum(np.bincount(v, minlength=V), out=ptr[1:])
        return cls(across.reshape(3, n).T.copy(), ptr, face_of[ring], corner_of[ring])


def closest_point_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """For points ``p (N, 3)`` and triangles ``(a, b, c)`` (each ``(N, 3)``), float64: the closest
    point ``(N, 3)``, its feature kind ``(N,)`` (:data:`FACE`, :data:`EDGE`, :data:`VERTEX`) and
    index ``(N,)`` (the corner for a vertex, the corner opposite the edge for an edge, 0 for the
    face)."""
    ab, ac, ap = b - a, c - a, p - a
    bp, cp = p - b, p - c
    dot = np.einsum
    d1, d2 = dot("ij,ij->i", ab, ap), dot("ij,ij->i", ac, ap)
    d3, d4 = dot("ij,ij->i", ab, bp), dot("ij,ij->i", ac, bp)
    d5, d6 = dot("ij,ij->i", ab, cp), dot("ij,ij->i", ac, cp)
    vc, vb, va = d1 * d4 - d3 * d2, d5 * d2 - d1 * d6, d3 * d6 - d5 * d4
    regions = [  # in Ericson's order: the first that holds wins
        (d1 <= 0) & (d2 <= 0),  # vertex a
        (d3 >= 0) & (d4 <= d3),  # vertex b
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),  # edge ab (opposite c)
        (d6 >= 0) & (d5 <= d6),  # vertex c
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),  # edge ac (opposite b)
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),  # edge bc (opposite a)
    ]
    which = np.select(regions, np.arange(6), default=6)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        denom = va + vb + vc
        v, w = vb / denom, vc / denom
    cols = [a, b, a + t_ab[:, None] * ab, c, a + t_ac[:, None] * ac, b + t_bc[:, None] * (c - b),
            a + v[:, None] * ab + w[:, None] * ac]  # fmt: skip
    closest = np.choose(which[:, None], cols)
    kind = np.array([VERTEX, VERTEX, EDGE, VERTEX, EDGE, EDGE, FACE])[which]
    index = np.array([0, 1, 2, 2, 1, 0, 0])[which]
    return closest, kind, index


def signed_distance_to_faces(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, adjacency: MeshAdjacency,
                             face_idx: np.ndarray) -> np.ndarray:  # fmt: skip
    """Signed distances ``(N,)`` (metres, negative inside) of ``points (N, 3)`` to the closed mesh
    ``vertices (V, 3)``, ``faces (F, 3)`` as ``igl.signed_distance`` with the pseudonormal sign
    computes them, given that ``face_idx (N,)`` names each point's closest face. Face normals come
    from ``igl.per_face_normals``, for the faces read only. A point whose feature is an edge
    without exactly two faces gets NaN (let libigl answer it)."""
    import igl

    P = np.asarray(points, dtype=np.float64)
    Q = np.asarray(vertices, dtype=np.float64)
    fi = np.asarray(face_idx, dtype=np.int64)
    if not len(fi):
        return np.zeros(0)
    tri = faces[fi]
    c, kind, index = closest_point_on_triangles(P, Q[tri[:, 0]], Q[tri[:, 1]], Q[tri[:, 2]])
    edge, vert = np.flatnonzero(kind == EDGE), np.flatnonzero(kind == VERTEX)
    other = adjacency.across[fi[edge], index[edge]]
    ring = _ring_slots(adjacency, tri[vert, index[vert]])
    # only the faces read below (a face's normal depends on its vertices alone)
    need = np.unique(np.concatenate([fi, other[other >= 0], adjacency.ring_face[ring[0]]]))
    FN = np.zeros((len(faces), 3))
    FN[need] = igl.per_face_normals(Q, faces[need])
    n = FN[fi]
    n[edge] += FN[np.maximum(other, 0)]
    n[edge[other < 0]] = np.nan
    if len(vert):
        n[vert] = _vertex_pseudonormals(Q, faces, adjacency, FN, *ring)
    qc = P - c
    sign = np.where(np.einsum("ij,ij->i", qc, n) >= 0, 1.0, -1.0)
    d = sign * np.sqrt(np.einsum("ij,ij->i", qc, qc))
    d[np.isnan(n).any(axis=1)] = np.nan
    return d


def _ring_slots(adj: MeshAdjacency, verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(slots, counts)``: the positions in ``adj.ring_face`` of the faces around each of
    ``verts (M,)``, one vertex after the other, and how many each has."""
    lo, hi = adj.ring_ptr[verts], adj.ring_ptr[verts + 1]
    counts = hi - lo
    first = np.cumsum(counts) - counts
    return np.repeat(lo - first, counts) + np.arange(counts.sum()), counts


def _vertex_pseudonormals(Q, faces, adj: MeshAdjacency, FN, slots: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Angle-weighted sums of the face normals around each vertex of :func:`_ring_slots`'s
    ``(slots, counts)`` (not normalised: a sign does not need it), ``(M, 3)``."""
    f, k = adj.ring_face[slots], adj.ring_corner[slots]
    tri = faces[f]
    rows = np.arange(len(f))
    at = Q[tri[rows, k]]
    e1 = Q[tri[rows, (k + 1) % 3]] - at
    e2 = Q[tri[rows, (k + 2) % 3]] - at
    cos = np.einsum("ij,ij->i", e1, e2) / np.sqrt(np.einsum("ij,ij->i", e1, e1) * np.einsum("ij,ij->i", e2, e2))
    weighted = FN[f] * np.arccos(np.clip(cos, -1.0, 1.0))[:, None]
    return np.add.reduceat(weighted, np.cumsum(counts) - counts, axis=0)  # every vertex has a face

"""contacts.pseudonormal: libigl's pseudonormal signed distance, given the closest face."""

from __future__ import annotations

import numpy as np
import pytest

from dualhuman_builder.contacts.pseudonormal import (EDGE, FACE, VERTEX, MeshAdjacency, closest_point_on_triangles,
                                                     signed_distance_to_faces)  # fmt: skip


def _tetrahedron():
    V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # outward
    return V, F


def test_adjacency_of_a_tetrahedron():
    V, F = _tetrahedron()
    adj = MeshAdjacency.of(F, 4)
    for f in range(4):
        for x in range(3):
            g = adj.across[f, x]
            edge = {F[f, (x + 1) % 3], F[f, (x + 2) % 3]}
            assert g != f and edge <= set(F[g])  # the other face of that edge
    for v in range(4):
        lo, hi = adj.ring_ptr[v], adj.ring_ptr[v + 1]
        assert hi - lo == 3
        assert all(F[f, k] == v for f, k in zip(adj.ring_face[lo:hi], adj.ring_corner[lo:hi]))
    open_mesh = MeshAdjacency.of(F[:3], 4)  # the edges of the missing face have one face each
    assert (open_mesh.across == -1).sum() == 3


def test_closest_point_features():
    a, b, c = np.eye(3)[None, 0] * 0, np.array([[1.0, 0, 0]]), np.array([[0.0, 1, 0]])
    p = np.array([[0.2, 0.2, 0.5], [-1.0, -1.0, 0.3], [2.0, -0.1, 0.0], [0.5, -1.0, 0.0], [1.0, 1.0, 0.0]])
    n = len(p)
    C, kind, index = closest_point_on_triangles(p, np.repeat(a, n, 0), np.repeat(b, n, 0), np.repeat(c, n, 0))
    np.testing.assert_allclose(C, [[0.2, 0.2, 0.0], [0, 0, 0], [1, 0, 0], [0.5, 0, 0], [0.5, 0.5, 0]], atol=1e-15)
    assert kind.tolist() == [FACE, VERTEX, VERTEX, EDGE, EDGE]
    assert index.tolist() == [0, 0, 1, 2, 0]  # vertex a, vertex b, edge ab (opposite c), edge bc (opposite a)


def test_signed_distance_equals_libigl_on_a_body(body_model):
    """Points around and inside a posed anny body, on every kind of feature (many exactly above a
    vertex or an edge), against ``igl.signed_distance`` of the whole mesh: same value (1e-12 m)
    and sign given libigl's closest face."""
    import igl
    import torch

    from dualhuman_builder.body.topology import collision_faces

    faces = body_model.faces.cpu().numpy()
    F = faces[collision_faces(faces, body_model.num_vertices)].astype(np.int64)
    with torch.no_grad():
        pose = torch.zeros(1, body_model.num_bones, 3)
        V = body_model.forward(pose, None, torch.tensor([[0.0, 0.95, 0.0]])).vertices[0].double().numpy()
    rng = np.random.default_rng(1)
    vn = igl.per_vertex_normals(V, F)
    used = np.unique(F)
    at_vertices = V[used[::7]] + vn[used[::7]] * rng.uniform(-0.04, 0.04, (len(used[::7]), 1))
    mid = (V[F[::11, 0]] + V[F[::11, 1]]) / 2
    en = vn[F[::11, 0]] + vn[F[::11, 1]]
    at_edges = mid + en * rng.uniform(-0.03, 0.03, (len(mid), 1))
    P = np.concatenate([at_vertices, at_edges, V[used[::5]] + rng.normal(0, 0.02, (len(used[::5]), 3))])
    S, I, C, _ = igl.signed_distance(P, V, F, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)
    adj = MeshAdjacency.of(F, len(V))
    d = signed_distance_to_faces(P, V, F, adj, I)
    np.testing.assert_allclose(d, S, rtol=0, atol=1e-12)
    assert (S < 0).sum() > 500 and (S > 0).sum() > 500
    tri = F[I]
    _, kind, _ = closest_point_on_triangles(P, V[tri[:, 0]], V[tri[:, 1]], V[tri[:, 2]])
    assert min(np.sum(kind == k) for k in (FACE, EDGE, VERTEX)) > 50  # every branch of the sign is exercised


def test_an_edge_with_one_face_is_left_to_libigl():
    V, F = _tetrahedron()
    adj = MeshAdjacency.of(F[:3], 4)  # face 3 removed: edges 1-2, 2-3, 3-1 border the hole
    p = np.array([[0.6, 0.6, -0.2], [0.2, 0.2, -0.5]])  # closest to edge 1-2 (open), to face 0's interior
    d = signed_distance_to_faces(p, V, F[:3], adj, np.array([0, 0]))
    assert np.isnan(d[0]) and d[1] == pytest.approx(0.5)

"""contacts.pseudonormal: libigl's pseudonormal signed distance, given the closest face."""

from __future__ import annotations

import numpy as np
import pytest

from dualhuman_builder.geometry.pseudonormal import (EDGE, FACE, VERTEX, MeshAdjacency, closest_point_on_triangles,
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


def _posed_body_and_points(body_model):
    """A posed anny body ``(V, F)`` (float64, its closed component) and points ``P`` around and
    inside it on every kind of feature (many exactly above a vertex or an edge)."""
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
    return V, F, P


def test_signed_distance_equals_libigl_on_a_body(body_model):
    """Points around and inside a posed anny body, on every kind of feature, against
    ``igl.signed_distance`` of the whole mesh: same value (1e-12 m) and sign given libigl's
    closest face."""
    import igl

    V, F, P = _posed_body_and_points(body_model)
    S, I, C, _ = igl.signed_distance(P, V, F, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)
    adj = MeshAdjacency.of(F, len(V))
    d = signed_distance_to_faces(P, V, F, adj, I)
    np.testing.assert_allclose(d, S, rtol=0, atol=1e-12)
    assert (S < 0).sum() > 500 and (S > 0).sum() > 500
    tri = F[I]
    _, kind, _ = closest_point_on_triangles(P, V[tri[:, 0]], V[tri[:, 1]], V[tri[:, 2]])
    assert min(np.sum(kind == k) for k in (FACE, EDGE, VERTEX)) > 50  # every branch of the sign is exercised


def test_the_narrow_phase_kernel_computes_the_same_signed_distance(body_model):
    """The warp kernel of :class:`NearSelector` (float64, on the face its BVH found) gives what
    :func:`signed_distance_to_faces` gives on that face (1e-12 m) and what libigl gives on the
    whole mesh (1e-7 m: the float32 BVH may name the other of two faces at a tie), sign included,
    for every point it finds beyond the threshold; the others are left to libigl (NaN)."""
    import igl

    from dualhuman_builder.geometry.narrow import NearSelector

    V, F, P = _posed_body_and_points(body_model)
    adj = MeshAdjacency.of(F, len(V))
    sel = NearSelector(F, V, adjacency=adj)
    band, threshold = 0.05, 0.01
    near = sel.query(0, P, V, band, threshold)
    beyond = near.dist > threshold + sel.slack
    assert 500 < beyond.sum() < len(near.idx)
    assert np.isnan(near.signed[~beyond]).all()
    ref = signed_distance_to_faces(P[near.idx[beyond]], V, F, adj, near.face[beyond])
    np.testing.assert_allclose(near.signed[beyond], ref, rtol=0, atol=1e-12)
    S = igl.signed_distance(P[near.idx[beyond]], V, F, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)[0]
    np.testing.assert_allclose(near.signed[beyond], S, rtol=0, atol=1e-7)
    assert (S < 0).sum() > 100 and (S > 0).sum() > 100
    # libigl answers the possible contacts and those the kernel puts inside
    assert set(near.exact) == set(np.flatnonzero(~beyond | (near.signed < 0)))


def test_an_edge_with_one_face_is_left_to_libigl():
    V, F = _tetrahedron()
    adj = MeshAdjacency.of(F[:3], 4)  # face 3 removed: edges 1-2, 2-3, 3-1 border the hole
    p = np.array([[0.6, 0.6, -0.2], [0.2, 0.2, -0.5]])  # closest to edge 1-2 (open), to face 0's interior
    d = signed_distance_to_faces(p, V, F[:3], adj, np.array([0, 0]))
    assert np.isnan(d[0]) and d[1] == pytest.approx(0.5)


def test_the_narrow_phase_kernel_leaves_an_open_edge_to_libigl():
    from dualhuman_builder.geometry.narrow import NearSelector

    V, F = _tetrahedron()
    sel = NearSelector(F[:3], V)
    p = np.array([[0.6, 0.6, -0.2], [0.2, 0.2, -0.5]])
    near = sel.query(0, p, V, 1.0, 0.0)
    assert near.idx.tolist() == [0, 1]
    assert np.isnan(near.signed[0]) and near.signed[1] == pytest.approx(0.5, abs=1e-12)
    assert near.exact.tolist() == [0]

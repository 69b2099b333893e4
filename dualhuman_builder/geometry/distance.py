"""Signed distances between two deforming body meshes, for every frame of a scene (float32 warp queries).

:class:`MeshDistance` keeps a warp BVH of one body mesh: built on the first frame's vertices and
refit per frame after (a BVH keeps the split planes of its build through every refit, so it is
built on real vertices, never on placeholders). ``mesh_query_point_sign_normal`` gives, for each
query point within ``band`` of the surface, the distance to the closest point with the pseudonormal
sign (negative inside). :class:`PairDistance` answers both directions of a frame; its meshes are the
body component only (:func:`~dualhuman_builder.body.topology.collision_faces`), closed, so the
pseudonormal sign is exact wherever the surface does not cross itself.

Broad phase: only vertices of body parts whose bounding boxes, grown by ``band``, overlap a part
of the other body are queried; frames whose bodies are farther apart than ``band`` cost almost
nothing.

The scene generator and its checks use it. ``tests/sim/test_scenes.py`` checks it against
``igl.signed_distance`` (pseudonormal) within 1e-4 m on scene distances stored as float16;
``benchmarks/bench_contacts.py`` (row c) measures its speed. The contacts stage needs libigl's exact
answer instead (:mod:`dualhuman_builder.geometry.narrow`).

Distances are metres, float64; NaN means "farther than ``band``".
"""

from __future__ import annotations

import functools

import numpy as np


@functools.lru_cache(maxsize=1)
def _kernel():
    """warp and the ``signed_distance`` kernel: per point, its pseudonormal signed distance to the
    mesh (float32 metres, negative inside) where within ``band``, NaN elsewhere."""
    from dualhuman_builder.warp_runtime import init_warp

    wp = init_warp()

    @wp.kernel
    def signed_distance(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), band: float, out: wp.array(dtype=float)):
        i = wp.tid()
        p = points[i]
        q = wp.mesh_query_point_sign_normal(mesh, p, band)
        out[i] = wp.nan
        if q.result:
            c = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
            d = wp.length(p - c)
            if d <= band:
                out[i] = d * q.sign

    return wp, signed_distance


class MeshDistance:
    """Signed distance queries against one body mesh whose vertices change every frame.

    ``faces (F, 3)`` must describe a closed mesh (use the collision faces of anny).
    """

    def __init__(self, faces: np.ndarray, num_vertices: int, device: str = "cpu"):
        wp, self._kernel = _kernel()
        self._wp = wp
        self.device = device
        self.num_vertices = int(num_vertices)
        self._indices = wp.array(np.asarray(faces, np.int32).ravel(), dtype=int, device=device)
        self._points = self.mesh = None

    def update(self, vertices: np.ndarray) -> None:
        """Move the mesh to ``vertices (V, 3)`` (metres) and refit its BVH. The BVH is built on
        the first call's vertices and refit afterwards (a refit keeps the build's split planes:
        built on placeholder points, all at one spot, every query would visit most of the tree)."""
        wp = self._wp
        v = wp.array(np.asarray(vertices, np.float32), dtype=wp.vec3, device=self.device)
        if len(v) != self.num_vertices:
            raise ValueError(f"expected {self.num_vertices} vertices, got {len(v)}")
        if self.mesh is None:
            self._points = v
            self.mesh = wp.Mesh(points=self._points, indices=self._indices)
            return
        self._points.assign(v)
        self.mesh.refit()

    def query(self, points: np.ndarray, band: float) -> np.ndarray:
        """Signed distances ``(N,)`` of ``points (N, 3)`` to the mesh; NaN beyond ``band``."""
        wp = self._wp
        if self.mesh is None:
            raise RuntimeError("MeshDistance.query before update(): the mesh has no vertices yet")
        if len(points) == 0:
            return np.zeros(0)
        pts = wp.array(np.asarray(points, np.float32), dtype=wp.vec3, device=self.device)
        out = wp.zeros(len(points), dtype=float, device=self.device)
        wp.launch(self._kernel, dim=len(points), inputs=[self.mesh.id, pts, float(band), out], device=self.device)
        return out.numpy().astype(np.float64)


class PairDistance:
    """Both directions of signed distance between two bodies of the same topology, per frame.

    ``vertex_region (V,)`` (body-part labels, e.g. from ``rigs/anny_regions.toml``) enables the
    region broad phase: a region's vertices are queried only if its bounding box, grown by the
    band, overlaps the bounding box of some region of the other body.
    """

    def __init__(self, faces: np.ndarray, num_vertices: int, collision_face_index: np.ndarray | None = None,
                 vertex_region: np.ndarray | None = None, device: str = "cpu"):  # fmt: skip
        closed = faces if collision_face_index is None else faces[collision_face_index]
        self.meshes = (MeshDistance(closed, num_vertices, device), MeshDistance(closed, num_vertices, device))
        self.groups = None
        if vertex_region is not None:
            self.groups = [np.flatnonzero(vertex_region == r) for r in np.unique(vertex_region)]

    def _boxes(self, verts: np.ndarray) -> np.ndarray:
        """Per body part (one part without regions), the box ``(lo, hi)`` of ``verts (V, 3)``: ``(R, 2, 3)``."""
        groups = self.groups if self.groups is not None else [np.arange(len(verts))]
        return np.array([(verts[g].min(0), verts[g].max(0)) for g in groups])  # (R, 2, 3)

    def candidates(self, p: np.ndarray, other: np.ndarray, band: float, only: np.ndarray | None = None) -> np.ndarray:
        """Indices of the vertices of ``p`` (or of ``only``) that may lie within ``band`` of the
        body ``other``: those in a body part (or, for ``only``, each point) whose box grown by
        ``band`` overlaps the box of a part of ``other``."""
        boxes = self._boxes(other)
        if only is not None:
            q = p[only]
            hit = np.any(np.all((q[:, None] >= boxes[None, :, 0] - band) & (q[:, None] <= boxes[None, :, 1] + band),
                                axis=2), axis=1)  # fmt: skip
            return only[hit]
        groups = self.groups if self.groups is not None else [np.arange(len(p))]
        keep = []
        for g in groups:
            lo, hi = p[g].min(0) - band, p[g].max(0) + band
            if np.any(np.all((boxes[:, 0] <= hi) & (boxes[:, 1] >= lo), axis=1)):
                keep.append(g)
        return np.concatenate(keep) if keep else np.zeros(0, dtype=np.int64)

    def __call__(self, verts_a: np.ndarray, verts_b: np.ndarray, band: float = 0.05,
                 query_a: np.ndarray | None = None, query_b: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """``(d_a (V,), d_b (V,))``: each vertex of A to B's surface and of B to A's; NaN beyond
        ``band`` or not queried. ``query_a``/``query_b`` restrict the queried vertex indices."""
        out = []
        for i, (p, other, only) in enumerate(((verts_a, verts_b, query_a), (verts_b, verts_a, query_b))):
            d = np.full(len(p), np.nan)
            near = self.candidates(p, other, band, only)
            if len(near):
                mesh = self.meshes[1 - i]
                mesh.update(other)
                d[near] = mesh.query(p[near], band)
            out.append(d)
        return out[0], out[1]


@functools.lru_cache(maxsize=2)
def get_pair_distance(device: str = "cpu") -> PairDistance:
    """A :class:`PairDistance` for the process-wide anny model's topology, with the region broad
    phase of ``rigs/anny_regions.toml`` (built once)."""
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.body.regions import load_regions
    from dualhuman_builder.body.topology import collision_faces

    model = get_body_model()
    faces = model.faces.cpu().numpy()
    return PairDistance(faces, model.num_vertices, collision_faces(faces, model.num_vertices),
                        load_regions(model).vertex_region, device)  # fmt: skip

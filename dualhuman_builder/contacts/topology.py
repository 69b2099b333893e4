"""The mesh topology both bodies share, as the contact kernels index it.

One :class:`ContactTopology` per body model: the closed target mesh's faces, the vertex regions
that region events are named by (``rigs/anny_regions.toml`` for anny), the unique edges the deep
flood fill walks and the faces' adjacency for the pseudonormal sign. Both actors use the same
topology (the same body model), so it is built once (:func:`default_topology`).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from dualhuman_builder.geometry.pseudonormal import MeshAdjacency


@dataclass(frozen=True, eq=False)
class ContactTopology:
    """Index arrays for one mesh topology, shared by both bodies, built once.

    ``faces (F, 3)`` int64: the closed target mesh (for anny, its body component); ``num_vertices``
    V; ``vertex_region (V,)`` region index per vertex; ``region_names (R,)``; ``reference_vertices
    (V, 3)`` metres, any pose (the rest pose for anny): the warp BVHs of the narrow phase are built
    there and refit per frame. Derived: ``face_region (F,)``, the majority region of each face's
    vertices (the first vertex's on a three-way tie), the unique edges (for the flood fill) and
    the faces' :class:`~dualhuman_builder.geometry.pseudonormal.MeshAdjacency`.
    """

    faces: np.ndarray
    num_vertices: int
    vertex_region: np.ndarray
    region_names: tuple[str, ...]
    reference_vertices: np.ndarray = field(repr=False)
    face_region: np.ndarray = field(init=False, repr=False)
    edges: np.ndarray = field(init=False, repr=False)  # (E, 2) int64, unique, sorted per row
    adjacency: MeshAdjacency = field(init=False, repr=False)

    def __post_init__(self):
        faces = np.asarray(self.faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ValueError(f"faces must have shape (F, 3) with F > 0, got {faces.shape}")
        if not np.issubdtype(faces.dtype, np.integer):
            raise ValueError(f"faces must be integer vertex indices, got dtype {faces.dtype}")
        faces = faces.astype(np.int64)
        V = int(self.num_vertices)
        if faces.min() < 0 or faces.max() >= V:
            raise ValueError(f"faces index vertices 0..{V - 1}; found {faces.min()}..{faces.max()}")
        region = np.asarray(self.vertex_region)
        if region.shape != (V,):
            raise ValueError(f"vertex_region must have shape ({V},), got {region.shape}")
        if not np.issubdtype(region.dtype, np.integer) or region.min() < 0:
            raise ValueError("vertex_region must hold non-negative integer region indices")
        names = tuple(str(n) for n in self.region_names)
        if int(region.max()) >= len(names):
            raise ValueError(f"vertex_region uses region {int(region.max())} but only {len(names)} names are given")
        ref = np.asarray(self.reference_vertices, dtype=np.float64)
        if ref.shape != (V, 3) or not np.isfinite(ref).all():
            raise ValueError(f"reference_vertices must be finite with shape ({V}, 3), got {ref.shape}")
        region = region.astype(np.int64)
        a, b, c = region[faces[:, 0]], region[faces[:, 1]], region[faces[:, 2]]
        e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        for k, v in (("faces", faces), ("num_vertices", V), ("vertex_region", region), ("region_names", names),
                     ("reference_vertices", ref), ("face_region", np.where((b == c) & (a != b), b, a)),
                     ("edges", np.unique(np.sort(e, axis=1), axis=0)), ("adjacency", MeshAdjacency.of(faces, V))):  # fmt: skip
            object.__setattr__(self, k, v)

    @classmethod
    def for_model(cls, model=None, regions=None) -> "ContactTopology":
        """The topology of the anny ``model`` (default: the process-wide one): its body component
        (:func:`~dualhuman_builder.body.topology.collision_faces`), ``regions`` (default
        :func:`~dualhuman_builder.body.regions.load_regions`) and the rest pose."""
        from dualhuman_builder.body.model import get_body_model
        from dualhuman_builder.body.regions import load_regions
        from dualhuman_builder.body.topology import collision_faces

        model = model or get_body_model()
        faces = model.faces.cpu().numpy()
        regions = regions or load_regions(model)
        rest = model.rest().vertices[0].detach().cpu().numpy()
        return cls(faces[collision_faces(faces, model.num_vertices)], model.num_vertices, regions.vertex_region,
                   regions.names, rest)  # fmt: skip


@functools.lru_cache(maxsize=1)
def default_topology() -> ContactTopology:
    """:meth:`ContactTopology.for_model` of the process-wide anny model, built once per process."""
    return ContactTopology.for_model()

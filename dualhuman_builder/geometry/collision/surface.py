"""The obstacle surface of a body topology: the closed component the collision term queries against.

anny's mesh has four closed components: the body and three small shells (two eyeballs, the mouth
interior) that poke out of the body surface, where the pseudonormal sign of the whole mesh is wrong.
The obstacle is therefore the largest component alone
(:func:`~dualhuman_builder.body.topology.collision_faces`), and the query points are its vertices:
eyes and mouth never count. Inside/outside is defined only if that surface is closed (every edge
shared by exactly two faces), which :class:`ObstacleSurface` checks.
"""

from __future__ import annotations

import numpy as np
import torch

from dualhuman_builder.body.topology import collision_faces


def faces_array(faces) -> np.ndarray:
    """``faces`` (an ``(F, 3)`` int array or tensor, F > 0, no negative index) as int64 numpy;
    ``ValueError`` otherwise."""
    f = faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise ValueError(f"faces must have shape (F, 3) with F > 0, got {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be integer vertex indices, got dtype {f.dtype}")
    if f.min() < 0:
        raise ValueError("faces contain negative vertex indices")
    return f.astype(np.int64)


class ObstacleSurface:
    """The closed obstacle surface of ``faces (F, 3)`` (int array or tensor; e.g. anny's ``model.faces``).

    ``faces (F, 3)`` int64, all of them; ``num_vertices_min``: one more than the largest index (a
    body passed to the term needs at least that many vertices); ``obstacle_faces (F', 3)`` int64,
    the largest closed component; ``obstacle_vertices (S,)`` its vertices, sorted; ``edges (E, 2)``
    its undirected edges ``(u < w)``, sorted, which the sign flood fill follows.
    Raises ``ValueError`` on malformed faces (:func:`faces_array`) or an obstacle that is not closed.
    """

    def __init__(self, faces):
        self.faces = faces_array(faces)
        self.num_vertices_min = int(self.faces.max()) + 1
        self.obstacle_faces = self.faces[collision_faces(self.faces, self.num_vertices_min)]
        e = np.sort(np.concatenate([self.obstacle_faces[:, [0, 1]], self.obstacle_faces[:, [1, 2]],
                                    self.obstacle_faces[:, [2, 0]]]), axis=1)  # fmt: skip
        _, counts = np.unique(e, axis=0, return_counts=True)
        if not np.all(counts == 2):
            raise ValueError(
                f"the obstacle surface (largest component of faces) is not closed: {int(np.sum(counts == 1))} "
                f"boundary and {int(np.sum(counts > 2))} non-manifold edges; inside/outside is undefined"
            )
        self.obstacle_vertices = np.unique(self.obstacle_faces)
        self.edges = np.unique(e, axis=0)
        self._mask: np.ndarray | None = None

    def vertex_mask(self, V: int) -> np.ndarray:
        """``(V,)`` bool, True at the obstacle's vertices (the query points); cached per ``V``."""
        if self._mask is None or len(self._mask) != V:
            self._mask = np.zeros(V, bool)
            self._mask[self.obstacle_vertices] = True
        return self._mask

    def part_corners(self, parts) -> tuple[np.ndarray, np.ndarray, int]:
        """The obstacle's faces grouped by ``parts`` (``(V,)`` ints, or None: one part), as the
        ``(vertex, part)`` pairs of each part's face corners (two ``(n,)`` int32 arrays, sorted by part
        then vertex) and the part count. A face belongs to the highest-numbered part among its
        corners', so a part numbered above its neighbours (the fingers) takes the faces it shares
        with them: when it moves alone, the faces it leaves to them stay still."""
        if parts is None:
            labels = np.zeros(self.num_vertices_min, np.int64)
        else:
            labels = np.asarray(parts)
            if labels.ndim != 1 or len(labels) < self.num_vertices_min or not np.issubdtype(labels.dtype, np.integer):
                raise ValueError(f"parts must be (V,) integers with V >= {self.num_vertices_min}, "
                                 f"got {labels.shape} {labels.dtype}")
        face_part = np.unique(labels[self.obstacle_faces].max(axis=1), return_inverse=True)[1].ravel()
        pairs = np.unique(np.stack([np.repeat(face_part, 3), self.obstacle_faces.ravel()], axis=1), axis=0)
        vert, part = np.ascontiguousarray(pairs[:, 1], np.int32), np.ascontiguousarray(pairs[:, 0], np.int32)
        return vert, part, int(face_part.max()) + 1

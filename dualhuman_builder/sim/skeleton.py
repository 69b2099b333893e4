"""Fast forward kinematics on anny's skeleton alone (no skinning), for posing and IK.

With the pose parameterisation of :mod:`dualhuman_builder.body.model` (world-aligned local
rotations ``L``), world-aligned global rotations chain as ``A_c = A_p L_c`` and bone heads as
``h_c = h_p + A_p (r_c - r_p)``, where ``r`` are the rest bone heads of the actor's shape and
``h_root = transl``. That is anny's own kinematics (``anny.utils.kinematics``, 'local-ref') without
the mesh, so posing many frames needs no skinning; :meth:`Skeleton.check_against_model` checks
the identity against the full model.

Arrays are float64 numpy: rotations ``(..., J, 3, 3)``, positions ``(..., J, 3)``, world metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Skeleton:
    """An actor's rest skeleton: ``names (J,)``, ``parents (J,)``, ``rest (J, 3)`` rest bone heads
    with the root at the origin (Y-up, facing +Z), ``shape`` the phenotype it was made from."""

    names: list[str]
    parents: np.ndarray
    rest: np.ndarray
    shape: np.ndarray

    @classmethod
    def from_model(cls, model, shape) -> "Skeleton":
        import torch

        shape_t = model.shape_tensor(shape)
        with torch.no_grad():
            rest = model.rest(shape_t).bone_heads[0].double().cpu().numpy()
        return cls(list(model.bone_names), np.asarray(model.bone_parents), rest, shape_t.cpu().numpy())

    def __post_init__(self):
        self._index = {n: i for i, n in enumerate(self.names)}

    def index(self, name: str) -> int:
        return self._index[name]

    def identity(self, frames: int = 1) -> np.ndarray:
        """``(frames, J, 3, 3)`` identity local rotations: the rest pose."""
        return np.broadcast_to(np.eye(3), (frames, len(self.names), 3, 3)).copy()

    def globals_(self, local: np.ndarray) -> np.ndarray:
        """World-aligned global rotations ``(..., J, 3, 3)`` from local ones."""
        out = np.empty_like(local)
        for c, p in enumerate(self.parents):  # anny lists parents before children
            out[..., c, :, :] = local[..., c, :, :] if p < 0 else out[..., p, :, :] @ local[..., c, :, :]
        return out

    def fk(self, local: np.ndarray, transl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bone heads ``(..., J, 3)`` and global rotations ``(..., J, 3, 3)`` for local rotations
        ``(..., J, 3, 3)`` and root positions ``(..., 3)``."""
        glob = self.globals_(local)
        heads = np.empty(local.shape[:-2] + (3,))
        heads[..., 0, :] = transl
        offsets = self.rest - self.rest[np.maximum(self.parents, 0)]
        for c, p in enumerate(self.parents):
            if p >= 0:
                heads[..., c, :] = heads[..., p, :] + np.einsum("...ij,j->...i", glob[..., p, :, :], offsets[c])
        return heads, glob

    def head(self, local: np.ndarray, transl: np.ndarray, bone: str) -> np.ndarray:
        return self.fk(local, transl)[0][..., self.index(bone), :]

    def length(self, a: str, b: str) -> float:
        """Rest distance between two bone heads (e.g. shoulder to elbow), metres."""
        return float(np.linalg.norm(self.rest[self.index(b)] - self.rest[self.index(a)]))

    def check_against_model(self, model, local: np.ndarray, transl: np.ndarray) -> float:
        """Largest bone-head difference (m) between this FK and the full anny model."""
        import roma
        import torch

        out = model(roma.rotmat_to_rotvec(torch.tensor(local, dtype=torch.float32)), torch.tensor(self.shape),
                    torch.tensor(transl, dtype=torch.float32))  # fmt: skip
        heads, _ = self.fk(local, transl)
        return float(np.abs(out.bone_heads.double().numpy() - heads).max())

"""A thin, batched wrapper over the ``anny`` body model in the toolkit's Y-up world frame.

Pose parameters (what :class:`~dualhuman_builder.tracks.BodyTrack` stores)
    ``pose``: ``(B, J, 3)`` rotation vectors (or ``(B, J, 3, 3)`` matrices), one per anny bone
    (J = 104 in the default rig), in anny's ``local-ref`` parameterisation expressed in **Y-up
    world-aligned axes**: bone ``c``'s entry is its rotation relative to its rest orientation, in
    axes that coincide with the world axes when its parents are at rest. Entry 0 (the ``root``
    bone, at the pelvis centre) is the global orientation of the body. This is SMPL's convention:
    all zeros is anny's rest pose (an A-pose) standing upright, facing +Z, left side towards +X.
    ``transl``: ``(B, 3)`` world position of the root bone head (pelvis centre), metres.
    ``shape``: ``(B, P)`` or ``(P,)`` anny phenotype values in [0, 1], in the order of
    :attr:`BodyModel.shape_names` (gender, age, muscle, weight, height, proportions).

World-aligned global rotations
    ``A_c = A_parent(c) @ L_c`` with ``A_root = L_root``; ``A_c`` is bone ``c``'s rotation away
    from its rest orientation, in world axes. :meth:`BodyModel.local_to_global` and
    :meth:`BodyModel.global_to_local` convert; retargeting segment orientations works in ``A``.

Internally anny is Z-up; every input is conjugated by :data:`~dualhuman_builder.conventions.ZUP_TO_YUP`
and every output rotated by it (a rotation, so triangle winding stays outward).
"""

from __future__ import annotations

import functools
import glob
import os
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import roma
import torch

from dualhuman_builder.conventions import ZUP_TO_YUP
from dualhuman_builder.errors import BodyModelError

MODEL_NAME = "anny"


def anny_version() -> str:
    import importlib.metadata

    return importlib.metadata.version("anny")


def anny_cache_dir() -> Path:
    """Folder where anny keeps its built model data (``ANNY_CACHE_DIR`` or ``~/.cache/anny``)."""
    return Path(os.environ.get("ANNY_CACHE_DIR", Path.home() / ".cache" / "anny"))


def anny_cache_files() -> list[Path]:
    """The built files of the default anny model for the installed anny's data version."""
    from anny.models.model_data import CURRENT_DATA_VERSION

    pattern = anny_cache_dir() / f"v{CURRENT_DATA_VERSION}" / "build_compact_model_data_*.safetensors"
    return [Path(p) for p in sorted(glob.glob(str(pattern))) if Path(p).stat().st_size > 0]


def anny_cache_is_warm() -> bool:
    """True when constructing the default model loads anny's built data from its cache instead of
    building it (see :func:`anny_cache_files`)."""
    return bool(anny_cache_files())


@dataclass
class BodyOutput:
    """Result of :meth:`BodyModel.forward`; all in the Y-up world frame, metres.

    ``vertices (B, V, 3)``, ``bone_heads (B, J, 3)`` (joint centres), ``bone_rotations (B, J, 3, 3)``
    (each bone's world orientation, columns are the bone axes), ``joints (B, 22, 3)`` (the
    HumanML3D joint set, see :mod:`dualhuman_builder.body.joints`).
    """

    vertices: torch.Tensor
    bone_heads: torch.Tensor
    bone_rotations: torch.Tensor
    joints: torch.Tensor


class BodyModel:
    """anny with batched forward in the Y-up world frame. Build it with :func:`get_body_model`.

    Attributes: ``bone_names`` (J,), ``bone_parents`` (J,) int array (root's parent -1),
    ``shape_names`` (P,), ``faces`` ``(F, 3)`` int64 tensor, ``num_vertices``.
    """

    name = MODEL_NAME

    def __init__(self, device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32):
        _quiet_warp()
        import anny

        _reuse_skinning_kernels()
        self.version = anny_version()
        self.device = torch.device(device)
        self.dtype = dtype
        try:
            self.anny = anny.Anny().to(device=self.device, dtype=dtype)
        except Exception as e:  # anny raises plain exceptions when its data or cache is broken
            raise BodyModelError(
                f"could not build the anny body model ({type(e).__name__}: {e})",
                fix=f"rebuild the cache: rm -rf {anny_cache_dir()} && dualhuman body warm",
            ) from e
        self.anny.requires_grad_(False)
        self.bone_names: list[str] = list(self.anny.bone_labels)
        self.bone_parents = np.asarray([int(p) for p in self.anny.bone_parents], dtype=np.int64)
        self.shape_names: list[str] = list(self.anny.phenotype_labels)
        self.faces = self.anny.faces.to(self.device)
        self.num_vertices = int(self.anny.template_vertices.shape[0])
        self._c = torch.as_tensor(ZUP_TO_YUP, dtype=dtype, device=self.device)
        self._bone_index = {n: i for i, n in enumerate(self.bone_names)}
        self._levels = _depth_levels(self.bone_parents)
        from dualhuman_builder.body.joints import JOINT22_BONES

        self.joint22_index = torch.as_tensor(
            [self.bone_index(b) for b in JOINT22_BONES], device=self.device
        )
        self._coco = None

    # ----------------------------------------------------------------------------- names
    @property
    def num_bones(self) -> int:
        return len(self.bone_names)

    def bone_index(self, name: str) -> int:
        try:
            return self._bone_index[name]
        except KeyError:
            raise BodyModelError(f"anny has no bone {name!r}", fix="see `dualhuman body info --bones`") from None

    def default_shape(self) -> torch.Tensor:
        """``(P,)`` phenotype of anny's average adult (all 0.5)."""
        return torch.full((len(self.shape_names),), 0.5, dtype=self.dtype, device=self.device)

    def shape_tensor(self, shape: dict[str, float] | np.ndarray | torch.Tensor | None) -> torch.Tensor:
        """Phenotype values as a ``(P,)`` or ``(B, P)`` tensor; a dict may omit names (0.5)."""
        if shape is None:
            return self.default_shape()
        if isinstance(shape, dict):
            unknown = set(shape) - set(self.shape_names)
            if unknown:
                raise BodyModelError(f"unknown shape parameters {sorted(unknown)}; anny has {self.shape_names}")
            return torch.as_tensor(
                [float(shape.get(n, 0.5)) for n in self.shape_names], dtype=self.dtype, device=self.device
            )
        t = self._tensor(shape)
        if t.shape[-1] != len(self.shape_names):
            raise BodyModelError(f"shape has {t.shape[-1]} values, anny expects {len(self.shape_names)} {self.shape_names}")
        return t

    # ----------------------------------------------------------------------------- forward
    def forward(
        self,
        pose: torch.Tensor | None = None,
        shape: torch.Tensor | None = None,
        transl: torch.Tensor | None = None,
        batch_size: int | None = None,
    ) -> BodyOutput:
        """Pose the body. ``pose (B, J, 3|3x3)``, ``shape (B|1, P)`` or ``(P,)``, ``transl (B, 3)``.

        Any of the three may be omitted (rest pose, average shape, origin). Differentiable in
        ``pose``, ``shape`` and ``transl``.
        """
        B = batch_size or _batch_of(pose, transl, shape)
        rot = self._rotations(pose, B)
        c = self._c
        # local-ref deltas in anny's Z-up axes: D = C^T R C.
        d = c.T @ rot @ c
        h = torch.zeros(B, self.num_bones, 4, 4, dtype=self.dtype, device=self.device)
        h[..., :3, :3] = d
        h[..., 3, 3] = 1.0
        if transl is not None:
            transl = self._tensor(transl).reshape(B, 3)
            h[:, 0, :3, 3] = transl @ c  # C^T t as row vectors
        shape_t = self.shape_tensor(shape)
        if shape_t.dim() == 1:
            shape_t = shape_t[None]
        out = self.anny(pose_parameters=h, phenotype_kwargs=shape_t)
        vertices = out["vertices"] @ c.T
        poses = out["bone_poses"]
        heads = poses[..., :3, 3] @ c.T
        rots = c @ poses[..., :3, :3]
        return BodyOutput(
            vertices=vertices,
            bone_heads=heads,
            bone_rotations=rots,
            joints=heads[:, self.joint22_index],
        )

    __call__ = forward

    def bone_heads(self, pose=None, shape=None, transl=None, batch_size: int | None = None) -> torch.Tensor:
        """Bone heads ``(B, J, 3)`` (world metres, Y-up) of :meth:`forward` without skinning the
        mesh: forward kinematics over the bone tree from the zero-pose heads of ``shape`` (one anny
        call at batch 1). Same inputs as :meth:`forward` (one shape for the batch); equal to its
        ``bone_heads`` within 1e-5 m (``tests/body/test_body.py``). The export uses it for track
        joints, which need no mesh (docs/decisions/0024-export-format-and-loaders.md;
        ``benchmarks/bench_export.py``)."""
        B = batch_size or _batch_of(pose, transl, shape)
        local = self._rotations(pose, B)
        shape_t = self.shape_tensor(shape)
        if shape_t.dim() == 2 and shape_t.shape[0] != 1:
            raise BodyModelError("bone_heads takes one shape for the whole batch")
        eye = torch.eye(4, dtype=self.dtype, device=self.device).expand(1, self.num_bones, 4, 4)
        zero = self.anny(pose_parameters=eye, phenotype_kwargs=shape_t.reshape(1, -1))["bone_poses"][0]
        h0 = zero[:, :3, 3] @ self._c.T  # (J, 3) Y-up, root at the origin
        parents = self.bone_parents
        edges = h0 - h0[np.maximum(parents, 0)]
        rot = self.local_to_global(local)
        heads: list = [None] * self.num_bones
        root = torch.zeros(B, 3, dtype=self.dtype, device=self.device) if transl is None else self._tensor(transl).reshape(B, 3)
        for level in self._levels:
            for j in level:
                pj = parents[j]
                heads[j] = root if pj < 0 else heads[pj] + rot[:, pj] @ edges[j]
        return torch.stack(heads, dim=1)

    def rest(self, shape=None) -> BodyOutput:
        """The rest pose (anny's A-pose) of one body, root at the origin: batch of 1."""
        return self.forward(None, shape, None, batch_size=1)

    def _tensor(self, x) -> torch.Tensor:
        if isinstance(x, np.ndarray) and not x.flags.writeable:
            x = np.array(x)  # torch refuses to wrap read-only arrays (tracks store theirs read-only)
        return torch.as_tensor(x, dtype=self.dtype, device=self.device)

    def _rotations(self, pose, batch: int) -> torch.Tensor:
        if pose is None:
            return torch.eye(3, dtype=self.dtype, device=self.device).expand(batch, self.num_bones, 3, 3)
        pose = self._tensor(pose)
        if pose.shape[-2:] == (3, 3) and pose.dim() == 4:
            rot = pose
        elif pose.dim() == 3 and pose.shape[-1] == 3:
            rot = roma.rotvec_to_rotmat(pose)
        else:
            raise BodyModelError(
                f"pose must have shape (B, {self.num_bones}, 3) rotation vectors or (B, {self.num_bones}, 3, 3) "
                f"matrices, got {tuple(pose.shape)}"
            )
        if rot.shape[1] != self.num_bones:
            raise BodyModelError(f"pose has {rot.shape[1]} bones, anny's rig has {self.num_bones}")
        return rot

    # ----------------------------------------------------------------------------- keypoints
    def coco(self, vertices: torch.Tensor) -> torch.Tensor:
        """COCO-17 keypoints ``(B, 17, 3)`` from ``vertices (B, V, 3)`` with anny's regressor."""
        from dualhuman_builder.body.joints import COCO17

        if self._coco is None:
            import anny

            reg = anny.KeypointsRegressor.coco(self.anny, labels=list(COCO17))
            self._coco = reg.regression_weights.to(device=self.device, dtype=self.dtype)
        return torch.einsum("kv,bvd->bkd", self._coco, vertices)

    # ----------------------------------------------------------------------------- rotations on the tree
    def local_to_global(self, local: torch.Tensor) -> torch.Tensor:
        """World-aligned local rotations ``(..., J, 3, 3)`` to world-aligned global ones ``A``."""
        out = [None] * self.num_bones
        for level in self._levels:
            for c in level:
                p = self.bone_parents[c]
                out[c] = local[..., c, :, :] if p < 0 else out[p] @ local[..., c, :, :]
        return torch.stack(out, dim=-3)

    def global_to_local(self, glob_rot: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`local_to_global`: ``L_c = A_parent^T A_c``."""
        parents = torch.as_tensor(np.maximum(self.bone_parents, 0), device=glob_rot.device)
        parent_rot = glob_rot[..., parents, :, :]
        local = parent_rot.transpose(-1, -2) @ glob_rot
        local[..., 0, :, :] = glob_rot[..., 0, :, :]
        return local

    def vertex_bone(self) -> np.ndarray:
        """``(V,)`` index of the bone with the largest skinning weight for each vertex."""
        w = self.anny.vertex_bone_weights.detach().cpu().numpy()
        idx = self.anny.vertex_bone_indices.detach().cpu().numpy()
        return idx[np.arange(len(idx)), w.argmax(axis=1)]


def _quiet_warp() -> None:
    """Start warp before anny does, without its banner or (on a machine without an NVIDIA driver)
    its CUDA-driver warning: :func:`~dualhuman_builder.warp_runtime.init_warp`."""
    try:
        from dualhuman_builder.warp_runtime import init_warp

        init_warp()
    except Exception:  # warp is optional for anny (it falls back to dense skinning)
        pass


def _reuse_skinning_kernels() -> None:
    """Make anny's warp skinning reuse its kernel for the same dtypes instead of building a new one
    at every call.

    anny 0.6.2's ``LinearBlendSkinning.forward`` calls ``warp_skinning.get_kernel``, which defines a
    fresh ``@wp.kernel`` each time, so warp parses and generates its code again at every skinning
    call, and a fit makes many (``benchmarks/bench_fit.py`` times one). The kernel depends only on
    the arguments, so the first one built for them serves every later call."""
    try:
        from anny.skinning import warp_skinning
    except Exception:  # no warp: anny skins densely
        return
    if not hasattr(warp_skinning.get_kernel, "cache_info"):  # not wrapped yet
        warp_skinning.get_kernel = functools.lru_cache(maxsize=None)(warp_skinning.get_kernel)


def _batch_of(*tensors) -> int:
    for t in tensors:
        if t is not None and len(getattr(t, "shape", np.shape(t))) >= 2:
            return int(t.shape[0]) if hasattr(t, "shape") else len(t)
    return 1


def _depth_levels(parents: np.ndarray) -> list[list[int]]:
    depth = np.zeros(len(parents), dtype=int)
    for i, p in enumerate(parents):
        depth[i] = 0 if p < 0 else depth[p] + 1  # anny lists parents before children
    return [list(np.flatnonzero(depth == d)) for d in range(depth.max() + 1)]


_lock = threading.Lock()


@functools.lru_cache(maxsize=4)
def _cached_model(device: str, dtype: torch.dtype) -> BodyModel:
    return BodyModel(device=device, dtype=dtype)


def get_body_model(device: str | torch.device = "cpu", dtype: torch.dtype = torch.float32) -> BodyModel:
    """The process-wide :class:`BodyModel` for ``device`` and ``dtype`` (built once, then reused)."""
    with _lock:
        return _cached_model(str(torch.device(device)), dtype)

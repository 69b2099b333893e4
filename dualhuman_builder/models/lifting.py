"""The sanity baseline of the pose estimator: each person's 2D keypoints lifted to 3D by a small MLP,
registered as ``lifting-baseline`` (``dualhuman train lifting-baseline DATASET``).

It shows what the image model and its interaction attention add over the 2D keypoints alone: every
person is lifted independently (Martinez et al.'s simple baseline: linear layers with residual blocks),
from the render's keypoints, never from the image.

Input per person, from :class:`~dualhuman_builder.models.images.ImageFrames` (its ``"image"`` is not
used): the 22 keypoints normalised by the crop's intrinsics ``K``, ``((u - cx) / fx, (v - cy) / fy)``
(so the figures do not depend on the crop size or focal length), multiplied by their visibility, the
visibility itself, all relative to the mean of the visible keypoints, and that mean: 22 x 3 + 2 numbers.
A hidden joint's pixel is zeroed (a 2D detector gives none), so occlusion costs this baseline as it would.

Output per person: the pose, root-relative joints in camera metres ``(22, 3)``, and the root, as an
offset ``(a, b)`` of its normalised image position from the keypoints' mean and its log depth ``log z``,
so that the root is ``((m + (a, b)) z, z)`` in camera metres. Loss: L1 of the pose (metres) +
``root_weight`` x L1 of the root (metres). Figures (``evaluate``): MPJPE, PA-MPJPE and translation error
(mm, :func:`~dualhuman_builder.models.metrics.pose_errors`) over both people in camera coordinates.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import torch
from torch import nn

from dualhuman_builder.models.base import Phase, register
from dualhuman_builder.models.data import TRAINING_SPLITS

NAME = "lifting-baseline"
NUM_JOINTS = 22
IN_DIM = NUM_JOINTS * 3 + 2
OUT_DIM = NUM_JOINTS * 3 + 3

DEFAULTS: dict[str, Any] = {
    "size": 32,
    "hidden": 256,
    "blocks": 2,
    "dropout": 0.1,
    "root_weight": 1.0,
    "steps": 2000,
    "lr": 1e-3,
    "weight_decay": 5e-4,
}


def lifting_input(keypoints2d: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(x (B, P, 68), mean (B, P, 2))``: the network input of keypoints ``(B, P, 22, 3)`` (u, v in
    pixels, visibility) seen with intrinsics ``K (B, 3, 3)`` (module docstring), and each person's mean
    normalised visible keypoint."""
    kp = keypoints2d.float()
    Kf = K.float()[:, None, None]
    u = (kp[..., 0] - Kf[..., 0, 2]) / Kf[..., 0, 0]
    v = (kp[..., 1] - Kf[..., 1, 2]) / Kf[..., 1, 1]
    vis = (kp[..., 2] > 0.5).to(kp.dtype)
    uv = torch.stack([u, v], dim=-1) * vis[..., None]
    n = vis.sum(-1, keepdim=True)
    mean = uv.sum(-2) / n.clamp_min(1.0)
    rel = (uv - mean[..., None, :]) * vis[..., None]
    x = torch.cat([torch.cat([rel, vis[..., None]], dim=-1).flatten(-2), mean], dim=-1)
    return x, mean


class _Block(nn.Module):
    def __init__(self, hidden: int, dropout: float):
        super().__init__()
        self.body = nn.Sequential(nn.Linear(hidden, hidden), nn.LayerNorm(hidden), nn.ReLU(), nn.Dropout(dropout),
                                  nn.Linear(hidden, hidden), nn.LayerNorm(hidden), nn.ReLU(), nn.Dropout(dropout))  # fmt: skip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


class LiftingBaseline(nn.Module):
    """The MLP of the module docstring; :meth:`forward` takes a batch of ImageFrames."""

    def __init__(self, config: dict[str, Any]):
        super().__init__()
        c = self.config = {**DEFAULTS, **config}
        h = int(c["hidden"])
        self.mlp = nn.Sequential(nn.Linear(IN_DIM, h), nn.ReLU(), *[_Block(h, float(c["dropout"])) for _ in range(int(c["blocks"]))],
                                 nn.Linear(h, OUT_DIM))  # fmt: skip

    def forward(self, keypoints2d: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(pose (B, P, 22, 3) root-relative camera metres, root (B, P, 3) camera metres)``."""
        x, mean = lifting_input(keypoints2d, K)
        y = self.mlp(x)
        pose = y[..., : NUM_JOINTS * 3].reshape(*y.shape[:-1], NUM_JOINTS, 3)
        pose = pose - pose[..., :1, :]
        z = torch.exp(y[..., -1].clamp(-5.0, 5.0))
        xy = (mean + y[..., -3:-1]) * z[..., None]
        return pose, torch.cat([xy, z[..., None]], dim=-1)


def predict(module: LiftingBaseline, batch: dict[str, Any]) -> dict[str, torch.Tensor]:
    """Camera-space joints ``"joints_cam" (B, 2, 22, 3)`` metres (pose placed at the root) and
    ``"root_cam" (B, 2, 3)``, in the batch's person order."""
    pose, root = module(batch["keypoints2d"], batch["K"])
    return {"joints_cam": pose + root[..., None, :], "root_cam": root}


class LiftingBaselineSpec:
    """:class:`~dualhuman_builder.models.base.ModelSpec` of the lifting baseline (module docstring)."""

    name = NAME
    about = ("the pose estimator's sanity baseline: each person's 2D keypoints lifted to camera-space joints and "
             "translation by a small MLP, without the image")

    def default_config(self) -> dict[str, Any]:
        return dict(DEFAULTS)

    def build(self, config: dict[str, Any]) -> nn.Module:
        return LiftingBaseline({**DEFAULTS, **config})

    def phases(self, config: dict[str, Any]) -> list[Phase]:
        c = {**DEFAULTS, **config}
        return [Phase("lift", int(c["steps"]), float(c["lr"]), float(c["weight_decay"]))]

    def make_dataset(self, export_dir: str | Path, split: str, config: dict[str, Any], seed: int):
        """Rendered frames (:class:`~dualhuman_builder.models.images.ImageFrames`, flip and crop jitter in
        training); the image is decoded but not used, so ``size`` is kept small."""
        from dualhuman_builder.models.images import ImageFrames

        c = {**DEFAULTS, **config}
        ds = ImageFrames(export_dir, split, size=int(c["size"]), augment=(split in TRAINING_SPLITS), seed=seed)
        # what the training loop records of its data, where the image dataset does not say it itself
        for key, value in (("num_sequences", len(ds.ids)), ("frames", len(ds)), ("window", 1), ("swapped", []),
                           ("too_short", list(ds.without_renders))):  # fmt: skip
            if not hasattr(ds, key):
                setattr(ds, key, value)
        return ds

    def parameters(self, module: nn.Module, phase: str) -> Iterable[nn.Parameter]:
        if phase != "lift":
            raise ValueError(f"the lifting baseline has one phase 'lift', not {phase!r}")
        return list(module.parameters())

    def losses(self, module: nn.Module, batch: dict[str, Any], phase: str) -> dict[str, torch.Tensor]:
        truth = batch["joints_cam"].float()
        pose, root = module(batch["keypoints2d"], batch["K"])
        pose_l1 = (pose - (truth - truth[..., :1, :])).abs().mean()
        root_l1 = (root - truth[..., 0, :]).abs().mean()
        loss = pose_l1 + float(module.config["root_weight"]) * root_l1
        return {"loss": loss, "pose_l1_m": pose_l1.detach(), "root_l1_m": root_l1.detach()}

    def evaluate(self, module: nn.Module, batches: Iterator[dict[str, Any]], device: torch.device) -> dict[str, float]:
        from dualhuman_builder.models.metrics import pose_errors

        preds, truths = [], []
        for batch in batches:
            preds.append(predict(module, batch)["joints_cam"].detach().float().cpu())
            truths.append(batch["joints_cam"].float().cpu())
        if not preds:
            return {}
        p, t = torch.cat(preds).numpy(), torch.cat(truths).numpy()
        out = {"frames": float(len(p)), **pose_errors(p, t)}
        for k, name in enumerate(("a", "b")):
            for key, v in pose_errors(p[:, k], t[:, k]).items():
                out[f"{name}_{key}"] = v
        return out


register(NAME, LiftingBaselineSpec)

__all__ = ["DEFAULTS", "NAME", "LiftingBaseline", "LiftingBaselineSpec", "lifting_input", "predict"]

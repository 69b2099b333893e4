"""The temporal refinement network after the pose estimator (the Dual-Human paper §3.2): SmoothNet-style
(``cure-lab/SmoothNet``), registered as ``temporal-refiner`` (``dualhuman train temporal-refiner DATASET``).

A per-frame estimator's motion jitters and drifts; this network cleans one person's motion over a
sliding window of ``window`` frames. As SmoothNet does, it treats every dimension of the per-frame
vector as its own time series: a fully connected layer over time (``window`` values -> ``hidden``),
``blocks`` residual blocks (``hidden -> res_hidden -> hidden``, LeakyReLU 0.2, dropout), and a layer back
to ``window`` values, the same weights for every dimension. The result is added to the input (the last
layer starts at zero, so an untrained network is the identity; SmoothNet predicts the output directly).

Representations (``representation``):

- ``"features"`` (default, the paper's): the export's 269-dim motion features per person
  (:func:`~dualhuman_builder.export.features.motion_features` of the window's joints, ``window - 1``
  rows), normalised per dimension by statistics of the first training batches (saved with the
  weights). The refined features are turned back into joints by :func:`recover_joints_torch`, the
  differentiable twin of :func:`~dualhuman_builder.export.features.recover_joints`, so the loss can
  compare joints too.
- ``"joints"``: the 22 joints' positions (66 numbers a frame) less the window's mean root, in metres
  normalised per coordinate: SmoothNet's own input (it smooths positions), kept to compare.

Training (one phase ``smooth``): windows of both people from :class:`~dualhuman_builder.models.data.
InteractionWindows` (each person a sample), corrupted by the reaction prior's visibility-driven noise
(:mod:`~dualhuman_builder.models.reaction_prior.noise`: smooth per-joint errors larger where the
ring of virtual cameras sees the joint less, white jitter, a root offset), as an image estimator's
output would be. Loss: ``feature_weight`` x L1 of the normalised features (features only) +
``position_weight`` x mean joint L1 in metres + ``accel_weight`` x mean L1 of the joints'
acceleration in metres per frame squared (SmoothNet's acceleration term).

Evaluation: on held-out windows corrupted with a seeded draw of the same noise, MPJPE, PA-MPJPE,
translation error (:func:`~dualhuman_builder.models.metrics.pose_errors`) and acceleration error
(:func:`accel_error_mm`) before and after. :func:`refine_motion` refines a whole sequence (windows
with half overlap, blended with triangular weights as :mod:`~.reaction_prior.refine` does).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from dualhuman_builder.export.features import FEATURE_DIM, NUM_JOINTS
from dualhuman_builder.models.base import Phase, register
from dualhuman_builder.models.data import InteractionWindows
from dualhuman_builder.models.motion_torch import recover_joints_torch, window_features
from dualhuman_builder.models.reaction_prior.noise import NoiseModel, corrupt
from dualhuman_builder.models.reaction_prior.representation import Normalizer
from dualhuman_builder.models.reaction_prior.noise import noise_model

NAME = "temporal-refiner"

#: Sized for a CPU (hidden 256, res_hidden 128; a step on 32 windows of both people takes about a quarter of
#: a second); SmoothNet's are hidden 512, res_hidden 256, 3 blocks, dropout 0.5 (``--set hidden=512 ...``).
DEFAULTS: dict[str, Any] = {
    "window": 32,
    "stride": None,
    "representation": "features",
    "hidden": 256,
    "res_hidden": 128,
    "blocks": 3,
    "dropout": 0.1,
    "noise": NoiseModel().as_dict(),
    "feature_weight": 1.0,
    "position_weight": 10.0,
    "accel_weight": 10.0,
    "stats_batches": 16,
    "fps": 20.0,
    "steps": 2000,
    "lr": 1e-3,
    "weight_decay": 5e-4,
    "eval_seed": 0,
}
REPRESENTATIONS = ("features", "joints")


# ----------------------------------------------------------------------------------- representation
def accel(joints: torch.Tensor) -> torch.Tensor:
    """Second differences ``(..., L - 2, J, 3)`` of ``joints (..., L, J, 3)`` along time (per frame squared)."""
    return joints[..., 2:, :, :] - 2.0 * joints[..., 1:-1, :, :] + joints[..., :-2, :, :]


def accel_error_mm(pred: np.ndarray | torch.Tensor, truth: np.ndarray | torch.Tensor) -> float:
    """Acceleration error, mm per frame squared: mean over frames and joints of the distance between the
    second differences of ``pred`` and ``truth`` ``(..., L, 22, 3)`` metres (absolute positions, as
    SmoothNet's ``calculate_accel_error``, which takes the norm of the difference per joint)."""
    p, t = torch.as_tensor(pred, dtype=torch.float64), torch.as_tensor(truth, dtype=torch.float64)
    if p.shape[-3] < 3:
        return float("nan")
    return float((accel(p) - accel(t)).norm(dim=-1).mean() * 1000.0)


# ----------------------------------------------------------------------------------- the network
class _ResBlock(nn.Module):
    def __init__(self, hidden: int, res_hidden: int, dropout: float):
        super().__init__()
        self.body = nn.Sequential(nn.Linear(hidden, res_hidden), nn.LeakyReLU(0.2), nn.Dropout(dropout),
                                  nn.Linear(res_hidden, hidden), nn.LeakyReLU(0.2), nn.Dropout(dropout))  # fmt: skip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


class SmoothNet(nn.Module):
    """Per-dimension temporal network over ``length`` frames: ``(B, length, D) -> (B, length, D)``, the
    input plus the network's correction (module docstring)."""

    def __init__(self, length: int, hidden: int = 512, res_hidden: int = 256, blocks: int = 3, dropout: float = 0.1):
        super().__init__()
        self.length = int(length)
        self.encoder = nn.Sequential(nn.Linear(self.length, hidden), nn.LeakyReLU(0.1), nn.Dropout(dropout))
        self.blocks = nn.Sequential(*[_ResBlock(hidden, res_hidden, dropout) for _ in range(int(blocks))])
        self.decoder = nn.Linear(hidden, self.length)
        nn.init.zeros_(self.decoder.weight)
        nn.init.zeros_(self.decoder.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[1] != self.length:
            raise ValueError(f"SmoothNet of {self.length} frames got {x.shape[1]}")
        y = x.transpose(1, 2)  # (B, D, length): every dimension is a sample
        return x + self.decoder(self.blocks(self.encoder(y))).transpose(1, 2)


class TemporalRefiner(nn.Module):
    """Normaliser + :class:`SmoothNet` over one representation (module docstring); windows of
    ``window`` frames of one person's joints ``(B, L, 22, 3)`` world metres in, the same out."""

    def __init__(self, config: dict[str, Any]):
        super().__init__()
        c = self.config = {**DEFAULTS, **config}
        if c["representation"] not in REPRESENTATIONS:
            raise ValueError(f"representation must be one of {REPRESENTATIONS}, got {c['representation']!r}")
        self.window = int(c["window"])
        if self.window < 4:
            raise ValueError(f"window must be at least 4 frames, got {self.window}")
        self.features = c["representation"] == "features"
        dim, length = (FEATURE_DIM, self.window - 1) if self.features else (NUM_JOINTS * 3, self.window)
        self.norm = Normalizer(dim, int(c["stats_batches"]))
        self.net = SmoothNet(length, int(c["hidden"]), int(c["res_hidden"]), int(c["blocks"]), float(c["dropout"]))

    def encode(self, joints: torch.Tensor, fps: float) -> tuple[torch.Tensor, torch.Tensor]:
        """``(x, centre)``: the representation ``(B, length, D)`` in metres/feature units of windows
        ``joints (B, L, 22, 3)`` and, for joints, the window's mean root ``(B, 1, 1, 3)`` taken out."""
        if self.features:
            return window_features(joints, fps), joints.new_zeros(joints.shape[0], 1, 1, 3)
        centre = joints[:, :, :1].mean(dim=1, keepdim=True)
        return (joints - centre).reshape(*joints.shape[:2], -1), centre

    def decode(self, x: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
        """Joints ``(B, L, 22, 3)`` world metres of a representation (inverse of :meth:`encode`)."""
        if self.features:
            return recover_joints_torch(x)
        return x.reshape(*x.shape[:2], NUM_JOINTS, 3) + centre

    def forward(self, joints: torch.Tensor, fps: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(refined joints (B, L, 22, 3), refined representation, input representation)`` of noisy windows."""
        x, centre = self.encode(joints.float(), fps)
        y = self.norm.inverse(self.net(self.norm(x)))
        return self.decode(y, centre), y, x


def _fps(batch: dict[str, Any], config: dict[str, Any]) -> float:
    f = batch.get("fps")
    if torch.is_tensor(f) and f.numel():
        return float(f.reshape(-1)[0])
    return float(config["fps"])


def _people(batch: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
    """Both people's windows as one batch ``(2B, L, 22, 3)``, and their visibility ``(2B, L, 22)``."""
    j = torch.cat([batch["joints_actor"], batch["joints_reactor"]]).float()
    v = torch.cat([batch["visibility_actor"], batch["visibility_reactor"]]).float()
    return j, v


class WindowsWithFps(InteractionWindows):
    """:class:`~dualhuman_builder.models.data.InteractionWindows` whose batches also carry ``"fps" (B,)``,
    the export's frame rate (the features' facing smoothing and contact speed depend on it)."""

    def batch(self, indices) -> dict[str, Any]:
        out = super().batch(indices)
        out["fps"] = torch.full((len(out["seq_id"]),), float(self.manifest.get("fps", DEFAULTS["fps"])))
        return out


class TemporalRefinerSpec:
    """:class:`~dualhuman_builder.models.base.ModelSpec` of the temporal refinement network (module docstring)."""

    name = NAME
    about = ("SmoothNet-style temporal refinement of one person's motion (the 269-dim features by default), "
             "trained on motion windows corrupted like an image estimator's output; runs after `dualhuman estimate`")

    def default_config(self) -> dict[str, Any]:
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in DEFAULTS.items()}

    def build(self, config: dict[str, Any]) -> nn.Module:
        return TemporalRefiner({**DEFAULTS, **config})

    def phases(self, config: dict[str, Any]) -> list[Phase]:
        c = {**DEFAULTS, **config}
        return [Phase("smooth", int(c["steps"]), float(c["lr"]), float(c["weight_decay"]))]

    def make_dataset(self, export_dir: str | Path, split: str, config: dict[str, Any], seed: int) -> WindowsWithFps:
        c = {**DEFAULTS, **config}
        return WindowsWithFps(export_dir, split, window=int(c["window"]), stride=c["stride"], visibility=True, seed=seed)

    def parameters(self, module: nn.Module, phase: str) -> Iterable[nn.Parameter]:
        if phase != "smooth":
            raise ValueError(f"the temporal refiner has one phase 'smooth', not {phase!r}")
        return list(module.net.parameters())

    def losses(self, module: nn.Module, batch: dict[str, Any], phase: str) -> dict[str, torch.Tensor]:
        cfg = module.config
        fps = _fps(batch, cfg)
        clean, vis = _people(batch)
        with torch.no_grad():
            noisy = corrupt(clean, vis.to(clean), noise_model(cfg))
            target, _ = module.encode(clean, fps)
            if module.training:
                module.norm.observe(target)
        refined, y, _ = module(noisy, fps)
        out: dict[str, torch.Tensor] = {}
        loss = clean.new_zeros(())
        if module.features:
            feat = (module.norm(y) - module.norm(target)).abs().mean()
            out["feature_l1"] = feat.detach()
            loss = loss + float(cfg["feature_weight"]) * feat
        pos = (refined - clean).abs().mean()
        acc = (accel(refined) - accel(clean)).abs().mean()
        out["position_l1_m"], out["accel_l1_m"] = pos.detach(), acc.detach()
        out["loss"] = loss + float(cfg["position_weight"]) * pos + float(cfg["accel_weight"]) * acc
        return out

    def evaluate(self, module: nn.Module, batches: Iterator[dict[str, Any]], device: torch.device) -> dict[str, float]:
        from dualhuman_builder.models.metrics import pose_errors

        cfg = module.config
        g = torch.Generator(device=device).manual_seed(int(cfg["eval_seed"]))
        truth, before, after = [], [], []
        for batch in batches:
            clean, vis = _people(batch)
            clean, vis = clean.to(device), vis.to(device)
            noisy = corrupt(clean, vis, noise_model(cfg), generator=g)
            refined, _, _ = module(noisy, _fps(batch, cfg))
            truth.append(clean.cpu())
            before.append(noisy.cpu())
            after.append(refined.detach().float().cpu())
        if not truth:
            return {}
        t, b, a = torch.cat(truth).numpy(), torch.cat(before).numpy(), torch.cat(after).numpy()
        out: dict[str, float] = {"windows": float(len(t))}
        for tag, x in (("before", b), ("after", a)):
            for k, v in pose_errors(x, t).items():
                out[f"{tag}_{k}"] = v
            out[f"{tag}_accel_mm"] = accel_error_mm(x, t)
        return out


# ----------------------------------------------------------------------------------- whole sequences
def refine_motion(module: TemporalRefiner, joints: np.ndarray, fps: float, device: str | torch.device = "cpu",
                  chunk: int = 256) -> np.ndarray:  # fmt: skip
    """One person's refined joints ``(T, 22, 3)`` float32 world metres from ``joints (T, 22, 3)``: windows of
    the module's length every half window (and one ending on the last frame), blended with the triangular
    weights of :func:`~.reaction_prior.refine.blend_weights`; a sequence shorter than a window is padded
    with its last frame and cropped after."""
    from dualhuman_builder.models.reaction_prior.refine import (
        blend_weights,
        window_starts,
    )

    j = np.asarray(joints, np.float32)
    T, L = len(j), module.window
    if T < 2:
        return j.copy()
    if T < L:
        j = np.concatenate([j, np.repeat(j[-1:], L - T, axis=0)])
    starts = window_starts(len(j), L)
    acc = np.zeros(j.shape, np.float64)
    wsum = np.zeros(len(j), np.float64)
    w = blend_weights(L)
    was = module.training
    module.eval()
    try:
        with torch.no_grad():
            for c0 in range(0, len(starts), chunk):
                part = starts[c0 : c0 + chunk]
                x = torch.from_numpy(np.stack([j[s : s + L] for s in part])).to(device)
                out = module(x, fps)[0].cpu().numpy().astype(np.float64)
                for s, o in zip(part, out):
                    acc[s : s + L] += w[:, None, None] * o
                    wsum[s : s + L] += w
    finally:
        module.train(was)
    return (acc / wsum[:, None, None])[:T].astype(np.float32)


register(NAME, TemporalRefinerSpec)

__all__ = [
    "DEFAULTS",
    "NAME",
    "SmoothNet",
    "TemporalRefiner",
    "TemporalRefinerSpec",
    "WindowsWithFps",
    "accel_error_mm",
    "recover_joints_torch",
    "refine_motion",
]  # fmt: skip

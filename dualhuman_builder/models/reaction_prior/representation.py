"""The motion representation of the reaction prior: both people in one window-canonical frame.

A window of ``L`` frames of two people, joints ``(L, 22, 3)`` world metres (Y up), is moved into the
frame of the **actor at the window's first frame**: the actor's root (pelvis, joint 0) is put at the
origin on the floor plane (x and z subtracted; heights are kept, y = 0 stays the floor) and the frame is
turned about +Y so that the actor faces +Z (facing from hips and shoulders, as
:func:`dualhuman_builder.export.features.facing_yaw` defines it). The reactor is moved by the same
transform, so both people share one frame: the reactor's placement relative to the actor is part of
its motion, and its translation error is measurable.

Two representations of a person's window in that frame (config ``representation``):

- ``"joints"`` (default): each frame is the 66 numbers of the 22 joints. The refinement's data term
  then compares positions directly.
- ``"features"``: the paper's: the 269-dim HumanML3D features (+6) of
  :func:`dualhuman_builder.export.features.motion_features`, computed on the window **already in the
  actor's window frame**, so a window of ``L`` frames gives ``L - 1`` rows and the reactor's dims
  [263:269] (its own initial facing and floor point) carry its placement relative to the actor,
  which per-person canonical features would otherwise remove.
  :func:`~dualhuman_builder.models.motion_torch.recover_joints_torch` is the differentiable inverse,
  which gives the ``L`` frames back.

Either is normalised per number by a mean and standard deviation computed from the training windows
(:class:`Normalizer`, kept as module buffers so that they travel with every checkpoint).
"""

from __future__ import annotations

import torch
from torch import nn

from dualhuman_builder.export.features import FEATURE_DIM

NUM_JOINTS = 22
FEATS = NUM_JOINTS * 3
#: hips and shoulders (right, left, right, left) that give the facing, as in the export's features
FACE_JOINTS = (2, 1, 17, 16)
#: smallest standard deviation a number is scaled by (metres for joints): a number that hardly varies
#: in the training windows (a foot's height at rest, a foot contact always on) is not blown up into noise
MIN_STD_M = 0.01
#: the representations (module docstring) and the numbers per row of each
REPRESENTATIONS = {"joints": FEATS, "features": FEATURE_DIM}


def rotate_y(v: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotate ``v (B, ..., 3)`` by ``angle (B,)`` radians about +Y (+Z goes to ``(sin, 0, cos)``)."""
    shape = (angle.shape[0],) + (1,) * (v.dim() - 2)
    c, s = torch.cos(angle).view(shape), torch.sin(angle).view(shape)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return torch.stack([c * x + s * z, y, -s * x + c * z], dim=-1)


def window_frame(actor: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(origin (B, 3), yaw (B,))`` of the canonical frame of windows ``actor (B, L, 22, 3)``: the
    actor's root on the floor plane at frame 0 and its facing yaw there (0 = +Z)."""
    j0 = actor[:, 0]
    across = (j0[:, FACE_JOINTS[0]] - j0[:, FACE_JOINTS[1]]) + (j0[:, FACE_JOINTS[2]] - j0[:, FACE_JOINTS[3]])
    yaw = torch.atan2(across[:, 2], -across[:, 0])  # forward = up x across; a degenerate facing gives 0
    origin = torch.stack([j0[:, 0, 0], torch.zeros_like(j0[:, 0, 0]), j0[:, 0, 2]], dim=-1)
    return origin, yaw


def to_canonical(joints: torch.Tensor, origin: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """World joints ``(B, L, 22, 3)`` -> the window frame given by ``origin``, ``yaw``."""
    return rotate_y(joints - origin[:, None, None, :], -yaw)


def to_world(joints: torch.Tensor, origin: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`to_canonical`."""
    return rotate_y(joints, yaw) + origin[:, None, None, :]


def canonical_pair(actor: torch.Tensor, reactor: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Both people of windows ``(B, L, 22, 3)`` in the actor's window frame:
    ``(actor, reactor, origin, yaw)``."""
    origin, yaw = window_frame(actor)
    return to_canonical(actor, origin, yaw), to_canonical(reactor, origin, yaw), origin, yaw


class Normalizer(nn.Module):
    """Per-coordinate mean and standard deviation of canonical joints, estimated from the first
    ``batches`` training batches (running sums in float64 buffers, then frozen), so the statistics
    are computed from the training data and saved with every checkpoint.

    ``ready`` (buffer) counts the batches seen; before any, the transform is the identity.
    """

    def __init__(self, feats: int = FEATS, batches: int = 16):
        super().__init__()
        self.batches = int(batches)
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("total", torch.zeros(feats, dtype=torch.float64))
        self.register_buffer("total_sq", torch.zeros(feats, dtype=torch.float64))
        self.register_buffer("ready", torch.zeros((), dtype=torch.int64))
        self.register_buffer("mean", torch.zeros(feats))
        self.register_buffer("std", torch.ones(feats))

    @torch.no_grad()
    def observe(self, x: torch.Tensor) -> None:
        """Add frames ``x (..., F)`` metres to the statistics while fewer than ``batches`` were seen."""
        if int(self.ready) >= self.batches:
            return
        flat = x.detach().reshape(-1, x.shape[-1]).to(torch.float64)
        self.count += flat.shape[0]
        self.total += flat.sum(0)
        self.total_sq += (flat * flat).sum(0)
        self.ready += 1
        mean = self.total / self.count
        var = (self.total_sq / self.count - mean * mean).clamp_min(0.0)
        self.mean.copy_(mean.to(self.mean.dtype))
        self.std.copy_(var.sqrt().clamp_min(MIN_STD_M).to(self.std.dtype))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Metres ``(..., F)`` -> normalised units."""
        return (x - self.mean) / self.std

    def inverse(self, x: torch.Tensor) -> torch.Tensor:
        """Normalised units ``(..., F)`` -> metres."""
        return x * self.std + self.mean


def flat(joints: torch.Tensor) -> torch.Tensor:
    """``(B, L, 22, 3)`` -> ``(B, L, 66)``."""
    return joints.reshape(*joints.shape[:-2], FEATS)


def unflat(x: torch.Tensor) -> torch.Tensor:
    """``(B, L, 66)`` -> ``(B, L, 22, 3)``."""
    return x.reshape(*x.shape[:-1], NUM_JOINTS, 3)


def rows(representation: str, length: int) -> int:
    """Rows per window of ``length`` frames: ``length`` for joints, ``length - 1`` for features
    (a feature row describes a frame and the step after it)."""
    return int(length) - (representation == "features")


def check_fps(config: dict, fps: float, where: str) -> None:
    """Refuse data at ``fps`` for a prior whose ``config`` (complete, defaults merged) computes its
    features at another rate (their contacts and facing smoothing depend on it); a prior on joints
    takes any rate."""
    from dualhuman_builder.errors import DualhumanError

    if config["representation"] == "features" and abs(float(fps) - float(config["features_fps"])) > 1e-6:
        want = float(config["features_fps"])
        raise DualhumanError(f"{where} is at {float(fps):g} fps, but this reaction prior's features are computed at "
                             f"{want:g} fps",
                             fix=f"train the prior with --set features_fps={float(fps):g}, or use data at {want:g} fps")  # fmt: skip

"""Torch twins of the export's motion features (:mod:`dualhuman_builder.export.features`), shared by
the models that learn in that representation (the temporal network, the reaction prior).

:func:`window_features` computes the features of a batch of windows with the export's own numpy code
(inputs, never optimised, so no gradient is needed and the definition cannot drift);
:func:`recover_joints_torch` is the batched, differentiable inverse, so a loss or a test-time
optimisation can act on the joints the features give back.
"""

from __future__ import annotations

import numpy as np
import torch

from dualhuman_builder.export.features import NUM_JOINTS, FeatureLayout, motion_features


def rotate_y(v: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotate ``v (..., 3)`` by ``angle`` (broadcast against ``v[..., 0]``) radians about +Y (+Z goes to
    ``(sin, 0, cos)``), as the export's features do."""
    c, s = torch.cos(angle), torch.sin(angle)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return torch.stack([c * x + s * z, y, -s * x + c * z], dim=-1)


def recover_joints_torch(features: torch.Tensor, world_from: str = "first") -> torch.Tensor:
    """World joints ``(B, N + 1, 22, 3)`` of features ``(B, N, 269)``: the batched, differentiable
    :func:`~dualhuman_builder.export.features.recover_joints` (same integration of the facing and the
    root velocity, same last frame). The world transform (dims [263:268], constant over a window's
    rows in data) is row 0's, as there, with ``world_from="first"``, or the mean over the rows with
    ``"mean"``: for decoded features, whose rows each estimate it."""
    if world_from not in ("first", "mean"):
        raise ValueError(f"world_from must be 'first' or 'mean', got {world_from!r}")
    f = features
    B, n = f.shape[:2]
    psi = torch.cat([f.new_zeros(B, 1), -2.0 * torch.cumsum(f[..., 0], dim=1)], dim=1)  # (B, N+1)
    vel = torch.stack([f[..., 1], torch.zeros_like(f[..., 1]), f[..., 2]], dim=-1)
    root_xz = torch.cat([f.new_zeros(B, 1, 3), torch.cumsum(rotate_y(vel, psi[:, 1:]), dim=1)], dim=1)
    flat = root_xz[:, :n] * root_xz.new_tensor([1.0, 0.0, 1.0])
    ric = f[..., FeatureLayout.RIC].reshape(B, n, NUM_JOINTS - 1, 3)
    rest = rotate_y(ric, psi[:, :n, None]) + flat[:, :, None]
    root = torch.stack([flat[..., 0], f[..., 3], flat[..., 2]], dim=-1)
    frames = torch.cat([root[:, :, None], rest], dim=2)  # (B, N, 22, 3)
    step = f[:, -1, FeatureLayout.JOINT_VELOCITIES].reshape(B, NUM_JOINTS, 3)
    last = frames[:, -1] + rotate_y(step, psi[:, n - 1, None])
    out = torch.cat([frames, last[:, None]], dim=1)
    world = f[:, 0, 263:268] if world_from == "first" else f[:, :, 263:268].mean(dim=1)
    yaw0 = torch.atan2(world[:, 0], world[:, 1])
    return rotate_y(out, yaw0[:, None, None]) + world[:, None, None, 2:5]


def window_features(joints: torch.Tensor, fps: float) -> torch.Tensor:
    """Features ``(B, L - 1, 269)`` of windows ``joints (B, L, 22, 3)`` world metres (each window its own
    canonical frame, computed in numpy by the export's own code; not differentiable)."""
    arr = joints.detach().to("cpu", torch.float64).numpy()
    out = np.stack([motion_features(w, float(fps)) for w in arr])
    return torch.from_numpy(out).to(joints.device, torch.float32)

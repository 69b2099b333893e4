"""Conventions shared by every stage, stated once.

Units
    metres, seconds, radians inside the code. Times of samples are integer nanoseconds (``int64``):
    ``device_time_ns`` is the device's own clock, ``host_time_ns`` the host's monotonic clock at
    receipt. Neither is ever dropped: the sync stage needs both.

World frame
    right-handed, **+Y up**, metres. A body at identity root orientation stands upright and faces
    **+Z**, with its left side towards **+X** (the SMPL / HumanML3D convention). The floor is the
    plane y = 0.

Rotations
    quaternions are stored **(x, y, z, w)** (scalar last, as in roma and scipy) and rotation
    vectors as axis * angle in radians. Arrays of rotations have shape ``(..., 4)`` or
    ``(..., 3, 3)``.

Conversions at the edges
    Xsens MVN's quaternion stream and anny's vertices are **Z-up**. Converting a Z-up vector to
    our Y-up world is the rotation ``(x, y, z) -> (x, z, -y)`` (-90 degrees about X), never an axis
    swap: a swap mirrors meshes and flips triangle winding. :data:`ZUP_TO_YUP` is that rotation.

Cameras
    intrinsics ``K`` and world-to-camera ``R | t`` in the OpenCV convention (+X right, +Y down,
    +Z forward); the renderer converts to Mitsuba's convention internally.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # torch is only needed when a tensor is passed in; capture code never imports it
    import torch

#: Rotation taking Z-up coordinates (MVN stream, anny) to our Y-up world: (x, y, z) -> (x, z, -y).
ZUP_TO_YUP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

#: Gravity in the world frame, m/s^2.
GRAVITY = np.array([0.0, -9.80665, 0.0])

#: Up axis index of the world frame.
UP_AXIS = 1


def _is_tensor(x) -> bool:
    """Whether ``x`` is a torch tensor, without importing torch when nobody has."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def zup_to_yup_points(points: np.ndarray | torch.Tensor):
    """Z-up points or vectors ``(..., 3)`` to the Y-up world frame (a rotation, not a mirror)."""
    if _is_tensor(points):
        import torch

        return torch.stack([points[..., 0], points[..., 2], -points[..., 1]], dim=-1)
    points = np.asarray(points)
    return np.stack([points[..., 0], points[..., 2], -points[..., 1]], axis=-1)


def yup_to_zup_points(points: np.ndarray | torch.Tensor):
    """Inverse of :func:`zup_to_yup_points`: (x, y, z) -> (x, -z, y)."""
    if _is_tensor(points):
        import torch

        return torch.stack([points[..., 0], -points[..., 2], points[..., 1]], dim=-1)
    points = np.asarray(points)
    return np.stack([points[..., 0], -points[..., 2], points[..., 1]], axis=-1)

"""Wire formats of the capture devices: encoders (typed samples -> the bytes devices send, used
by the simulated devices) and decoders (bytes -> typed samples, used by the capture sources).

One module per device family, each following byte for byte the published specification or
open-source driver its docstring names:

* :mod:`.mvn` — Xsens MVN real-time network stream ("MXTP" UDP datagrams, big-endian): pose
  quaternions (type 02), meta data (12), scale (13), time code (25); several characters on one
  port; large messages split over several datagrams.
* :mod:`.xbus` — Xsens MTi "Xbus" serial frames (MTData2 records, configuration messages) and
  :class:`~.xbus.SimulatedMti`, the device's side of the configuration dialogue.
* :mod:`.mti_can` — MTi-600 CAN frames (big-endian scaled int16 signals) as python-can messages.
* :mod:`.vive_hid` — the VIVE tracker's raw USB HID IMU report (three samples per report).
* :mod:`.vive_udp` — our tracker bridge datagram (little-endian), the format an OpenVR or
  libsurvive bridge sends us.

Frames at the edge: our samples are in the **Y-up** world (:mod:`dualhuman_builder.conventions`);
MVN type 02/13 and the MTi's earth frame are **Z-up**. Encoders rotate with the inverse of
:data:`~dualhuman_builder.conventions.ZUP_TO_YUP`; orientations are multiplied on the left only,
because a segment's or sensor's own axes are the device's and do not change with the world frame.
All three Xsens formats put the quaternion's scalar first (w, x, y, z); our samples store it last.
"""

from __future__ import annotations

import numpy as np

_H = np.sqrt(0.5)


def to_zup_wxyz(q_xyzw) -> np.ndarray:
    """World-frame orientations ``(..., 4)`` (x, y, z, w), Y-up world -> the same orientations in
    a Z-up world as ``(..., 4)`` (w, x, y, z), float64.

    ``R_zup = ZUP_TO_YUP^T @ R_yup``: the quaternion of ``ZUP_TO_YUP^T`` (+90 degrees about X)
    times ``q`` (Hamilton product). The sign of ``q`` is kept (no canonical hemisphere).
    """
    q = np.asarray(q_xyzw, dtype=np.float64)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([_H * (w - x), _H * (x + w), _H * (y - z), _H * (z + y)], axis=-1)


def check_unit_quaternions(q, what: str, tol: float = 1e-3) -> None:
    """Raise ``ValueError`` unless every quaternion of ``q (..., 4)`` is finite with norm 1 +- tol."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1:] != (4,):
        raise ValueError(f"{what} must have shape (..., 4), got {q.shape}")
    n = np.linalg.norm(q, axis=-1)
    bad = ~np.isfinite(n) | (np.abs(n - 1.0) > tol)
    if np.any(bad):
        at = tuple(int(i) for i in np.argwhere(np.atleast_1d(bad))[0])
        raise ValueError(f"{what} is not a finite unit quaternion at {at} (norm {np.atleast_1d(n)[at]:.6g})")


def check_finite(a, what: str) -> np.ndarray:
    """``a`` as float64; ``ValueError`` naming ``what`` if any entry is NaN or infinite."""
    arr = np.asarray(a, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} holds non-finite values: {arr.tolist()}")
    return arr

"""Smooth timing for keyframed motion: minimum-jerk easing, keyframe tracks and footsteps.

Times are seconds; ``t`` arrays hold the frame times. Keyframe values may be scalars or vectors;
between two keys the value follows a minimum-jerk curve (zero velocity and acceleration at both
keys), the profile of human point-to-point movements (Flash & Hogan 1985).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def minjerk(s: np.ndarray) -> np.ndarray:
    """Minimum-jerk easing of ``s`` in [0, 1] (clipped): 10 s^3 - 15 s^4 + 6 s^5."""
    s = np.clip(s, 0.0, 1.0)
    return s**3 * (10 - 15 * s + 6 * s * s)


def keyframes(t: np.ndarray, times, values) -> np.ndarray:
    """Values at times ``t`` of a track through ``(times[k], values[k])`` with minimum-jerk
    segments; constant before the first key and after the last. Returns ``(len(t),) + value shape``."""
    times = np.asarray(times, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if np.any(np.diff(times) <= 0):
        raise ValueError(f"key times must increase: {times}")
    k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 1)
    k1 = np.minimum(k + 1, len(times) - 1)
    span = np.where(k1 > k, times[k1] - times[k], 1.0)
    s = minjerk((t - times[k]) / span)
    s = s.reshape(s.shape + (1,) * (values.ndim - 1))
    return values[k] + s * (values[k1] - values[k])


def window(t: np.ndarray, start: float, end: float, ramp: float) -> np.ndarray:
    """Weight rising from 0 to 1 over ``[start, start + ramp]`` and back to 0 over
    ``[end - ramp, end]`` (minimum-jerk ramps)."""
    return minjerk((t - start) / ramp) * (1.0 - minjerk((t - (end - ramp)) / ramp))


@dataclass
class Step:
    """One footstep: the foot lifts at ``t0``, lands at ``t1`` on ``to`` (x, z) with yaw ``heading``."""

    foot: str
    t0: float
    t1: float
    to: tuple[float, float]
    heading: float
    lift: float = 0.05


def foot_track(t: np.ndarray, start_xz, start_heading: float, height: float, steps: list[Step], foot: str):
    """Ankle positions ``(T, 3)``, yaw ``(T,)`` and a stance mask ``(T,)`` (True while the foot is
    planted) for one foot following ``steps`` (only those of ``foot`` are used, in time order)."""
    pos = np.tile([start_xz[0], height, start_xz[1]], (len(t), 1)).astype(np.float64)
    yaw = np.full(len(t), float(start_heading))
    stance = np.ones(len(t), dtype=bool)
    cur_xz, cur_yaw = np.asarray(start_xz, dtype=np.float64), float(start_heading)
    for st in sorted((s for s in steps if s.foot == foot), key=lambda s: s.t0):
        s = (t - st.t0) / (st.t1 - st.t0)
        swing = (s > 0) & (s < 1)
        after = s >= 1
        e = minjerk(s)
        to = np.asarray(st.to, dtype=np.float64)
        xz = cur_xz + e[:, None] * (to - cur_xz)
        sel = swing | after
        pos[sel, 0], pos[sel, 2] = xz[sel, 0], xz[sel, 1]
        pos[swing, 1] = height + st.lift * np.sin(np.pi * s[swing])
        yaw[sel] = cur_yaw + e[sel] * _wrap(st.heading - cur_yaw)
        stance[swing] = False
        cur_xz, cur_yaw = to, cur_yaw + _wrap(st.heading - cur_yaw)
    return pos, yaw, stance


def _wrap(a: float) -> float:
    return (a + np.pi) % (2 * np.pi) - np.pi

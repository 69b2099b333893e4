"""Piecewise-linear functions of time on evenly spaced knots.

A value at time ``t`` is the linear interpolation of the two knots around it (hat-function
weights); :class:`Knots` locates samples on the knots and builds the banded normal equations of a
weighted least-squares fit, :func:`at_knots` evaluates knot values at located samples. The mount
calibration models the suit's heading and position drift this way (:mod:`.mount`).
"""

from __future__ import annotations

import math

import numpy as np


class Knots:
    """Evenly spaced knots over ``[t0, t1]`` (spacing at most ``spacing``) and the hat-function
    weights of times on them."""

    def __init__(self, t0: float, t1: float, spacing: float):
        span = t1 - t0
        self.n = max(2, math.ceil(span / spacing - 1e-9) + 1)
        self.t = np.linspace(t0, t1, self.n)
        self.step = span / (self.n - 1)
        self.t0 = t0

    def locate(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = (times - self.t0) / self.step
        j = np.clip(np.floor(x).astype(np.int64), 0, self.n - 2)
        u = np.clip(x - j, 0.0, 1.0)
        return j, u

    def normal(self, j, u, w, y=None):
        """Banded normal matrix (diag, off1) of ``sum w (B c - y)^2`` and its right-hand side."""
        n = self.n
        diag = np.bincount(j, w * (1 - u) ** 2, n) + np.bincount(j + 1, w * u * u, n)
        off1 = np.bincount(j, w * u * (1 - u), n)[: n - 1]
        rhs = None
        if y is not None:
            rhs = np.bincount(j, w * (1 - u) * y, n) + np.bincount(j + 1, w * u * y, n)
        return diag, off1, rhs


def at_knots(values: np.ndarray, j: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Linear interpolation of knot ``values (J, ...)`` at samples located by :meth:`Knots.locate`
    (knot ``j (T,)``, fraction ``u (T,)``): ``(T, ...)``."""
    u = u.reshape(u.shape + (1,) * (values.ndim - 1))
    return values[j] * (1 - u) + values[j + 1] * u


"""The coincidence guard: a push apart for two bodies on the same spot.

Identical bodies have every vertex on the other's surface, so every depth is 0, and no symmetric
penetration measure can separate them (at identical bodies its gradient with respect to a equals the
one with respect to b). So where the centroids of the guard vertices of a and b are closer than
``guard_m`` the frame also pays ``weight * (1 - |dc| / guard_m)`` (``dc``: b's centroid minus a's),
whose gradient pushes them apart along ``dc`` (world +X when they coincide).

The guard vertices should be ones whose centroids coincide only when the bodies do: the fitter passes
the torsos' (:func:`~dualhuman_builder.fit.skeleton.torso_vertices`), since arms wrapped round a
partner pull whole-body centroids together in a close hug
(``docs/decisions/0014-hand-openings-and-torso-guard.md``).
"""

from __future__ import annotations

import numpy as np
import torch


class CoincidenceGuard:
    """The guard at distance ``guard_m`` (metres) and weight ``weight`` (dimensionless, >= 0; 0: off),
    over ``vertices``: ``(G,)`` vertex indices, or None for every vertex."""

    def __init__(self, guard_m: float, weight: float, vertices=None):
        self.guard_m = float(guard_m)
        self.weight = float(weight)
        gv = None if vertices is None else np.unique(np.asarray(vertices, dtype=np.int64).ravel())
        if gv is not None and (len(gv) == 0 or gv.min() < 0):
            raise ValueError("guard_vertices must be a non-empty list of vertex indices")
        #: (G,) int64 vertex indices, sorted, whose centroids the guard compares; None: all
        self.vertices = gv
        self._idx = None if gv is None else torch.as_tensor(gv)  # moved to the vertices' device on use

    def moves_with(self, moving: np.ndarray) -> bool:
        """Whether a move of the vertices ``moving`` (``(V,)`` bool) can change the guard."""
        return bool(moving.any()) if self._idx is None else bool(moving[self._idx.numpy()].any())

    def frames(self, va: torch.Tensor, vb: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
        """Frames ``(n,)`` int64 of the batch ``va``, ``vb`` ``(B, V, 3)`` (metres, detached) where the
        guard is on: ``active`` (``(B,)`` bool) and the guard vertices' centroids closer than ``guard_m``."""
        V = va.shape[1]
        if self.weight == 0:
            return torch.zeros(0, dtype=torch.int64, device=va.device)
        if self._idx is None:
            sel = slice(None)
        elif self.vertices[-1] >= V:  # sorted: the last is the largest
            raise ValueError(f"guard_vertices index {int(self.vertices[-1])} is out of range for {V} vertices")
        else:
            sel = self._idx.to(va.device)
        on = active & ((vb[:, sel].mean(dim=1) - va[:, sel].mean(dim=1)).norm(dim=1) < self.guard_m)
        return torch.nonzero(on).flatten()

    def loss(self, frames: torch.Tensor, B: int, V: int, dev, dtype, points) -> torch.Tensor:
        """``weight * relu(1 - |dc| / guard_m)`` ``(B,)`` on ``frames`` (0 elsewhere, where it is 0 with a
        zero gradient anyway), the centroids read through ``points(body, frames, vertices) -> (M, 3)``
        with their gradient; the push direction ``dc / |dc|`` is held."""
        out = torch.zeros(B, device=dev, dtype=dtype)
        if not len(frames):
            return out
        frames = frames.to(dev)
        gv = torch.arange(V, device=dev) if self._idx is None else self._idx.to(dev)
        G = len(gv)
        f = frames.repeat_interleave(G)
        v = gv.repeat(len(frames))
        ca, cb = (points(body, f, v).reshape(len(frames), G, 3).mean(dim=1) for body in (0, 1))
        delta = cb - ca  # (n, 3)
        with torch.no_grad():
            dist = delta.norm(dim=1, keepdim=True)
            ex = torch.zeros_like(delta)
            ex[:, 0] = 1.0
            u = torch.where(dist > 1e-9, delta / dist.clamp_min(1e-20), ex)
        proj = (delta * u).sum(dim=1)
        g = self.weight * torch.relu(1.0 - proj / self.guard_m)
        return out.index_put((frames,), g.to(out.dtype))

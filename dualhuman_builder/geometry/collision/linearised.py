"""Held contacts: the collision term located once and evaluated many times.

An optimiser's line search evaluates the term many times on bodies that move by millimetres, and
locating the contacts (whole meshes posed, closest points queried) is most of its cost. So the
contacts are located once (:meth:`~.term.CollisionTerm.linearise`): every vertex inside the other
body, or outside it within a margin, with its closest triangle, barycentric weights and the
obstacle's outward normal ``m`` there. Each evaluation (:meth:`~.term.CollisionTerm.linear_loss`)
re-reads only their positions and measures ``depth = (c - p) . m`` against the plane held at the
closest point: the first-order (point-to-plane) expansion of the signed depth, exact in value and
gradient where it was located. Vertices that cross in from beyond the margin are missed until the
next :meth:`~.term.CollisionTerm.linearise`, which the caller runs after each optimiser step.
Why and where it stalls: ``docs/decisions/0016-held-contacts.md``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from dualhuman_builder.geometry.collision.depth import outward_normals
from dualhuman_builder.geometry.collision.guard import CoincidenceGuard
from dualhuman_builder.geometry.collision.locate import Contacts


@dataclass
class Linearised:
    """The collision term located once, for many evaluations.

    ``contacts``: the located vertices (``depth`` metres, negative outside); ``normals (M, 3)``
    float64, the outward normal ``m`` at each; ``guard (n,)`` int64 tensor, frames where the
    coincidence guard is on; ``B``, ``V`` the batch; ``max_depth_m``, ``share``, ``penetrating``,
    ``active`` ``(B,)`` numpy: the diagnostics of :meth:`~.term.CollisionTerm.penetration` at the
    located bodies.
    """

    contacts: Contacts
    normals: np.ndarray
    guard: torch.Tensor
    B: int
    V: int
    max_depth_m: np.ndarray
    share: np.ndarray
    penetrating: np.ndarray
    active: np.ndarray

    def subset(self, frames) -> Linearised:
        """The same contacts restricted to the batch rows ``frames`` (distinct ints), renumbered
        ``0..len(frames)-1`` in that order."""
        frames = np.asarray(frames, np.int64).ravel()
        if len(np.unique(frames)) != len(frames) or (len(frames) and (frames.min() < 0 or frames.max() >= self.B)):
            raise ValueError(f"frames must be distinct rows of the batch of {self.B}")
        row = np.full(self.B, -1, np.int64)
        row[frames] = np.arange(len(frames))
        c = self.contacts
        keep = row[c.frame] >= 0
        sub = c.select(keep, frame=row[c.frame[keep]])
        g = torch.as_tensor(row, device=self.guard.device)[self.guard]
        return Linearised(contacts=sub, normals=self.normals[keep], guard=g[g >= 0], B=len(frames), V=self.V,
                          max_depth_m=self.max_depth_m[frames], share=self.share[frames],
                          penetrating=self.penetrating[frames], active=self.active[frames])  # fmt: skip

    def moving_only(self, moving: np.ndarray, obstacle_faces: np.ndarray, guard: CoincidenceGuard) -> Linearised:
        """The contacts whose held depth changes when only the vertices ``moving`` (``(V,)`` bool, the
        same in both bodies) move: their query vertex or a corner of their triangle (a row of
        ``obstacle_faces``) is among them. The guard frames are kept unless ``guard`` does not move with
        them. The held loss of the answer differs from this one's by a constant per frame over such a
        move: the same gradient, fewer points to read."""
        moving = np.asarray(moving, bool)
        if moving.shape != (self.V,):
            raise ValueError(f"moving must be a ({self.V},) bool mask, got shape {moving.shape}")
        c = self.contacts
        keep = moving[c.vert] | moving[obstacle_faces[c.face]].any(axis=1)
        kept_guard = self.guard if guard.moves_with(moving) else self.guard[:0]
        return dataclasses.replace(self, contacts=c.select(keep), normals=self.normals[keep], guard=kept_guard)


def held_normals(c: Contacts, va: torch.Tensor, vb: torch.Tensor, obstacle_faces: np.ndarray) -> np.ndarray:
    """The obstacle's outward normal ``(M, 3)`` float64 at each contact of ``c`` on the bodies ``va``,
    ``vb`` ``(B, V, 3)`` (detached; read at the contacts only, in float64), as
    :func:`~.depth.outward_normals` finds it (inside: along ``c - p``; outside: against it)."""
    f, side = torch.as_tensor(c.frame), torch.as_tensor(c.side)
    A, Bv = va.cpu(), vb.cpu()
    tri = torch.as_tensor(obstacle_faces[c.face])
    q = torch.where((side == 0)[:, None], Bv[f, torch.as_tensor(c.vert)], A[f, torch.as_tensor(c.vert)]).double()
    x = torch.where((side == 0)[:, None, None], A[f[:, None], tri], Bv[f[:, None], tri]).double()
    diff = (torch.as_tensor(c.bary, dtype=torch.float64)[:, :, None] * x).sum(dim=1) - q
    return outward_normals(diff, x, inside=torch.as_tensor(np.asarray(c.depth) > 0)).numpy()

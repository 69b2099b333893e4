"""anny's hands: the palm's axes and the *open hand*, the pose a hand takes flat on a surface.

An inertial suit measures the hand segment but not the fingers, so the fitter keeps anny's relaxed
rest fingers unless the bodies touch; a palm pressed on a partner's back is flat, though, and the
relaxed fingers (the thumb most: it stands ~3 cm out of the palm plane) would sit inside the
partner. :func:`open_hand` gives, per hand, the local rotations that straighten the four fingers
along their metacarpals and lay the thumb in the palm plane; scaled by an *opening* in [0, 1] they
go from the relaxed hand (0) to the flat one (1). The scenes open their actors' hands this way when
a palm rests on the partner (:mod:`dualhuman_builder.sim.performer`), and the fitter's collision
passes may open the fitted hands along the same family (:class:`~dualhuman_builder.fit.skeleton.BodyRig`).

Conventions: Y-up world, rest (zero-pose) bone heads and vertices of one shape; rotations are
anny's world-aligned local rotations (``A_child = A_parent @ L_child``).
"""

from __future__ import annotations

import numpy as np

SIDES = ("L", "R")
#: the four opening parameters of a body, in this order
OPENINGS = ("thumb.L", "fingers.L", "thumb.R", "fingers.R")
#: the thumb lies in the palm plane this far off the middle finger when the hand is open (deg)
THUMB_SPREAD_DEG = 35.0


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def hand_axes(names: list[str], rest_heads: np.ndarray, side: str) -> tuple[np.ndarray, np.ndarray]:
    """``(fingers0, normal0)``: unit rest directions wrist -> middle knuckle and out of the palm of
    hand ``side`` ("L" or "R") from rest bone heads ``(J, 3)``."""
    r = rest_heads
    wrist, knuckle = r[names.index(f"wrist.{side}")], r[names.index(f"finger3-1.{side}")]
    across = r[names.index(f"finger2-1.{side}")] - r[names.index(f"finger5-1.{side}")]  # pinky -> index
    fingers0 = _unit(knuckle - wrist)
    normal0 = _unit((1.0 if side == "L" else -1.0) * np.cross(fingers0, across))
    return fingers0, normal0


def _minimal(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation about ``a x b`` taking unit ``a`` to unit ``b``."""
    axis = np.cross(a, b)
    if np.linalg.norm(axis) < 1e-9:
        return np.eye(3)
    n = _unit(axis)
    return np.stack([b, n, np.cross(b, n)], -1) @ np.stack([a, n, np.cross(a, n)], -1).T


def open_hand(names: list[str], parents: np.ndarray, rest_heads: np.ndarray, rest_vertices: np.ndarray,
              vertex_bone: np.ndarray, side: str) -> dict[int, np.ndarray]:  # fmt: skip
    """Local rotations ``{bone index: (3, 3)}`` that open hand ``side`` flat: each finger's middle
    and distal phalanges straightened along the phalanx before them, the thumb's base turned into
    the palm plane :data:`THUMB_SPREAD_DEG` off the middle finger (its other phalanges straight).
    ``rest_vertices (V, 3)`` and ``vertex_bone (V,)`` give a fingertip bone's direction (towards the
    centre of its own vertices)."""
    r = rest_heads
    fingers0, normal0 = hand_axes(names, r, side)

    def direction(i: int) -> np.ndarray:
        kids = np.flatnonzero(np.asarray(parents) == i)
        if len(kids):
            return _unit(r[kids[0]] - r[i])
        return _unit(rest_vertices[vertex_bone == i].mean(0) - r[i])  # a fingertip

    out = {}
    for f in range(1, 6):
        chain = [names.index(f"finger{f}-{k}.{side}") for k in (1, 2, 3)]
        if f == 1:  # the thumb: into the palm plane, angled away from the fingers
            base = r[chain[0]] - r[names.index(f"wrist.{side}")]
            out_dir = _unit(base - (base @ normal0) * normal0 - (base @ fingers0) * fingers0)
            spread = np.radians(THUMB_SPREAD_DEG)
            out[chain[0]] = _minimal(direction(chain[0]), _unit(np.cos(spread) * fingers0 + np.sin(spread) * out_dir))
        for parent, child in zip(chain[:-1], chain[1:]):
            out[child] = _minimal(direction(child), direction(parent))
    return out


def opening_slot(names: list[str], bone: int) -> int:
    """Which of :data:`OPENINGS` moves finger bone ``bone``."""
    name = names[bone]
    side = name.rsplit(".", 1)[-1]
    return OPENINGS.index(("thumb." if name.startswith("finger1-") else "fingers.") + side)


__all__ = ["OPENINGS", "SIDES", "THUMB_SPREAD_DEG", "hand_axes", "open_hand", "opening_slot"]

"""Where consecutive segments meet: measuring each seam's cross-fade, and fitting it again where the blend
passes through the partner (:func:`fit_seam`, :func:`apply_seams`).

Two segments can keep a hand clear of the partner in two different ways (open on one side of an arm in
one, curled in the other), and the blend between two such answers can pass through the partner
(docs/design/fit-collision.md, "Segments and seams"). A seam needs only its two segments, so it is
mended as soon as both are done.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import numpy as np

from dualhuman_builder.fit.collision_rounds import within_tolerance
from dualhuman_builder.fit.layout import SegmentAnswer, cross_fade
from dualhuman_builder.fit.segment import SegmentFitter


@dataclass
class Seam:
    """Where two consecutive segments meet: their shared timeline frames ``b0 .. e - 1``, the depth
    (m) and penetrating share ``(e - b0,)`` their cross-fade leaves there, and the window fitted
    again over them (a :class:`~dualhuman_builder.fit.layout.SegmentAnswer`), or None where the
    cross-fade was clean."""

    b0: int
    e: int
    depth: np.ndarray
    share: np.ndarray
    fixed: SegmentAnswer | None = None


def fit_seam(fitter: SegmentFitter, prev: SegmentAnswer, part: SegmentAnswer, say: Callable[[str], None]) -> Seam | None:
    """Measure, and fit again where needed, the seam between consecutive segments ``prev`` and ``part``
    (None: they share no frames, or there is no collision term).

    A seam whose shared frames the blend leaves deeper than ``collision_tolerance_m``, or with a larger
    penetrating share than ``collision_share_tolerance``, is fitted again as one window over those
    frames and ``overlap`` more on each side, starting from the blend, with the two frames on either
    side fixed as context (so it joins both segments smoothly)."""
    cfg = fitter.cfg
    b0, e = part.start, prev.start + len(prev.pen_before)
    if fitter.collide is None or e <= b0:
        return None
    a = prev.start
    local = cross_fade([dataclasses.replace(prev, start=0), dataclasses.replace(part, start=part.start - a)],
                       part.start + len(part.pen_before) - a)  # fmt: skip
    fitter.collide.clear_memo()  # measured the same whichever segments this process fitted before
    depth, share = fitter.depths(b0, e, local["delta"], local["dtransl"], local["opening"], origin=a)
    seam = Seam(b0, e, depth, share)
    if not within_tolerance(depth, share, cfg):
        O = max(int(cfg.overlap), 0)
        c0, c1 = max(b0 - O, a), min(e + O, part.start + len(part.pen_before))
        say(f"seam frames {b0}-{e - 1}: {1000 * depth.max():.1f} mm deep after the cross-fade")
        seam.fixed = fitter.segment([(0, c0, c1)], 0, say, init=local, origin=a)
    return seam


def apply_seams(joined: dict, seams: list[Seam | None]) -> list[str]:
    """Write the seams' depths and their windows fitted again into ``joined``
    (:func:`~dualhuman_builder.fit.layout.cross_fade`'s dict), in place; returns those windows as
    ``"frames a-b"``."""
    mended = []
    for seam in seams:
        if seam is None:
            continue
        joined["pen_after"][seam.b0 : seam.e], joined["share_after"][seam.b0 : seam.e] = seam.depth, seam.share
        f = seam.fixed
        if f is not None:
            c0, c1 = f.start, f.start + len(f.pen_before)
            for key in ("delta", "dtransl", "opening"):
                for dst, src in zip(joined[key], getattr(f, key)):
                    dst[c0:c1] = src
            joined["pen_after"][c0:c1], joined["share_after"][c0:c1] = f.pen_after, f.share_after
            mended.append(f"frames {c0}-{c1 - 1}")
    return mended

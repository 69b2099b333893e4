"""How a take is cut into windows and segments (:func:`layout`), what a segment's fit gives
(:class:`SegmentAnswer`) and how consecutive segments' answers are joined (:func:`cross_fade`).

A window is ``(index, first frame, end frame)`` on the timeline (end exclusive). Segments are groups of
consecutive windows that do not depend on each other, so they can be fitted in any order and process
with the same answer (docs/decisions/0018-segments-in-worker-processes.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dualhuman_builder.fit.config import FitConfig


@dataclass
class SegmentAnswer:
    """One segment's answer, for timeline frames ``start .. start + n - 1``: per actor the corrections
    ``delta (n, 23, 3)`` (rotation vectors, rad), ``dtransl (n, 3)`` (m) and the hand openings ``opening
    (n, 4)``; the depth ``pen_before (n,)`` (m) and penetrating share ``share_before (n,)`` after the
    skeleton pass, ``pen_after``/``share_after`` the same at the answer (None without the collision
    term); and the collision passes' counts and lists (the fit summary's, see
    :func:`~dualhuman_builder.fit.fitter.fit_actors`)."""

    start: int
    delta: list
    dtransl: list
    opening: list
    pen_before: np.ndarray
    share_before: np.ndarray
    pen_after: np.ndarray | None = None
    share_after: np.ndarray | None = None
    collided: int = 0  # frames the skeleton pass left in contact
    rounds: int = 0  # the most full collision rounds any window used
    diverged: list = field(default_factory=list)  # collision passes that stepped to non-finite values (undone)
    worsened: list = field(default_factory=list)  # collision passes that left the deepest frame deeper than the best (undone)
    exact_frames: list = field(default_factory=list)  # timeline frames located at every evaluation after a stall
    exact_windows: list = field(default_factory=list)  # windows the held rounds did not settle, fitted again exactly
    stalled: list = field(default_factory=list)  # held rounds that stalled
    energy_refits: list = field(default_factory=list)  # windows fitted again exactly for their skeleton energy


def layout(T: int, cfg: FitConfig) -> list[list[tuple[int, int, int]]]:
    """The windows of a ``T``-frame take, ``(index, first frame, end frame)``, grouped into segments.

    Windows of ``cfg.window`` frames start every ``window - overlap`` frames (none that only repeats
    the previous one's last frames). Each group of ``cfg.segment_windows`` consecutive windows is a
    segment (0: the whole take is one): within it each window starts from the previous one's answer
    in their shared frames and its smoothness terms read the previous one's last two frames; a
    segment's first window starts from the retarget alone, and ``overlap`` frames earlier than the
    window layout puts it, so consecutive segments share ``2 overlap`` frames, which
    :func:`cross_fade` blends."""
    W, O = max(int(cfg.window), 4), max(int(cfg.overlap), 0)
    starts = [s for s in range(0, T, max(W - O, 1)) if s == 0 or s + O < T]
    wins = [(i, s, min(s + W, T)) for i, s in enumerate(starts)]
    m = int(cfg.segment_windows)
    if m <= 0:
        return [wins]
    segments = [wins[i : i + m] for i in range(0, len(wins), m)]
    for seg in segments[1:]:
        i, s0, s1 = seg[0]
        seg[0] = (i, max(s0 - O, 0), s1)
    return segments


def cross_fade(parts: list[SegmentAnswer], T: int) -> dict:
    """The segments' answers on the whole timeline: ``delta``/``dtransl``/``opening`` lists (per actor)
    of ``(T, ...)`` float32 arrays, ``pen_before``/``share_before``/``pen_after``/``share_after``
    ``(T,)``. In frames two consecutive segments share, the later one's weight rises linearly from ``1
    / (n + 1)`` to ``n / (n + 1)`` over the ``n`` shared frames (rotation vectors, translations and
    openings alike: the corrections are small, so blending rotation vectors is blending rotations); the
    depths are the later segment's (in the shared frames
    :func:`~dualhuman_builder.fit.seams.fit_seam` measures the blend's)."""
    first = parts[0]
    out = {key: [np.zeros((T,) + x.shape[1:], np.float32) for x in getattr(first, key)] for key in ("delta", "dtransl", "opening")}
    for key in ("pen_before", "share_before", "pen_after", "share_after"):
        out[key] = np.zeros(T)
    end = 0  # frames before this are written
    for p in parts:
        a, n = p.start, len(p.pen_before)
        shared = max(0, min(end, a + n) - a)
        w = (np.arange(1, shared + 1) / (shared + 1)).astype(np.float32)
        for key in ("delta", "dtransl", "opening"):
            for dst, src in zip(out[key], getattr(p, key)):
                src = np.asarray(src, np.float32)
                ws = w.reshape(-1, *([1] * (src.ndim - 1)))
                dst[a : a + shared] = (1 - ws) * dst[a : a + shared] + ws * src[:shared]
                dst[a + shared : a + n] = src[shared:]
        for key in ("pen_before", "share_before", "pen_after", "share_after"):
            if getattr(p, key) is not None:
                out[key][a : a + n] = getattr(p, key)
        end = max(end, a + n)
    return out

"""The window solver: fits one segment's windows (:class:`SegmentFitter`), in this process or in a worker
(:mod:`dualhuman_builder.fit.workers`).

Each window is one L-BFGS problem over both actors: first the skeleton pass (every term but the
collision term, :mod:`dualhuman_builder.fit.energy`), then the collision passes where the bodies
touch (:class:`~dualhuman_builder.fit.collision_rounds.CollisionRounds`), then the contact pass where they
come within a few millimetres without touching (:class:`~dualhuman_builder.fit.contact_pass.ContactPass`).
A segment's first window starts from the retarget (zero corrections); each next one starts from the
previous one's answer in
the frames they share and reads its last two frames as fixed context. The answer is the same in any
process: every segment starts from the same state (docs/decisions/0018-segments-in-worker-processes.md).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.fit.collision_rounds import CollisionRounds, runs
from dualhuman_builder.fit.contact_pass import ContactPass
from dualhuman_builder.fit.energy import context_of
from dualhuman_builder.fit.layout import SegmentAnswer
from dualhuman_builder.fit.problem import PARAMS_PER_ACTOR, FitProblem, Window


class SegmentFitter(FitProblem):
    """A take's :class:`~dualhuman_builder.fit.problem.FitProblem` that fits its segments
    (:func:`~dualhuman_builder.fit.layout.layout`) window by window."""

    def segment(self, wins: list[tuple[int, int, int]], n_windows: int, say: Callable[[str], None],
                init: dict | None = None, origin: int = 0) -> SegmentAnswer:  # fmt: skip
        """Fit the windows ``wins`` of one segment, the first from the retarget alone, each next from the
        one before; ``n_windows``: the take's count (for progress messages; 0: ``wins`` is a seam's
        window). ``init``: an answer so far (:func:`~dualhuman_builder.fit.layout.cross_fade`'s dict; its
        row 0 is timeline frame ``origin``): then the first window starts from it, and the windows read its
        two frames before the first and after the last (as far as it reaches) as fixed context (a seam's
        window)."""
        run = _SegmentRun(self, wins, init, origin)
        if self.collide is not None:
            self.collide.clear_memo()  # each segment starts from the same state in any process
        for j_win, (wi, s0, s1) in enumerate(wins):
            win = run.window(j_win, s0, s1)
            self.skeleton_pass(win.params, win.sl, win.ctxs, win.afters)
            if self.collide is not None:
                run.record_collision(win, *CollisionRounds(self, win, run.out, say).run())
                if self.cfg.contact_reach_m > 0:
                    run.record_contact(win, ContactPass(self, win, say).run())
            run.store(win)
            say(f"window {wi + 1}/{n_windows}: frames {s0}-{s1 - 1}" if n_windows else f"seam: frames {s0}-{s1 - 1} fitted again")
        return run.finish()

class _SegmentRun:
    """One segment's state while its windows are fitted: the corrections of timeline frames ``a0 .. a1 -
    1`` (per actor ``deltas``, ``dtransl``, ``openings``; with a seam's ``init``, two frames of context
    on either side of the windows), the answer ``out`` for frames ``first .. last - 1`` and, per frame of
    it, the depth (m) and penetrating share ``known (2, last - first)`` of its current corrections where
    a check measured them (nan: not measured), so that the answer's depths need no second measurement."""

    def __init__(self, fitter: SegmentFitter, wins: list, init: dict | None, origin: int):
        self.fitter, self.wins, self.init = fitter, wins, init
        dev = fitter.dev
        self.first, self.last = first, last = wins[0][1], wins[-1][2]
        if init is None:
            self.a0, self.a1 = first, last
        else:
            self.a0, self.a1 = max(first - 2, origin), min(last + 2, origin + len(init["delta"][0]))
        n, S = self.a1 - self.a0, len(MVN_SEGMENTS)
        if init is None:
            self.deltas = [torch.zeros(n, S, 3, device=dev) for _ in fitter.acts]
            self.dtransl = [torch.zeros(n, 3, device=dev) for _ in fitter.acts]
            self.openings = [torch.zeros(n, 4, device=dev) for _ in fitter.acts]
        else:
            a, b = self.a0 - origin, self.a1 - origin
            self.deltas, self.dtransl, self.openings = ([torch.tensor(x[a:b], device=dev) for x in init[key]]
                                                        for key in ("delta", "dtransl", "opening"))  # fmt: skip
        self.out = SegmentAnswer(first, [], [], [], np.zeros(last - first), np.zeros(last - first))
        self.known = np.full((2, last - first), np.nan)

    def _context(self, k: int, csl: slice):
        """Actor ``k``'s context of timeline frames ``csl`` from the segment's corrections."""
        cloc = slice(csl.start - self.a0, csl.stop - self.a0)
        return context_of(self.fitter.acts[k], self.deltas[k][cloc], self.dtransl[k][cloc], self.openings[k][cloc], csl)

    def window(self, j_win: int, s0: int, s1: int) -> Window:
        """Window ``j_win`` of the segment (timeline frames ``s0 .. s1 - 1``): its corrections (copies that
        require gradients; the openings only when ``cfg.hand_opening``) and its contexts."""
        fitter, a0 = self.fitter, self.a0
        ctx_n = min(2, s0 - a0) if (j_win or self.init is not None) else 0
        after_n = self.a1 - s1 if j_win == len(self.wins) - 1 else 0
        acts = range(len(fitter.acts))
        with torch.no_grad():
            ctxs = [self._context(k, slice(s0 - ctx_n, s0)) if ctx_n else None for k in acts]
            afters = [self._context(k, slice(s1, s1 + after_n)) if after_n else None for k in acts]
        loc = slice(s0 - a0, s1 - a0)
        params = []
        for k in acts:
            params += [self.deltas[k][loc].clone().requires_grad_(True), self.dtransl[k][loc].clone().requires_grad_(True),
                       self.openings[k][loc].clone().requires_grad_(fitter.cfg.hand_opening)]  # fmt: skip
        return Window(s0, s1, params, ctxs, afters)

    def record_collision(self, win: Window, before: tuple, span: tuple[int, int], after: tuple | None) -> None:
        """Note the window's depths: ``before`` ``(depth, share)`` after its skeleton pass (``(W,)`` each),
        ``after`` those of the answer of its span rows ``span`` (None: not measured)."""
        ploc = slice(win.s0 - self.first, win.s1 - self.first)
        self.out.pen_before[ploc], self.out.share_before[ploc] = before
        self.known[:, ploc] = before
        r0, r1 = span
        rows = slice(ploc.start + r0, ploc.start + r1)
        self.known[:, rows] = np.nan
        if after is not None:
            self.known[:, rows] = after

    def record_contact(self, win: Window, after: tuple | None) -> None:
        """Note the window's depths ``(depth, share)`` ``(W,)`` each after its contact pass (None: it moved
        nothing)."""
        if after is not None:
            self.known[:, win.s0 - self.first : win.s1 - self.first] = after

    def store(self, win: Window) -> None:
        """Write the window's answer into the segment's corrections (the frames it shares with the next
        window take that one's answer once it is fitted)."""
        loc = slice(win.s0 - self.a0, win.s1 - self.a0)
        P = PARAMS_PER_ACTOR
        for k in range(len(self.fitter.acts)):
            for j, t in enumerate((self.deltas[k], self.dtransl[k], self.openings[k])):
                t[loc] = win.params[P * k + j].detach()

    def finish(self) -> SegmentAnswer:
        """The segment's answer: its frames' corrections as arrays and, with the collision term, the depths
        of the answer (measured here where no check did)."""
        out, first, last, a0 = self.out, self.first, self.last, self.a0
        out.delta, out.dtransl, out.opening = ([x[first - a0 : last - a0].cpu().numpy() for x in xs]
                                               for xs in (self.deltas, self.dtransl, self.openings))  # fmt: skip
        if self.fitter.collide is not None:
            out.pen_after, out.share_after = self.known
            for a, b in runs(np.isnan(self.known[0])):
                out.pen_after[a:b], out.share_after[a:b] = self.fitter.depths(first + a, first + b, self.deltas, self.dtransl,
                                                                              self.openings, origin=a0)  # fmt: skip
        return out

"""The collision passes of one window (:class:`CollisionRounds`), after its skeleton pass.

The schedule, its reasons and its switches are in ``docs/design/fit-collision.md``; in short:

- The frames the skeleton pass left in contact are found; the passes move those within
  ``collision_span_s`` of them (the *span*), the rest of the window held, its two frames on either side
  of the span read as fixed context (:func:`span_rows`).
- The hands' pass moves the hand openings alone; then up to ``collision_rounds`` full rounds move
  everything, while a frame is over a tolerance. Each pass is weighted ``collision_weight_step`` times
  the one before; frames deeper than ``collision_deep_m`` one step ahead from round 1 on
  (docs/decisions/0015-collision-weight-schedule.md). A full round moves only the frames the pass
  before left over a tolerance and ``SMOOTH_REACH`` on either side (``collision_hold_settled``).
- Contacts are *held* within a pass (located by the check before it, re-read as planes); a round that
  stalls has the frames it left deep located at every evaluation from then on; a window left unsettled
  is fitted again from its skeleton pass that way (the *exact* mode), and the less deep answer kept; a
  window settled only after a stall but with its skeleton energy over ``collision_energy_ratio`` times
  the skeleton pass's is fitted again the exact way too, and the lower energy kept
  (docs/decisions/0016-held-contacts.md).
- A pass that diverges or leaves the deepest frame deeper than the best pass before it is undone;
  stuck frames restart from their neighbours (docs/decisions/0017-undo-and-restart.md).

Depths are metres; a window's rows are its frames ``0 .. W - 1``, a span's rows ``0 .. n - 1``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from dualhuman_builder.fit.config import FitConfig
from dualhuman_builder.fit.energy import join_contexts, opening_energy, stack_contexts
from dualhuman_builder.fit.layout import SegmentAnswer
from dualhuman_builder.fit.problem import PARAMS_PER_ACTOR, FitProblem, LocatedContacts, Window

#: restarts of stuck frames per window: one does not always free them (docs/decisions/0017-undo-and-restart.md,
#: measured by ``benchmarks/bench_fit_accuracy.py``)
MAX_RESTARTS = 2
#: the frames on either side of one whose smoothness terms read it too (the second difference at t - 1, t
#: and t + 1 reads t - 2 .. t + 2): a full round moves these with the frames still over a tolerance
SMOOTH_REACH = 2
#: a held full round stalled where it leaves the deepest frame deeper than this share of the depth it
#: started from (docs/decisions/0016-held-contacts.md)
STALL_SHARE = 0.75
#: a frame over the tolerance that a round left deeper than this share of the depth it started from
#: (moved by less than 20 %) is stuck (docs/decisions/0017-undo-and-restart.md)
STUCK_SHARE = 0.8


class Diverged(Exception):
    """An L-BFGS line search stepped to non-finite parameters."""


def all_finite(tensors) -> bool:
    """Whether every tensor of ``tensors`` holds only finite values."""
    return all(bool(torch.isfinite(t).all()) for t in tensors)


def within_tolerance(depth: np.ndarray, share: np.ndarray, cfg: FitConfig) -> bool:
    """Whether frames with per-frame deepest vertices ``depth`` (m) and penetrating shares ``share``
    are all within ``cfg.collision_tolerance_m`` and ``cfg.collision_share_tolerance``."""
    return bool(np.max(depth) <= cfg.collision_tolerance_m and np.max(share) <= cfg.collision_share_tolerance)


def restore(params, saved) -> None:
    """Copy ``saved`` tensors back into the optimised ``params`` (in place)."""
    with torch.no_grad():
        for p, k in zip(params, saved):
            p.copy_(k)


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """The runs of True in ``mask (n,)``, as ``(first, end)`` index pairs."""
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(np.int8), 0]))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def dilate(mask: np.ndarray, n: int) -> np.ndarray:
    """``(W,)`` bool: the rows within ``n`` rows of a True row of ``mask (W,)``."""
    c = np.r_[0, np.cumsum(mask, dtype=np.int64)]
    i = np.arange(len(mask))
    return c[np.minimum(i + n + 1, len(mask))] - c[np.maximum(i - n, 0)] > 0


def span_rows(hit: np.ndarray, W: int, cfg: FitConfig, fps: float) -> tuple[int, int]:
    """Window rows ``r0 .. r1 - 1`` the collision passes of a ``W``-frame window move, for its hit frames
    ``hit`` (rows, sorted): from ``cfg.collision_span_s`` before the first to as long after the last
    (the whole window when that is 0 or there is no hit)."""
    if not len(hit) or cfg.collision_span_s <= 0:
        return 0, W
    n = int(np.ceil(cfg.collision_span_s * fps))
    return max(int(hit[0]) - n, 0), min(int(hit[-1]) + 1 + n, W)


def restart_from_neighbours(params, stuck: np.ndarray) -> bool:
    """Set every run of ``stuck (W,)`` frames of the window's ``params`` (each ``(W, ...)``) to the
    linear interpolation between the frames just before and after it (the one there is at the
    window's edge). False when every frame is stuck (no neighbour to start from)."""
    W = len(stuck)
    if stuck.all():
        return False
    with torch.no_grad():
        for a, b in runs(stuck):  # frames a .. b-1
            lo, hi = a - 1, b
            for p in params:
                if lo < 0:
                    p[a:b] = p[hi]
                elif hi >= W:
                    p[a:b] = p[lo]
                else:
                    w = torch.linspace(0.0, 1.0, b - a + 2, dtype=p.dtype, device=p.device)[1:-1]
                    w = w.reshape(-1, *([1] * (p.dim() - 1)))
                    p[a:b] = (1 - w) * p[lo] + w * p[hi]
    return True


@dataclass
class _Snapshot:
    """An answer of the span: its deepest frame's depth ``depth`` (m), copies of the corrections
    ``params``, the per-frame deepest vertices ``depths (n,)`` (m) and penetrating shares ``shares (n,)``,
    and the contacts located there (None: not located)."""

    depth: float
    params: list
    depths: np.ndarray
    shares: np.ndarray
    located: LocatedContacts | None


@dataclass
class _Pass:
    """What one collision pass reads: ``what`` (``"hands"`` or ``"all"``), its full round's number
    (0 for the hands' pass), its weight, the span rows it moves (``rows_m``) and holds (``frozen_t``,
    None when none), the hit rows that move (``phit``, ``hit_t``), of those the rows whose contacts are
    held (``rows_h``, with ``held``; ``use_held``: any) and located at every evaluation (``rows_x``), the weights' multiples
    of both (``ahead_h``, ``ahead_x``), and for the hands' pass the bones' rotations as constants
    (``fixed``)."""

    what: str
    n_round: int
    label: str
    weight: float
    rows_m: np.ndarray
    frozen_t: torch.Tensor | None
    phit: np.ndarray
    hit_t: torch.Tensor
    rows_h: np.ndarray
    rows_x: np.ndarray
    use_held: bool
    held: object
    ahead_h: torch.Tensor
    ahead_x: torch.Tensor
    fixed: tuple | None
    start_left: np.ndarray


class CollisionRounds:
    """The collision passes of window ``win`` of ``problem`` after its skeleton pass: :meth:`run` moves
    ``win.params`` in place and adds its counts and lists to the segment's answer ``out``; ``say`` gets
    progress lines."""

    def __init__(self, problem: FitProblem, win: Window, out: SegmentAnswer, say: Callable[[str], None]):
        self.problem, self.win, self.out, self.say = problem, win, out, say
        self.cfg = problem.cfg

    def run(self) -> tuple[tuple[np.ndarray, np.ndarray], tuple[int, int], tuple[np.ndarray, np.ndarray] | None]:
        """Fit the window's collision passes. Returns the depths ``(depth, share)`` ``(W,)`` each after the
        skeleton pass, the span rows ``(r0, r1)`` the passes moved, and the depths ``(r1 - r0,)`` of the
        span's answer when a check measured them (None: a restart in the last round moved it since)."""
        win, cfg = self.win, self.cfg
        pen, located = self.problem.check(win.params, win.sl)
        before = (pen["max_depth_m"], pen["share"])
        hit = np.flatnonzero(pen["max_depth_m"] > 0)
        self.out.collided += len(hit)
        pen, hit = self._cut_span(pen, located, hit)
        P = PARAMS_PER_ACTOR
        n_acts = len(self.problem.acts)
        self.cbones = [p for k in range(n_acts) for p in self.cparams[P * k : P * k + 2]]
        self.chands = [self.cparams[P * k + 2] for k in range(n_acts)] if cfg.hand_opening else []
        # the skeleton pass's answer; `best`: the best round's so far (an undone round goes back to it
        # without locating its contacts again)
        self.start = _Snapshot(float(pen["max_depth_m"].max()), [p.detach().clone() for p in self.cparams], pen["max_depth_m"],
                               pen["share"], self.located)  # fmt: skip
        # the hands first: their openings have no data term, so they give way before any bone the suit and
        # trackers hold, and the full rounds start from hands that already fit
        self.passes = (["hands"] if self.chands else []) + ["all"] * max(int(cfg.collision_rounds), 1)
        # held contacts first, exact where a held round stalled; then, for a window left unsettled, exact
        self.modes = ["held", "exact"] if cfg.collision_hold_contacts else ["exact"]
        # rows of the span whose contacts are located at every evaluation
        self.exact = np.zeros(0, np.int64) if cfg.collision_hold_contacts else np.arange(self.c1 - self.c0)
        self.best, self.held_best = self.start, None
        self.energies = None  # (after the skeleton pass, after the held rounds) where they settled after a stall
        for mode in self.modes if len(hit) else []:
            if self._run_mode(mode):
                break
            self.held_best = self.best
        self._keep_the_better()
        after = self._measured_answer()
        self._write_back()
        return before, (self.r0, self.r1), after

    # ---- the span

    def _cut_span(self, pen: dict, located, hit: np.ndarray) -> tuple[dict, np.ndarray]:
        """Set the span (rows ``r0 .. r1 - 1``, timeline frames ``c0 .. c1 - 1``), its corrections
        ``cparams`` (the window's own when the span is the whole window, else copies), its contexts and
        its located contacts; returns the skeleton pass's depths and hit rows, as span rows."""
        win, problem = self.win, self.problem
        s0, s1 = win.s0, win.s1
        self.r0, self.r1 = r0, r1 = span_rows(hit, s1 - s0, self.cfg, problem.fps)
        self.c0, self.c1, self.csl = s0 + r0, s0 + r1, slice(s0 + r0, s0 + r1)
        self.located = located
        if (r0, r1) == (0, s1 - s0):
            self.cparams, self.cctxs, self.cafters = win.params, win.ctxs, win.afters
            return pen, hit
        acts = problem.acts
        self.cparams = [p[r0:r1].detach().clone().requires_grad_(p.requires_grad) for p in win.params]
        self.cctxs = [join_contexts(win.ctxs[k], win.held_rows(a, k, max(r0 - 2, 0), r0), last=True) for k, a in enumerate(acts)]
        self.cafters = [join_contexts(win.held_rows(a, k, r1, min(r1 + 2, s1 - s0)), win.afters[k], last=False)
                        for k, a in enumerate(acts)]  # fmt: skip
        if located is not None:
            self.located = LocatedContacts(located.take(np.arange(r0, r1)), np.arange(r1 - r0))
        return {key: pen[key][r0:r1] for key in ("max_depth_m", "share")}, hit - r0

    def _skeleton_energy(self, ps) -> float:
        """The skeleton energy (every term but the collision term) of the span at corrections ``ps``."""
        with torch.no_grad():
            return float(self.problem.energy(ps, self.csl, self.cctxs, self.cafters)[0])

    # ---- one mode: the hands' pass and the full rounds, held or exact

    def _run_mode(self, mode: str) -> bool:
        """Run the passes in ``mode`` (``"held"`` or ``"exact"``) from the skeleton pass's answer; True when
        no further mode is to run (settled, or this was the exact mode)."""
        cfg, out = self.cfg, self.out
        self.best, self.restarts, self.settled = self.start, 0, False
        self.hit = np.flatnonzero(self.start.depths > 0)
        if mode == "exact" and len(self.modes) == 2:
            # exact in the frames the held rounds located exactly and those they left over the tolerance
            # (docs/decisions/0016-held-contacts.md: not every frame of the window)
            self.exact = np.union1d(self.exact, np.flatnonzero(self.held_best.depths > cfg.collision_tolerance_m))
            restore(self.cparams, self.start.params)
            out.exact_windows.append(f"frames {self.c0}-{self.c1 - 1}")
            self.located = self.start.located
        n_round = 0  # the full rounds count from 1 (the hands' pass: 0)
        for i_pass, what in enumerate(self.passes):
            n_round += what == "all"
            if self._one_pass(i_pass, what, n_round):
                break
        if mode == "held" and self.settled and len(self.modes) == 2 and len(self.exact) and cfg.collision_energy_ratio > 0:
            # settled after a stall: were the bodies bent out of shape to get there? (collision_energy_ratio)
            self.energies = max(self._skeleton_energy(self.start.params), 1e-12), self._skeleton_energy(self.best.params)
            if self.energies[1] > cfg.collision_energy_ratio * self.energies[0]:
                self.settled = False
                self.say(f"frames {self.c0}-{self.c1 - 1}: the held rounds settled with the skeleton energy "
                         f"{self.energies[1] / self.energies[0]:.1f}x the skeleton pass's; fitted again the exact way")  # fmt: skip
        return self.settled or mode == "exact"

    def _one_pass(self, i_pass: int, what: str, n_round: int) -> bool:
        """Collision pass ``i_pass`` (``what``: ``"hands"`` or ``"all"``, full round ``n_round``): set it up,
        step L-BFGS, measure the answer and keep or undo it. True when the mode stops here."""
        ps = self._prepare(i_pass, what, n_round)
        if ps is None:
            return True
        copt = torch.optim.LBFGS(self.chands if what == "hands" else self.cbones + self.chands, lr=1.0,
                                 max_iter=self.cfg.collision_iterations, line_search_fn="strong_wolfe")  # fmt: skip
        self.located = None  # the bodies move
        try:
            copt.step(self._closure(ps, copt))
        except Diverged:
            pass
        if not all_finite(self.cparams):
            # the line search stepped to non-finite corrections: keep the best round's answer
            restore(self.cparams, self.best.params)
            self.out.diverged.append(ps.label)
            return True
        if self._measure(ps):
            return True
        if what == "all" and self.cfg.collision_restart and self.restarts < MAX_RESTARTS and n_round >= 2:
            self._restart_stuck(ps)
        return False

    def _prepare(self, i_pass: int, what: str, n_round: int) -> _Pass | None:
        """The pass's weights, moving rows and contacts (:class:`_Pass`); None when the best answer is
        within the tolerances already (the mode is settled)."""
        cfg, problem, dev = self.cfg, self.problem, self.problem.dev
        n = self.c1 - self.c0
        weight = cfg.collision_weight * cfg.collision_weight_step**i_pass  # the hands' pass included
        if i_pass == 0:  # per row of the span, the weight's multiple (collision_deep_m)
            self.ahead = np.ones(n)
        if what == "all" and n_round == 1 and cfg.collision_deep_m > 0:
            self.ahead = np.where(self.best.depths > cfg.collision_deep_m, cfg.collision_weight_step, 1.0)
        if i_pass == 0:  # span rows this pass moves: all in the first; then see collision_hold_settled
            self.moving = np.ones(n, bool)
        elif what == "all" and cfg.collision_hold_settled:
            over = (self.best.depths > cfg.collision_tolerance_m) | (self.best.shares > cfg.collision_share_tolerance)
            if not over.any():
                # the best answer is within the tolerances already: the skeleton pass left only shallow
                # contacts and the pass after it was undone (deeper); nothing to move
                self.settled = True
                return None
            # (frames held so far kept the depths that let them be held, so `over` lies in `moving`)
            self.moving = self.moving & dilate(over, SMOOTH_REACH)
        rows_m = np.flatnonzero(self.moving)
        frozen_t = None if self.moving.all() else torch.as_tensor(np.flatnonzero(~self.moving), device=dev)
        phit = self.hit[self.moving[self.hit]]  # the hit rows that move (a held row's term is a constant)
        label = f"frames {self.c0}-{self.c1 - 1}, " + ("the hands' collision pass" if what == "hands" else f"collision round {n_round}")
        # rows of `phit` whose contacts are held, and those located at every evaluation
        rows_x = np.flatnonzero(np.isin(phit, self.exact))
        rows_h = np.setdiff1d(np.arange(len(phit)), rows_x)
        use_held = len(rows_h) > 0
        label += ", held contacts" if len(rows_x) == 0 else (f", exact at {len(rows_x)} frames" if use_held else "")
        held = None
        if use_held:  # located where the pass starts (by the last check, if the bodies are still there)
            if self.located is None:
                _, self.located = problem.check(self.cparams, self.csl, rows_m)
            held = self.located.take(phit[rows_h])
        # the hands' pass moves the openings alone: the bones' rotations and positions are constants there
        # (no gradient, no skeleton terms but the openings', opening_energy), and so are the depths of the
        # held contacts that touch no finger
        fixed = None
        if what == "hands":
            with torch.no_grad():
                fixed = problem.stack.rotations(torch.stack(self.cparams[0::PARAMS_PER_ACTOR]), self.csl).unbind(0)
            if held is not None:
                held = problem.collide.moving_only(held, problem.fingers)
        ahead_h, ahead_x = (torch.as_tensor(self.ahead[phit[r]], dtype=self.cparams[0].dtype, device=dev) for r in (rows_h, rows_x))
        return _Pass(what, n_round, label, weight, rows_m, frozen_t, phit, torch.as_tensor(phit, device=dev), rows_h, rows_x,
                     use_held, held, ahead_h, ahead_x, fixed, self.best.depths)  # fmt: skip

    def _closure(self, ps: _Pass, copt: torch.optim.LBFGS) -> Callable[[], torch.Tensor]:
        """L-BFGS's closure for pass ``ps``: the skeleton energy (the openings' terms alone in the hands'
        pass) plus ``ps.weight`` times the collision term of the hit rows that move, its gradient with the
        held rows' zeroed."""
        problem, cfg, dev, collide = self.problem, self.cfg, self.problem.dev, self.problem.collide
        acts, cparams, csl, c0, P = problem.acts, self.cparams, self.csl, self.c0, PARAMS_PER_ACTOR

        def closure():
            if not all_finite(cparams):
                raise Diverged
            copt.zero_grad()
            if ps.fixed is None:
                e, rots = problem.energy(cparams, csl, self.cctxs, self.cafters)
                transl = [cparams[P * k + 1] for k in range(len(acts))]
            else:
                e = opening_energy(torch.stack(cparams[2::P]), stack_contexts(self.cctxs), stack_contexts(self.cafters), cfg,
                                   problem.fps)  # fmt: skip
                rots, transl = ps.fixed, [cparams[P * k + 1].detach() for k in range(len(acts))]
            # every bone of the hit frames (fingers opened), for the few thousand (frame, vertex) pairs the
            # loss reads, skinned with the gradient (index_select: its backward is an index_add, cheaper than
            # indexing's index_put)
            hit_t = ps.hit_t
            posed_hit = [a.rig.pose(rots[k].index_select(0, hit_t), a.transl0[c0 + hit_t] + transl[k].index_select(0, hit_t),
                                    False, cparams[P * k + 2].index_select(0, hit_t)) for k, a in enumerate(acts)]  # fmt: skip

            def at(rows):  # the collision term's batch rows are `rows` of `phit`
                rows = torch.as_tensor(rows, device=dev)
                return lambda body, f, v: acts[body].rig.skin_at(posed_hit[body], rows[f], v)

            c = 0.0
            if ps.held is not None:
                c = c + (ps.ahead_h * collide.linear_loss(ps.held, at(ps.rows_h), device=dev)).sum()
            if len(ps.rows_x):  # the full meshes, without gradient, locate the contacts
                with torch.no_grad():
                    vs = [p.vertices for p in problem.pose_bodies(cparams, csl, hit_t[ps.rows_x])]
                c = c + (ps.ahead_x * collide(vs[0], vs[1], keys=c0 + ps.phit[ps.rows_x], points=at(ps.rows_x)).loss).sum()
            e = e + ps.weight * c
            e.backward()
            if ps.frozen_t is not None:  # the rows this pass holds: no step (L-BFGS keeps them where they are)
                for q in cparams:
                    if q.grad is not None:
                        q.grad.index_fill_(0, ps.frozen_t, 0.0)
            return e

        return closure

    def _measure(self, ps: _Pass) -> bool:
        """Check the depths the pass left; note a stall, undo a pass that left the window deeper than the
        best so far, else keep it as the best. True when the span is settled."""
        cfg, out = self.cfg, self.out
        # how deep one pass leaves a frame depends on where it started, so frames still deeper than the
        # tolerance go round again with the term weighted up. Every frame ever hit keeps the term (released,
        # it would spring back while its neighbours are refitted); frames pushed into contact by their
        # neighbours join.
        now_pen, self.located = self.problem.check(self.cparams, self.csl, ps.rows_m)
        if ps.frozen_t is not None:  # the rows held are where the pass started (the best answer): its depths
            for key, prior in (("max_depth_m", self.best.depths), ("share", self.best.shares)):
                full = np.array(prior, dtype=float)
                full[ps.rows_m] = now_pen[key]
                now_pen[key] = full
        left = now_pen["max_depth_m"]
        if ps.what == "all":  # the summary counts the full rounds (the hands' pass is extra)
            out.rounds = max(out.rounds, ps.n_round)
        stall = max(cfg.collision_tolerance_m, STALL_SHARE * ps.start_left.max())
        if ps.use_held and ps.what == "all" and left.max() > stall:
            # held planes stall where the answer lies through a thin part of the partner or where the closest
            # faces change as the bodies move (docs/decisions/0016-held-contacts.md): the frames left that
            # deep are located at every evaluation from now on
            new = np.setdiff1d(np.flatnonzero(left > stall), self.exact)
            self.exact = np.union1d(self.exact, new)
            out.stalled.append(ps.label)
            out.exact_frames += [int(self.c0 + f) for f in new]
        if left.max() > self.best.depth:
            # deeper than the best round so far (L-BFGS stepped into a worse basin): undo it; the next round
            # starts again from the best answer, with the term weighted up
            restore(self.cparams, self.best.params)
            self.located = self.best.located
            out.worsened.append(f"{ps.label}: {1000 * left.max():.1f} mm after, {1000 * self.best.depth:.1f} mm before")
        else:
            self.best = _Snapshot(float(left.max()), [p.detach().clone() for p in self.cparams], left, now_pen["share"], self.located)
            if within_tolerance(left, now_pen["share"], cfg):
                self.settled = True
                return True
        self.hit = np.union1d(self.hit, np.flatnonzero(left > 0))
        return False

    def _restart_stuck(self, ps: _Pass) -> None:
        """Restart each run of too-deep frames that holds a stuck one (over the tolerance, moved by less
        than ``1 - STUCK_SHARE`` of its depth: interlocked hands, whose two pushes oppose each other) from
        the straight line between the frames around it. The span holds the best answer (kept or restored)
        and the round started from the best before it: those two are compared."""
        now = self.best.depths
        deep = now > self.cfg.collision_tolerance_m
        stuck = deep & (now > STUCK_SHARE * ps.start_left)
        if stuck.any():
            run = np.cumsum(np.r_[True, deep[1:] != deep[:-1]])
            if restart_from_neighbours(self.cparams, deep & np.isin(run, run[stuck])):
                self.restarts += 1
                self.located = None
                self.say(f"{ps.label}: {int(stuck.sum())} frames stuck, restarted from their neighbours")

    # ---- the window's answer

    def _keep_the_better(self) -> None:
        """Where both modes ran, keep the held rounds' answer if it is the better one: of two settled
        answers after the energy refit the lower skeleton energy, else the less deep."""
        held_best, best = self.held_best, self.best
        if held_best is None:
            return
        if self.energies is not None and within_tolerance(best.depths, best.shares, self.cfg):
            (e_start, e_held), e_exact = self.energies, self._skeleton_energy(best.params)
            keep_held = e_held <= e_exact
            self.out.energy_refits.append(f"frames {self.c0}-{self.c1 - 1}: skeleton energy {e_held / e_start:.2f}x the skeleton "
                                          f"pass's held, {e_exact / e_start:.2f}x exact; kept {'held' if keep_held else 'exact'}")  # fmt: skip
        else:
            keep_held = held_best.depth < best.depth  # the held rounds had left it less deep
        if keep_held:
            restore(self.cparams, held_best.params)

    def _measured_answer(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The span's depths if a check measured its answer (the best round's, the held rounds' best or the
        skeleton pass's); None when a restart in the last round moved it since."""
        for snap in (self.best, self.held_best):
            if snap is not None and all(torch.equal(p, q) for p, q in zip(self.cparams, snap.params)):
                return snap.depths, snap.shares
        return None

    def _write_back(self) -> None:
        """Copy the span's answer into the window's corrections (when the span had copies of its own)."""
        if self.cparams is not self.win.params:
            with torch.no_grad():
                for p, q in zip(self.win.params, self.cparams):
                    p[self.r0 : self.r1] = q

"""The take solver (``FitConfig.solver = "take"``): the whole take, both actors, as one problem
(:class:`TakeFitter`).

The window solver (:mod:`~dualhuman_builder.fit.segment`) fits 48-frame windows one after another,
each with its own collision rounds and per-window rules (undo a round that left the window deeper,
restart stuck frames, refit a window bent out of shape, seams fitted again). Here every frame's
corrections are one set of tensors, and the schedule is per frame instead of per window:

1. **Skeleton pass**: L-BFGS on the skeleton energy (:mod:`~dualhuman_builder.fit.energy`) of every
   frame at once, ``cfg.iterations`` iterations. The smoothness terms couple neighbouring frames
   directly, so there are no contexts, cross-fades or seams.
2. **Collision continuation**: a pass that moves the hand openings alone (they have no data term, so
   they give way before any bone), then full rounds. Each frame that touches its partner carries its own multiple of
   ``cfg.collision_weight``: 1 where first found in contact (``collision_weight_step`` where deeper
   than ``collision_deep_m``), and one ``collision_weight_step`` more after every round that leaves
   it over a tolerance. A round locates the contacts of the frames still over a tolerance (held as
   planes through the round, :meth:`~dualhuman_builder.geometry.collision.CollisionTerm.linearise`)
   and moves them and the ``SMOOTH_REACH`` frames on either side with one L-BFGS run of
   ``cfg.take_iterations`` iterations (more than a window's ``collision_iterations``: the frames share
   the run's curvature pairs and step length), or with ``cfg.take_step = "runs"`` one run per block of
   those frames, evaluated together (:mod:`~dualhuman_builder.fit.block_lbfgs`); settled frames keep
   their term and hold still. A frame
   the round leaves over ``collision_tolerance_m`` and deeper than its best answer so far goes back to
   that answer (the window solver's undo of a round, per frame). A frame a
   held round left stalled (no shallower than ``STALL_SHARE`` of its depth) is located at every
   evaluation from then on, as in the window solver (docs/decisions/0016-held-contacts.md). At most
   ``cfg.collision_rounds`` rounds.

From round 2 on, frames a round leaves stuck (over a tolerance and moved by less than 20 %:
interlocked hands) restart from their neighbours, as in the window solver
(docs/decisions/0017-undo-and-restart.md), the run restarted bounded by ``cfg.window`` frames; a
restart the next round does not make pay is undone there, per frame, like any deeper answer. The
contact pass (:mod:`~dualhuman_builder.fit.contact_pass`) does not run here.

Contacts are located ``CHUNK`` frames at a time, so memory grows with the frames in contact, not
with whole meshes of the take. With contacts held, the query that measures the depths after a round
also locates the contacts (:meth:`~dualhuman_builder.fit.problem.FitProblem.check`, the window
solver's), and the next round holds them for the frames that have not moved since: the two queries
of the same poses become one.
Depths are metres; rows are timeline frames ``0 .. T - 1``.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.fit.block_lbfgs import block_lbfgs, frame_blocks
from dualhuman_builder.fit.collision_rounds import (MAX_RESTARTS, SMOOTH_REACH, STALL_SHARE, STUCK_SHARE, Diverged, all_finite,
                                                   dilate, restart_from_neighbours, restore, runs)
from dualhuman_builder.fit.layout import SegmentAnswer
from dualhuman_builder.fit.problem import PARAMS_PER_ACTOR, FitProblem

#: frames posed at once where contacts are located (bounds the meshes held in memory)
CHUNK = 256


class TakeFitter(FitProblem):
    """A take's :class:`~dualhuman_builder.fit.problem.FitProblem` fitted as one problem (see the module
    docstring): :meth:`fit` returns the whole take's :class:`~dualhuman_builder.fit.layout.SegmentAnswer`."""

    def fit(self, say: Callable[[str], None]) -> SegmentAnswer:
        """Fit every frame of the take; ``say`` gets one line per pass."""
        T, P, dev, cfg = self.T, PARAMS_PER_ACTOR, self.dev, self.cfg
        S = len(MVN_SEGMENTS)
        self.sl, self.none = slice(0, T), [None] * len(self.acts)
        self.located: dict = {}  # frame -> the LocatedContacts (problem.py) holding its contacts, while still valid
        params = []
        for _ in self.acts:
            params += [torch.zeros(T, S, 3, device=dev, requires_grad=True), torch.zeros(T, 3, device=dev, requires_grad=True),
                       torch.zeros(T, 4, device=dev, requires_grad=cfg.hand_opening)]  # fmt: skip
        self.params = params
        self.bones = [p for k in range(len(self.acts)) for p in params[P * k : P * k + 2]]
        self.hands = [params[P * k + 2] for k in range(len(self.acts))] if cfg.hand_opening else []
        self.skeleton_pass(params, self.sl, self.none, self.none)
        say(f"take: skeleton pass over {T} frames")
        out = SegmentAnswer(0, [], [], [], np.zeros(T), np.zeros(T))
        if self.collide is not None:
            self.collide.clear_memo()
            depth, share = self._measure(np.arange(T))
            out.pen_before, out.share_before = depth.copy(), share.copy()
            out.collided = int((depth > 0).sum())
            self._continuation(depth, share, out, say)
            out.pen_after, out.share_after = depth, share
        out.delta, out.dtransl, out.opening = ([params[P * k + j].detach().cpu().numpy() for k in range(len(self.acts))]
                                               for j in range(P))  # fmt: skip
        return out

    # ---- the passes

    def _continuation(self, depth: np.ndarray, share: np.ndarray, out: SegmentAnswer, say) -> None:
        """The collision rounds (module docstring), updating ``depth``/``share`` ``(T,)`` in place and
        ``out``'s counts."""
        cfg = self.cfg
        step = cfg.collision_weight_step
        mult = np.zeros(self.T)  # per frame, the multiple of collision_weight its term carries (0: none yet)
        hit = depth > 0
        mult[hit] = np.where((depth[hit] > cfg.collision_deep_m) & (cfg.collision_deep_m > 0), step, 1.0)
        exact = np.full(self.T, not cfg.collision_hold_contacts)  # frames located at every evaluation
        restarts = np.zeros(self.T, np.int64)  # per frame, the restarts from its neighbours so far
        # per frame, its best answer so far: the corrections, depth and share (a round that leaves a frame
        # deeper goes back to it there)
        best = ([p.detach().clone() for p in self.params], depth.copy(), share.copy())
        # the hands first: their openings have no data term, so they give way before any bone the suit and
        # trackers hold, and the full rounds start from hands that already fit (as in the window solver)
        passes = (["hands"] if self.hands else []) + ["all"] * max(int(cfg.collision_rounds), 1)
        n_round = 0  # the full rounds count from 1 (the hands' pass: 0)
        for i_pass, what in enumerate(passes):
            n_round += what == "all"
            over = self._over(depth, share)
            if not over.any():
                return
            if i_pass > 0:
                mult[over] *= step
            moving = dilate(over, SMOOTH_REACH)
            rows = np.flatnonzero(moving)
            termed = np.flatnonzero(moving & (mult > 0))  # the moving frames with a collision term
            start = depth[rows].copy()
            label = (f"take: collision round {n_round}" if what == "all" else "take: the hands' collision pass") + \
                f", {int(over.sum())} frames over the tolerance"  # fmt: skip
            if not self._round(rows, termed, mult, exact, self.hands if what == "hands" else self.bones + self.hands):
                out.diverged.append(label)
                say(f"{label}: the line search stepped to non-finite corrections; kept the round before")
                return
            depth[rows], share[rows] = self._measure(rows)
            undone = self._keep_best(rows, depth, share, best)
            if len(undone):
                out.worsened.append(f"{label}: {len(undone)} frames left deeper, undone")
            out.rounds = max(out.rounds, n_round)
            fresh = (depth > 0) & (mult == 0)
            mult[fresh] = step**i_pass  # frames pushed into contact join at this pass's level
            # frames a full round started over a tolerance and left no shallower than STALL_SHARE of their depth
            stalled = rows[over[rows] & (depth[rows] > np.maximum(cfg.collision_tolerance_m, STALL_SHARE * start)) & ~exact[rows]]
            stalled = stalled if what == "all" else stalled[:0]
            if len(stalled):
                exact[stalled] = True
                out.stalled.append(label)
                out.exact_frames += [int(f) for f in stalled]
            say(f"{label}: deepest {1000 * depth.max():.1f} mm after" + (f", {len(stalled)} stalled" if len(stalled) else "")
                + (f", {len(undone)} frames undone" if len(undone) else ""))
            if cfg.collision_restart and n_round >= 2 and i_pass < len(passes) - 1:  # a restart needs a round after it
                self._restart_stuck(rows, start, over, depth, share, restarts, f"{label}: ", say)

    def _copy_rows(self, rows: np.ndarray, src: list, dst: list) -> None:
        """Copy frames ``rows`` of the tensors ``src`` into ``dst`` (in place, no gradient)."""
        if len(rows):
            i = torch.as_tensor(rows, device=self.dev)
            with torch.no_grad():
                for p, q in zip(src, dst):
                    q.index_copy_(0, i, p.detach().index_select(0, i))

    def _keep_best(self, rows, depth, share, best) -> np.ndarray:
        """Per frame of ``rows`` (moved by a round; restarted frames are judged by the round after), keep
        the answer if it is within ``collision_tolerance_m`` or no deeper than the frame's best so far,
        else go back to the best (L-BFGS stepped into a worse basin there, or a restart did not pay): the
        window solver's undo of a round, per frame. Each frame's depth reads only its own corrections, so
        the best depths come back with it. ``best`` ``(corrections, depth (T,), share (T,))`` and
        ``depth``/``share`` are updated in place; returns the frames sent back."""
        keep = (depth[rows] <= self.cfg.collision_tolerance_m) | (depth[rows] <= best[1][rows])
        back, ahead = rows[~keep], rows[keep]
        self._copy_rows(back, best[0], self.params)
        self._forget(back)
        self._copy_rows(ahead, self.params, best[0])
        depth[back], share[back] = best[1][back], best[2][back]
        best[1][ahead], best[2][ahead] = depth[ahead], share[ahead]
        return back

    def _over(self, depth: np.ndarray, share: np.ndarray) -> np.ndarray:
        """Frames over a tolerance: deepest vertex over ``collision_tolerance_m`` or penetrating share over
        ``collision_share_tolerance``."""
        return (depth > self.cfg.collision_tolerance_m) | (share > self.cfg.collision_share_tolerance)

    def _restart_stuck(self, rows, start, over, depth, share, restarts, label: str, say) -> None:
        """Restart the stuck frames of the round that moved ``rows`` (started at depths ``start``): frames it
        started and left over a tolerance, moved by less than ``1 - STUCK_SHARE`` of their depth (interlocked
        hands, whose two pushes oppose each other), each at most ``MAX_RESTARTS`` times. Each run of frames
        over the tolerance that holds one starts the next round from the straight line between the frames
        around it, as in the window solver, where a window bounds the run; a longer run than ``cfg.window``
        restarts only its stuck frames, so that no more than a window's motion is replaced.
        ``depth``/``share``/``restarts`` ``(T,)`` are updated in place."""
        cfg = self.cfg
        deep = self._over(depth, share)
        stuck = np.zeros(self.T, bool)
        stuck[rows] = over[rows] & deep[rows] & (depth[rows] > STUCK_SHARE * start)
        stuck &= restarts < MAX_RESTARTS
        if not stuck.any():
            return
        run_id = np.cumsum(np.r_[True, deep[1:] != deep[:-1]])
        move = stuck.copy()
        for a, b in runs(deep & np.isin(run_id, run_id[stuck])):
            if b - a <= max(int(cfg.window), 1):
                move[a:b] = True
        if restart_from_neighbours(self.params, move):
            restarts[move] += 1
            at = np.flatnonzero(dilate(move, SMOOTH_REACH))
            depth[at], share[at] = self._measure(at)
            say(f"{label}{int(stuck.sum())} frames stuck, {int(move.sum())} restarted from their neighbours")

    def _round(self, rows: np.ndarray, termed: np.ndarray, mult: np.ndarray, exact: np.ndarray, variables: list) -> bool:
        """One collision pass: L-BFGS (one run, or one per block of ``rows`` by ``cfg.take_step``) over
        ``variables`` (the openings alone in the hands' pass, else the bones' corrections too) at frames
        ``rows`` (the others held), on the skeleton energy plus ``collision_weight`` x ``mult`` times the
        collision term of frames ``termed`` (held planes located here, or located at every evaluation
        where ``exact``). False (the corrections restored) when the line search stepped to non-finite
        values."""
        cfg, dev, collide, acts, P = self.cfg, self.dev, self.collide, self.acts, PARAMS_PER_ACTOR
        params = self.params
        saved = [p.detach().clone() for p in params]
        held_rows, exact_rows = termed[~exact[termed]], termed[exact[termed]]
        held_rows, held = self._locate(held_rows)  # per chunk (first row of it in `order`, its length, its contacts)
        order = np.concatenate([held_rows, exact_rows])  # the rows posed with the gradient, in this order
        order_t = torch.as_tensor(order, device=dev)
        w = torch.as_tensor(cfg.collision_weight * mult[order], dtype=params[0].dtype, device=dev)
        frozen = np.ones(self.T, bool)
        frozen[rows] = False
        per_frame = cfg.take_step == "runs"

        def add(e, first, n, term):  # the collision term of `order[first : first + n]`, `term (n,)`
            return e.index_add(0, order_t[first : first + n], term) if per_frame else e + term.sum()

        def energy():  # the round's energy: a 0-d tensor, or per frame (T,) for block_lbfgs
            e, rots = self.energy(params, self.sl, self.none, self.none, per_frame=per_frame)
            if len(order):
                posed = [a.rig.pose(rots[k].index_select(0, order_t), a.transl0[order_t] + params[P * k + 1].index_select(0, order_t),
                                    False, params[P * k + 2].index_select(0, order_t)) for k, a in enumerate(acts)]  # fmt: skip

                def at(first):  # the collision term's batch row f is posed row first + f
                    return lambda body, f, v: acts[body].rig.skin_at(posed[body], torch.as_tensor(f, device=dev) + first, v)

                for first, n, lin in held:
                    e = add(e, first, n, w[first : first + n] * collide.linear_loss(lin, at(first), device=dev))
                for c0 in range(0, len(exact_rows), CHUNK):
                    sub = exact_rows[c0 : c0 + CHUNK]
                    with torch.no_grad():
                        vs = [p.vertices for p in self.pose_bodies(params, self.sl, torch.as_tensor(sub, device=dev))]
                    first = len(held_rows) + c0
                    loss = collide(vs[0], vs[1], keys=sub, points=at(first)).loss
                    e = add(e, first, len(sub), w[first : first + len(sub)] * loss)
            return e

        if per_frame:
            block, energy_block, n_blocks = frame_blocks(~frozen, SMOOTH_REACH)
            block_lbfgs(variables, energy, block, energy_block, n_blocks, cfg.take_iterations)
        else:
            frozen_t = torch.as_tensor(np.flatnonzero(frozen), device=dev) if frozen.any() else None
            opt = torch.optim.LBFGS(variables, lr=1.0, max_iter=cfg.take_iterations, line_search_fn="strong_wolfe")

            def closure():
                if not all_finite(params):
                    raise Diverged
                opt.zero_grad()
                e = energy()
                e.backward()
                if frozen_t is not None:  # the held frames: no step
                    for q in params:
                        if q.grad is not None:
                            q.grad.index_fill_(0, frozen_t, 0.0)
                return e

            try:
                opt.step(closure)
            except Diverged:
                pass
        if not all_finite(params):
            restore(params, saved)
            return False
        return True

    # ---- depths and contacts, CHUNK frames at a time

    def _locate(self, rows: np.ndarray) -> tuple[np.ndarray, list]:
        """The contacts of frames ``rows`` held as planes: ``(order, held)``, ``order`` the same frames
        regrouped, ``held`` per group ``(first, n, lin)`` whose frames are ``order[first : first + n]``
        and ``lin`` their :class:`~dualhuman_builder.geometry.collision.Linearised`. Frames whose
        contacts :meth:`_measure` located at their current corrections reuse them; the rest are located
        here (a round holds contacts only when ``cfg.collision_hold_contacts``)."""
        order, held, groups = [], [], {}
        for f in rows.tolist():
            located = self.located.get(f)
            groups.setdefault(id(located), (located, []))[1].append(f)
        fresh = np.asarray(groups.pop(id(None), (None, []))[1], np.int64)
        parts = list(groups.values()) + [(self.check(self.params, self.sl, sub)[1], sub.tolist())
                                         for sub in (fresh[c0 : c0 + CHUNK] for c0 in range(0, len(fresh), CHUNK))]  # fmt: skip
        for located, fs in parts:
            held.append((len(order), len(fs), located.take(fs)))
            order += fs
        return np.asarray(order, np.int64), held

    def _forget(self, rows: np.ndarray) -> None:
        """Drop the contacts located at frames ``rows``, whose corrections changed since."""
        for f in np.asarray(rows).tolist():
            self.located.pop(f, None)

    def _measure(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The deepest vertex (m) and penetrating share ``(len(rows),)`` each of frames ``rows`` (sorted)
        at the current corrections (:meth:`~dualhuman_builder.fit.problem.FitProblem.check`). When
        contacts are held, the query that measures them also locates their contacts, kept for the next
        :meth:`_locate` (the poses it would query are these, unless a frame moves first: see
        :meth:`_forget`)."""
        depth, share = np.zeros(len(rows)), np.zeros(len(rows))
        for c0 in range(0, len(rows), CHUNK):
            sub = rows[c0 : c0 + CHUNK]
            pen, located = self.check(self.params, self.sl, sub)
            if located is not None:
                self.located.update((f, located) for f in sub.tolist())
            depth[c0 : c0 + len(sub)], share[c0 : c0 + len(sub)] = pen["max_depth_m"], pen["share"]
        return depth, share

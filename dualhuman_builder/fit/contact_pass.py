"""The contact pass of one window (:class:`ContactPass`), after its collision passes: keep the contacts
the data supports.

The collision term only pushes: a hand the suit and trackers put a few millimetres from the partner's
hand stays there, and at the contact threshold (20 mm, :mod:`dualhuman_builder.contacts`) the band of
vertices labelled in contact then shrinks by those millimetres. Where the fitted surfaces come within
``cfg.contact_reach_m`` of each other without touching (the inputs put them there, so a contact is what
the data says), this pass pulls the ``cfg.contact_pairs`` nearest vertex pairs of each such frame to
``cfg.contact_gap_m`` apart, each by a squared residual over ``cfg.sigma_contact_gap_m`` added to the
skeleton energy (so the trackers and the suit still weigh against the pull), and the collision term, held
over the same contacts (:meth:`~dualhuman_builder.geometry.collision.CollisionTerm.linearise`, with the reach
as the margin) at the last collision round's weight, keeps the pull from pushing anything in. The pass
moves only those frames and the ``SMOOTH_REACH`` frames on either side; it is undone when it leaves any
frame deeper than the tolerance and deeper than it found it, so the penetration goals stand as the
collision passes left them. Units: metres.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from dualhuman_builder.fit.collision_rounds import SMOOTH_REACH, dilate, restore
from dualhuman_builder.fit.problem import PARAMS_PER_ACTOR, FitProblem, Window


def nearest_pairs(lin, reach_m: float, pairs: int, touching_m: float) -> np.ndarray:
    """Indices into ``lin.contacts`` (a :class:`~dualhuman_builder.geometry.collision.Linearised` located
    with a margin of at least ``reach_m``) of the ``pairs`` nearest outside vertices of each frame whose
    two bodies come within ``reach_m`` but no closer than ``touching_m`` and where no vertex is inside the
    other body (a frame the collision passes settle is theirs); sorted."""
    c = lin.contacts
    gap = -np.asarray(c.depth, dtype=np.float64)  # > 0 outside
    chosen = []
    for f in np.unique(c.frame):
        at = np.flatnonzero(c.frame == f)
        g = gap[at]
        if (g <= 0).any() or g.min() > reach_m or g.min() <= touching_m:
            continue
        chosen.append(at[np.argsort(g, kind="stable")[:pairs]])
    return np.sort(np.concatenate(chosen)) if chosen else np.zeros(0, np.int64)


class ContactPass:
    """The contact pass of window ``win`` of ``problem`` (see the module docstring): :meth:`run` moves
    ``win.params`` in place and returns the window's ``(depth, share)`` ``(W,)`` after it, or None when
    it moved nothing (no frame to pull, or the pass was undone)."""

    def __init__(self, problem: FitProblem, win: Window, say: Callable[[str], None]):
        self.problem, self.win, self.say, self.cfg = problem, win, say, problem.cfg

    def run(self) -> tuple[np.ndarray, np.ndarray] | None:
        problem, win, cfg = self.problem, self.win, self.cfg
        collide, dev, P = problem.collide, problem.dev, PARAMS_PER_ACTOR
        W = win.s1 - win.s0
        reach = min(cfg.contact_reach_m, collide.band, collide.pad)
        with torch.no_grad():
            vs = [p.vertices for p in problem.pose_bodies(win.params, win.sl, slice(None))]
            lin = collide.linearise(vs[0], vs[1], keys=range(win.s0, win.s1), margin_m=reach)
        pick = nearest_pairs(lin, reach, cfg.contact_pairs, cfg.contact_gap_m)
        if not len(pick):
            return None
        pulled = np.unique(lin.contacts.frame[pick])
        moving = dilate(np.isin(np.arange(W), pulled), SMOOTH_REACH)
        rows = np.flatnonzero(moving)  # window rows the pass moves and reads
        before = (lin.max_depth_m.copy(), lin.share.copy())
        held = lin.subset(rows)  # the collision term's contacts, renumbered over `rows`
        row_of = np.full(W, -1, np.int64)
        row_of[rows] = np.arange(len(rows))
        c = lin.contacts
        q_body = torch.as_tensor(np.where(c.side[pick] == 1, 0, 1), device=dev)  # side 1: a vertex of a against b
        q_row = torch.as_tensor(row_of[c.frame[pick]], device=dev)
        q_vert = torch.as_tensor(c.vert[pick], device=dev)
        corners = torch.as_tensor(collide.obstacle_faces[c.face[pick]], device=dev)  # (M, 3)
        bary = torch.as_tensor(c.bary[pick], device=dev, dtype=torch.float32)
        normal = torch.as_tensor(lin.normals[pick], device=dev, dtype=torch.float32)
        rows_t = torch.as_tensor(rows, device=dev)
        frozen = torch.as_tensor(np.flatnonzero(~moving), device=dev) if not moving.all() else None
        weight = cfg.collision_weight * cfg.collision_weight_step ** (1 + max(int(cfg.collision_rounds), 1))
        saved = [p.detach().clone() for p in win.params]
        bones = [p for k in range(len(problem.acts)) for p in win.params[P * k : P * k + 2]]
        hands = [win.params[P * k + 2] for k in range(len(problem.acts))] if cfg.hand_opening else []
        opt = torch.optim.LBFGS(bones + hands, lr=1.0, max_iter=cfg.contact_iterations, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            e, rots = problem.energy(win.params, win.sl, win.ctxs, win.afters)
            posed = [a.rig.pose(rots[k].index_select(0, rows_t),
                                a.transl0[win.s0 + rows_t] + win.params[P * k + 1].index_select(0, rows_t), False,
                                win.params[P * k + 2].index_select(0, rows_t))
                     for k, a in enumerate(problem.acts)]  # fmt: skip

            def points(body, f, v):
                return problem.acts[body].rig.skin_at(posed[body], torch.as_tensor(f, device=dev), v)

            gap = torch.zeros(len(pick), device=dev)
            for body in (0, 1):
                m = q_body == body
                if bool(m.any()):
                    p = points(body, q_row[m], q_vert[m])
                    x = points(1 - body, q_row[m].repeat_interleave(3), corners[m].reshape(-1)).reshape(-1, 3, 3)
                    gap[m] = ((p - (bary[m, :, None] * x).sum(1)) * normal[m]).sum(1)
            pull = torch.relu(gap - cfg.contact_gap_m).pow(2).sum() / cfg.sigma_contact_gap_m**2
            e = e + pull + weight * collide.linear_loss(held, points, device=dev).sum()
            e.backward()
            if frozen is not None:
                for q in win.params:
                    if q.grad is not None:
                        q.grad.index_fill_(0, frozen, 0.0)
            return e

        opt.step(closure)
        if not all(bool(torch.isfinite(p).all()) for p in win.params):
            restore(win.params, saved)
            return None
        pen, _ = problem.check(win.params, win.sl)
        worse = (pen["max_depth_m"] > np.maximum(before[0], cfg.collision_tolerance_m)) | \
            (pen["share"] > np.maximum(before[1], cfg.collision_share_tolerance))  # fmt: skip
        if worse.any():
            restore(win.params, saved)
            self.say(f"frames {win.s0}-{win.s1 - 1}: the contact pass left {int(worse.sum())} frames deeper; undone")
            return None
        self.say(f"frames {win.s0}-{win.s1 - 1}: contact pass on {len(pulled)} frames")
        return pen["max_depth_m"], pen["share"]

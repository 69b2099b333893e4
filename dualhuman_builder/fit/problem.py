"""One take's fitting problem: both actors' tensors and the collision term (:class:`FitProblem`), and the
variables of one window (:class:`Window`).

The variables are, per actor, ``PARAMS_PER_ACTOR`` tensors over a window's ``W`` frames: the corrections
``delta (W, 23, 3)`` (world-frame rotation vectors on the retargeted bones, rad), ``dtransl (W, 3)`` (m,
on the fused pelvis) and the hand openings ``opening (W, 4)``; a list of them, actor after actor, is
what the energies, poses and depth checks below take (``ps``). Frames are timeline frames; ``psl`` is
the slice of them that ``ps``'s rows cover.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.fit.actors import ActorStack, ActorTensors
from dualhuman_builder.fit.config import FitConfig
from dualhuman_builder.fit.energy import context_of, skeleton_energy, stack_contexts
from dualhuman_builder.fit.inputs import ActorInput
from dualhuman_builder.fit.skeleton import sole_vertices, torso_vertices

#: optimised tensors per actor: delta, dtransl, opening
PARAMS_PER_ACTOR = 3


def timeline_rows(sl: slice, idx):
    """Timeline frames of window rows ``idx`` (a slice of the window or an index tensor); ``sl``: the
    window's timeline frames."""
    if isinstance(idx, slice):
        return slice(sl.start + (idx.start or 0), sl.start + (idx.stop if idx.stop is not None else sl.stop - sl.start))
    return sl.start + idx


@dataclass
class LocatedContacts:
    """Contacts located at some rows of a window's span: ``lin`` (a
    :class:`~dualhuman_builder.geometry.collision.Linearised`) whose batch rows are the span rows ``rows``
    (sorted)."""

    lin: object
    rows: np.ndarray

    def take(self, rows) -> object:
        """The contacts of span rows ``rows`` (each located here), renumbered ``0 .. len(rows) - 1``."""
        rows = np.asarray(rows, np.int64)
        at = np.minimum(np.searchsorted(self.rows, rows), max(len(self.rows) - 1, 0))
        if len(rows) and not np.array_equal(self.rows[at], rows):
            raise RuntimeError(f"span rows {np.setdiff1d(rows, self.rows).tolist()} were not located")
        return self.lin.subset(at)


class FitProblem:
    """Both actors' tensors (:class:`~dualhuman_builder.fit.actors.ActorTensors`, stacked as
    :class:`~dualhuman_builder.fit.actors.ActorStack`) and the collision term for one take of ``T``
    frames; poses, skeleton energies and depth checks of both bodies at given corrections."""

    def __init__(self, model, inputs: list[ActorInput], fps: float, cfg: FitConfig, threads: int | None = None):
        """``threads``: the collision term's query threads (None: its default, the CPUs up to 8); worker
        processes build theirs with the same (:mod:`~dualhuman_builder.fit.workers`)."""
        from dualhuman_builder.geometry.collision import CollisionTerm

        self.cfg, self.fps, self.T, self.threads = cfg, fps, len(inputs[0].seg_rot), threads
        soles = sole_vertices(model)
        slots = max(len(inp.trk_segment) for inp in inputs)
        self.acts = [ActorTensors(model, inp, fps, cfg, soles, slots) for inp in inputs]
        self.stack = ActorStack(self.acts)
        #: ``(V,)`` bool: the vertices the hand openings move (one topology and skinning for both actors)
        self.fingers = self.acts[0].rig.opening_vertices
        self.dev = torch.device(cfg.device)
        # The collision term (docs/design/fit-collision.md, docs/decisions/0020-collision-term-cost.md):
        # - a 3 cm band of exact signed distances (the broad-phase boxes grow by 1 cm): the same depths as
        #   a narrower band, but signs stay known over larger moves between L-BFGS evaluations
        #   (benchmarks/probes/probe_collision_band.py compares bands);
        # - the coincidence guard compares the torsos' centroids (docs/decisions/0014-hand-openings-and-torso-guard.md);
        # - the sign bound's parts are each hand's fingers and the rest, so the hands' pass, which moves
        #   the fingers alone, keeps the signs elsewhere;
        # - the pooled meshes' trees are built over the first actor's rest pose, so the answers do not
        #   depend on which segments a process fitted before (CollisionTerm's ``bvh_points``).
        self.collide = None
        if cfg.collision and len(self.acts) == 2:
            with torch.no_grad():
                eye = torch.eye(3, device=self.dev).expand(1, len(MVN_SEGMENTS), 3, 3)
                rest = self.acts[0].rig.pose(eye, torch.zeros(1, 3, device=self.dev), True).vertices[0].cpu().numpy()
            self.collide = CollisionTerm(model.faces.cpu().numpy(), band_m=0.03, pad_m=0.01,
                                         guard_vertices=torso_vertices(model), bvh_points=rest, threads=threads,
                                         parts=self.acts[0].rig.opening_groups)  # fmt: skip

    def pose_bodies(self, ps: list, psl: slice, idx) -> list:
        """Both actors' posed bodies (:class:`~dualhuman_builder.fit.skeleton.Posed`, with vertices) at
        rows ``idx`` (a slice or index tensor) of the corrections ``ps`` of timeline frames ``psl``."""
        P = PARAMS_PER_ACTOR
        return [a.pose(ps[P * k][idx], ps[P * k + 1][idx], timeline_rows(psl, idx), True, ps[P * k + 2][idx])[1]
                for k, a in enumerate(self.acts)]  # fmt: skip

    def energy(self, ps: list, psl: slice, ctxs: list, afters: list, per_frame: bool = False) -> tuple:
        """Both actors' skeleton energy (:func:`~dualhuman_builder.fit.energy.skeleton_energy`, at once;
        per frame ``(n,)`` with ``per_frame``) of the corrections ``ps`` of timeline frames ``psl`` with
        the per-actor contexts ``ctxs`` before and ``afters`` after them (each None or a context), and
        their driven bones' rotations (per actor, ``(n, 23, 3, 3)``)."""
        P = PARAMS_PER_ACTOR
        e, rot = skeleton_energy(self.stack, *(torch.stack(ps[j::P]) for j in range(P)), psl, stack_contexts(ctxs),
                                 self.cfg, self.fps, stack_contexts(afters), per_frame)  # fmt: skip
        return e, rot.unbind(0)

    def skeleton_pass(self, ps: list, psl: slice, ctxs: list, afters: list) -> None:
        """L-BFGS on the skeleton energy (:meth:`energy`) of timeline frames ``psl`` over the bones'
        corrections of ``ps`` (``delta``, ``dtransl``; no term there reads the fingers), ``cfg.iterations``
        iterations, in place."""
        P = PARAMS_PER_ACTOR
        bones = [p for k in range(len(self.acts)) for p in ps[P * k : P * k + 2]]
        opt = torch.optim.LBFGS(bones, lr=1.0, max_iter=self.cfg.iterations, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            e, _ = self.energy(ps, psl, ctxs, afters)
            e.backward()
            return e

        opt.step(closure)

    def check(self, ps: list, psl: slice, rows=None) -> tuple:
        """The depths of timeline frames ``psl`` (only its rows ``rows``, sorted, when given) at the
        corrections ``ps``: ``penetration``'s dict (``max_depth_m``, ``share``, per row checked) and, when
        ``cfg.collision_hold_contacts``, the contacts located there (a :class:`LocatedContacts` the next
        held pass starts from; else None)."""
        cfg, collide = self.cfg, self.collide
        rows = np.arange(psl.stop - psl.start) if rows is None else np.asarray(rows)
        with torch.no_grad():
            idx = slice(None) if len(rows) == psl.stop - psl.start else torch.as_tensor(rows, device=self.dev)
            vs = [p.vertices for p in self.pose_bodies(ps, psl, idx)]
            keys = psl.start + rows
            if not cfg.collision_hold_contacts:
                return collide.penetration(vs[0], vs[1], keys=keys), None
            lin = collide.linearise(vs[0], vs[1], keys=keys, margin_m=cfg.collision_margin_m)
            return {"max_depth_m": lin.max_depth_m, "share": lin.share}, LocatedContacts(lin, rows)

    def depths(self, s0: int, s1: int, delta: list, dtransl: list, opening: list, origin: int) -> tuple[np.ndarray, np.ndarray]:
        """The deepest vertex (m) and the penetrating share of timeline frames ``s0 .. s1 - 1`` ``(n,)``
        each, for per-actor corrections ``delta``/``dtransl``/``opening`` (arrays or tensors whose row
        0 is timeline frame ``origin``), 64 frames at a time."""
        depth, share = np.zeros(s1 - s0), np.zeros(s1 - s0)
        for c0 in range(s0, s1, 64):
            sl = slice(c0, min(c0 + 64, s1))
            rows = slice(sl.start - origin, sl.stop - origin)
            with torch.no_grad():
                vs = [a.pose(*(torch.as_tensor(x[k][rows], device=self.dev) for x in (delta, dtransl)), sl, True,
                             torch.as_tensor(opening[k][rows], device=self.dev))[1].vertices for k, a in enumerate(self.acts)]  # fmt: skip
                pen = self.collide.penetration(vs[0], vs[1], keys=range(sl.start, sl.stop))
            depth[sl.start - s0 : sl.stop - s0] = pen["max_depth_m"]
            share[sl.start - s0 : sl.stop - s0] = pen["share"]
        return depth, share


@dataclass
class Window:
    """One window's variables: timeline frames ``s0 .. s1 - 1`` (``W`` of them), ``params`` (the
    corrections, ``PARAMS_PER_ACTOR`` tensors per actor, each ``(W, ...)``, optimised in place) and the
    per-actor contexts its smoothness terms read before (``ctxs``) and after (``afters``) it, each None
    or fixed."""

    s0: int
    s1: int
    params: list
    ctxs: list
    afters: list

    @property
    def sl(self) -> slice:
        """The window's timeline frames."""
        return slice(self.s0, self.s1)

    def held_rows(self, act: ActorTensors, k: int, lo: int, hi: int):
        """The context of actor ``k`` (``act``)'s window rows ``lo .. hi - 1`` as they are now, without
        gradient (the context of a span of the window; None when empty)."""
        if hi <= lo:
            return None
        P = PARAMS_PER_ACTOR
        with torch.no_grad():
            return context_of(act, *(self.params[P * k + j][lo:hi] for j in range(P)), slice(self.s0 + lo, self.s0 + hi))

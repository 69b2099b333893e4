"""L-BFGS over independent blocks of frames, all evaluated at once (:func:`block_lbfgs`), and the blocks
of a set of moving frames (:func:`frame_blocks`).

The take solver moves many separate runs of frames in one collision round. One L-BFGS run over all of
them (``torch.optim.LBFGS``) shares one step length and one curvature history: a run that needs a short
step shortens everyone's, and one decision taken differently moves every frame. Here each *block* (a
run of moving frames, runs closer than the energy's reach merged) has its own curvature pairs, initial
scaling, Armijo backtracking line search and stopping test, while every evaluation still poses all
frames at once: one batched program, which is what a GPU needs.

Contract of the objective: ``evaluate()`` sets nothing, reads the variables as they are, and returns the
energy per timeline frame ``(T,)`` (a term spanning several frames assigned to one of them, so that
every term touching a block's variables lands on a frame of that block's *energy rows*: see
:func:`frame_blocks`). Variables are tensors whose first axis is the timeline frame; only the frames of
a block move. Mirrors ``torch.optim.LBFGS``'s defaults (first step ``min(1, 1 / |g|_1)``, history 100,
``tolerance_grad`` 1e-7, ``tolerance_change`` 1e-9, each block's evaluations at most 5/4 of the
iterations: counted per block, so that no block's answer depends on another's). The line search is
per block: a step that does not decrease the energy enough (Armijo) shrinks by quadratic
interpolation; a first step that does, but leaves the slope steeper than ``C2`` of the start's (strong
Wolfe's curvature condition unmet), grows ``EXPAND`` times while the energy keeps falling, as torch's
strong Wolfe search extrapolates. Its zoom, which needs a bracket per block, is left out; a block whose
curvature pair fails ``y.s > 0`` just skips that pair.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

#: sufficient decrease constant of the line search (Armijo's c1, as torch's strong Wolfe search)
C1 = 1e-4
#: backtracking steps per iteration at most; a block that finds no decrease in them stops
MAX_BACKTRACKS = 10
#: the curvature condition's constant (strong Wolfe's c2, as torch's): a block whose first trial step
#: leaves the slope along its direction steeper than this share of the start's tries a longer one
C2 = 0.9
#: a longer step is this many times the last accepted one, at most ``MAX_EXPANSIONS`` times per iteration
EXPAND = 4.0
MAX_EXPANSIONS = 4


def frame_blocks(moving: np.ndarray, reach: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The blocks of the moving frames ``moving (T,)`` bool for an energy whose terms span at most
    ``reach + 1`` consecutive frames (a second difference: ``reach`` 2): runs of moving frames fewer
    than ``reach`` frames apart are one block, so that no term reads two blocks. Returns
    ``(block (T,), energy_block (T,), n)``: ``block`` each moving frame's block (``-1`` elsewhere);
    ``energy_block`` the block a frame's energy counts to (the nearest block within ``reach - 1`` frames
    for a held frame: a term centred there reads that block; ``-1``: it reads none), ``n`` blocks."""
    moving = np.asarray(moving, bool)
    T = len(moving)
    block = np.full(T, -1, np.int64)
    energy = np.full(T, -1, np.int64)
    at = np.flatnonzero(moving)
    if not len(at):
        return block, energy, 0
    new = np.r_[True, np.diff(at) > reach]  # a gap of `reach` held frames or more starts a new block
    block[at] = np.cumsum(new) - 1
    energy[at] = block[at]
    for d in range(1, reach):  # held frames next to a block count to it (the gaps are >= reach, so no ties)
        for side in (-d, d):
            src = at + side
            ok = (src >= 0) & (src < T)
            src, b = src[ok], block[at[ok]]
            free = energy[src] < 0
            energy[src[free]] = b[free]
    return block, energy, int(new.sum())


def _per_block(values: torch.Tensor, index: torch.Tensor, n: int) -> torch.Tensor:
    """Sums of ``values (R,)`` per block ``index (R,)`` in ``0 .. n`` (``n``: none), ``(n,)``."""
    return torch.zeros(n + 1, dtype=values.dtype, device=values.device).index_add_(0, index, values)[:n]


def _block_max(values: torch.Tensor, index: torch.Tensor, n: int) -> torch.Tensor:
    """Maxima of ``values (R,)`` (>= 0) per block ``index (R,)``, ``(n,)``."""
    out = torch.zeros(n + 1, dtype=values.dtype, device=values.device)
    return out.scatter_reduce_(0, index, values, "amax", include_self=True)[:n]


def block_lbfgs(variables: list, evaluate: Callable[[], torch.Tensor], block: np.ndarray, energy_block: np.ndarray,
                n_blocks: int, max_iter: int, max_eval: int | None = None, history: int = 100, tolerance_grad: float = 1e-7,
                tolerance_change: float = 1e-9) -> dict:
    """Minimise the energy ``evaluate()`` (per frame, ``(T,)``; see the module docstring) over the rows
    ``block >= 0`` of ``variables`` (tensors ``(T, ...)``, moved in place), each block of
    :func:`frame_blocks` its own L-BFGS run, every evaluation shared; each block stops after ``max_iter``
    iterations or ``max_eval`` evaluations (default ``max_iter * 5 // 4``, torch's). A trial whose energy is not finite
    counts as no decrease (the step shrinks). Returns ``{"iterations", "evaluations", "energy" (n,)
    per block at the end, "stopped" (n,) bool: the blocks that met a stopping test}``."""
    dev = variables[0].device
    rows_np = np.flatnonzero(np.asarray(block) >= 0)
    if n_blocks == 0 or not len(rows_np):
        return {"iterations": 0, "evaluations": 0, "energy": np.zeros(0), "stopped": np.zeros(0, bool)}
    rows = torch.as_tensor(rows_np, device=dev)
    rb = torch.as_tensor(np.asarray(block)[rows_np], device=dev)  # (R,) block of each moving row
    eb = torch.as_tensor(np.where(np.asarray(energy_block) >= 0, energy_block, n_blocks), device=dev)  # (T,)
    widths = [int(np.prod(p.shape[1:])) for p in variables]
    n = n_blocks

    def flat(tensors) -> torch.Tensor:  # (R, D): the moving rows of each tensor, side by side
        return torch.cat([t.index_select(0, rows).reshape(len(rows_np), -1) for t in tensors], 1)

    def put(x: torch.Tensor) -> None:
        with torch.no_grad():
            for p, part in zip(variables, torch.split(x, widths, 1)):
                p.index_copy_(0, rows, part.reshape(-1, *p.shape[1:]).to(p.dtype))

    def at(x: torch.Tensor):
        put(x)
        for p in variables:
            p.grad = None
        e = evaluate()
        e.sum().backward()
        g = flat([p.grad if p.grad is not None else torch.zeros_like(p) for p in variables])
        return _per_block(e.detach(), eb, n), g

    def dot(a, b):  # per block
        return _per_block((a * b).sum(1), rb, n)

    with torch.no_grad():
        x = flat([p.detach() for p in variables]).clone()
    f, g = at(x)
    evals, max_eval = 1, max_iter * 5 // 4 if max_eval is None else max_eval
    spent = torch.ones(n, dtype=torch.int64, device=dev)  # per block, the evaluations it has tried steps in
    active = _block_max(g.abs().amax(1), rb, n) > tolerance_grad
    S, Y, rho = [], [], []
    h_diag = torch.ones(n, dtype=x.dtype, device=dev)
    it = 0
    while it < max_iter and bool(active.any()):
        it += 1
        # two-loop recursion, per block (a pair with rho 0 is one the block skipped)
        q = -g
        alphas = []
        for s, y, r in zip(reversed(S), reversed(Y), reversed(rho)):
            a = r * dot(s, q)
            alphas.append(a)
            q = q - a[rb, None] * y
        d = q * h_diag[rb, None]
        for s, y, r, a in zip(S, Y, rho, reversed(alphas)):
            d = d + (a - r * dot(y, d))[rb, None] * s
        d = d * active[rb, None]
        gtd = dot(g, d)
        active &= gtd < -tolerance_change  # no descent direction left: that block stops (as torch's run)
        if not bool(active.any()):
            break
        t = torch.ones(n, dtype=x.dtype, device=dev)
        if it == 1:  # torch's first step: min(1, 1 / |g|_1)
            t = torch.clamp(1.0 / _per_block(g.abs().sum(1), rb, n).clamp_min(1e-30), max=1.0)
        pending, accepted = active.clone(), torch.zeros_like(active)
        f_new, g_new = f.clone(), g.clone()
        for i_ls in range(MAX_BACKTRACKS):
            step = torch.where(pending | accepted, t, torch.zeros_like(t))
            f_try, g_try = at(x + step[rb, None] * d)
            evals += 1
            spent += pending
            ok = pending & torch.isfinite(f_try) & (f_try <= f + C1 * t * gtd)
            if bool(ok.any()):
                f_new = torch.where(ok, f_try, f_new)
                g_new = torch.where(ok[rb, None], g_try, g_new)
            accepted |= ok
            pending &= ~ok
            if i_ls == 0:  # blocks whose first trial decreased enough but still descend steeply: a longer step
                grow = ok & (dot(g_try, d) < C2 * gtd)
            pending &= spent < max_eval
            if not bool(pending.any()):
                break
            # the minimum of the quadratic through f(0), f'(0) and f(t), kept within [0.1 t, 0.5 t]
            curv = f_try - f - gtd * t
            t_q = torch.where(torch.isfinite(curv) & (curv > 0), -gtd * t * t / (2 * curv.clamp_min(1e-30)), 0.1 * t)
            t = torch.where(pending, torch.minimum(torch.maximum(t_q, 0.1 * t), 0.5 * t), t)
        for _ in range(MAX_EXPANSIONS):  # the strong Wolfe search's extrapolation, per block
            grow &= spent < max_eval
            if not bool(grow.any()):
                break
            t_try = torch.where(grow, t * EXPAND, t)
            f_try, g_try = at(x + torch.where(accepted, t_try, torch.zeros_like(t))[rb, None] * d)
            evals += 1
            spent += grow
            ok = grow & torch.isfinite(f_try) & (f_try <= f + C1 * t_try * gtd) & (f_try < f_new)
            f_new = torch.where(ok, f_try, f_new)
            g_new = torch.where(ok[rb, None], g_try, g_new)
            t = torch.where(ok, t_try, t)
            grow = ok & (dot(g_try, d) < C2 * gtd)
        step = torch.where(accepted, t, torch.zeros_like(t))
        s = step[rb, None] * d
        y = g_new - g
        ys = dot(y, s)
        ok = accepted & (ys > 1e-10)
        S.append(s)
        Y.append(y)
        rho.append(torch.where(ok, 1.0 / ys.clamp_min(1e-30), torch.zeros_like(ys)))
        if len(S) > history:
            S.pop(0), Y.pop(0), rho.pop(0)
        h_diag = torch.where(ok, ys / dot(y, y).clamp_min(1e-30), h_diag)
        moved = _block_max(s.abs().amax(1), rb, n)
        stop = ~accepted | (_block_max(g_new.abs().amax(1), rb, n) <= tolerance_grad) | (moved <= tolerance_change) \
            | ((f_new - f).abs() < tolerance_change)
        active &= ~stop & (spent < max_eval)
        x, f, g = x + s, f_new, g_new
    put(x)
    for p in variables:
        p.grad = None
    stopped = ~active
    return {"iterations": it, "evaluations": evals, "energy": f.cpu().numpy(), "stopped": stopped.cpu().numpy()}

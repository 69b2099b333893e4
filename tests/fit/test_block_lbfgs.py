"""L-BFGS over independent blocks of frames (:mod:`dualhuman_builder.fit.block_lbfgs`) and the per-frame
skeleton energy it reads."""

from __future__ import annotations

import numpy as np
import torch

from dualhuman_builder.fit.block_lbfgs import block_lbfgs, frame_blocks

T = 40


def test_runs_closer_than_the_reach_are_one_block_and_held_frames_count_to_the_nearest():
    moving = np.zeros(T, bool)
    moving[3:10] = moving[11:14] = moving[20:30] = moving[32:36] = True  # gaps of 1 and 2 held frames
    block, energy, n = frame_blocks(moving, 2)
    assert n == 3
    assert (block[3:14][moving[3:14]] == 0).all() and block[10] == -1  # one held frame between: one block
    assert (block[20:30] == 1).all() and (block[32:36] == 2).all()
    assert energy[2] == 0 and energy[14] == 0 and energy[15] == -1  # within reach - 1 of the block
    assert energy[30] == 1 and energy[31] == 2  # a gap of two: each held frame to its own side
    assert (block[~moving] == -1).all()
    assert frame_blocks(np.zeros(5, bool), 2)[2] == 0


def _energy_of(scale_b=1.0):
    """A coupled, non-quadratic energy per frame of ``x (T, 3)``: data, second difference (counted to its
    middle frame) and a quartic; frames 20-29 weighed ``scale_b``."""
    g = torch.Generator().manual_seed(0)
    target = torch.randn(T, 3, generator=g)
    scale = torch.ones(T)
    scale[20:30] = scale_b

    def energy(x):
        e = ((x - target) ** 2).sum(1) * scale + x[:, 0] ** 4
        acc = x[2:] - 2 * x[1:-1] + x[:-2]
        return e + torch.nn.functional.pad((acc**2).sum(1) * 5, (1, 1))

    return energy


def _fit(moving, scale_b=1.0, **kw):
    x = torch.zeros(T, 3, requires_grad=True)
    energy = _energy_of(scale_b)
    info = block_lbfgs([x], lambda: energy(x), *frame_blocks(moving, 2), **kw)
    return x.detach(), info


def test_each_block_is_its_own_run_whatever_the_others_do():
    """A block's answer is bit for bit the same whether another block moves with it (here one weighed
    10,000 times more, which needs other steps) or not; held frames keep their values."""
    both = np.zeros(T, bool)
    both[3:14] = both[20:30] = True
    alone = both.copy()
    alone[20:30] = False
    x1, info = _fit(both, 1e4, max_iter=50)
    x2, _ = _fit(alone, max_iter=50)
    assert torch.equal(x1[3:14], x2[3:14])
    assert not torch.equal(x1[20:30], x2[20:30])
    assert x1[~torch.as_tensor(both)].abs().max() == 0
    assert info["stopped"].all() and info["iterations"] > 3


def test_it_reaches_the_minimum_a_long_torch_lbfgs_run_reaches():
    moving = np.zeros(T, bool)
    moving[5:30] = True
    energy = _energy_of()
    x, _ = _fit(moving, max_iter=100)
    y = torch.zeros(T, 3, requires_grad=True)
    opt = torch.optim.LBFGS([y], max_iter=500, line_search_fn="strong_wolfe", tolerance_grad=1e-9)
    held = torch.as_tensor(~moving)

    def closure():
        opt.zero_grad()
        e = energy(y).sum()
        e.backward()
        y.grad[held] = 0
        return e

    opt.step(closure)
    ours, best, start = (float(energy(v).sum()) for v in (x, y.detach(), torch.zeros(T, 3)))
    assert abs(ours - best) <= 1e-4 * (start - best)


def test_a_step_to_a_non_finite_energy_shrinks_instead_of_diverging():
    """An energy that is NaN beyond a wall (log of a negative number) near the start: the first steps
    overshoot into it; the run backtracks and ends finite, lower than it started."""
    moving = np.ones(T, bool)
    x = torch.full((T, 3), 0.5, requires_grad=True)

    def energy():
        return (torch.log(1.0 - x) * -1.0 + 40.0 * (x - 2.0) ** 2).sum(1)

    with torch.no_grad():
        start = float(energy().sum())
    block_lbfgs([x], energy, *frame_blocks(moving, 2), max_iter=20)
    assert torch.isfinite(x).all() and (x < 1).all()
    with torch.no_grad():
        assert float(energy().sum()) < start


def test_a_first_step_that_still_descends_steeply_grows():
    """The first iteration's step is scaled by the gradient (``min(1, 1 / |g|_1)``, as torch's): here a
    move of 1/15 of the way to a steep quadratic's minimum, where the slope is still 14/15 of the
    start's. The line search extrapolates it (as a strong Wolfe search does) until the slope has
    flattened past ``C2``: four times as far."""
    moving = np.ones(5, bool)
    x = torch.zeros(5, 3, requires_grad=True)
    info = block_lbfgs([x], lambda: 1e3 * ((x - 1.0) ** 2).sum(1), *frame_blocks(moving, 2), max_iter=1, max_eval=10)
    assert info["iterations"] == 1 and info["evaluations"] > 2
    assert torch.allclose(x.detach(), torch.full((5, 3), 4 / 15))

"""The take solver (:mod:`dualhuman_builder.fit.take`): the whole take as one problem, with a per-frame
collision schedule instead of the window solver's per-window rules."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from dualhuman_builder.body.model import get_body_model
from dualhuman_builder.fit.fitter import ActorInput, FitConfig, FitError, fit_actors
from dualhuman_builder.fit.collision_rounds import SMOOTH_REACH, dilate
from dualhuman_builder.fit.config import solver_fields
from dualhuman_builder.fit.energy import skeleton_energy
from dualhuman_builder.fit.problem import PARAMS_PER_ACTOR
from dualhuman_builder.fit.take import TakeFitter

FPS = 15.0


@pytest.fixture(scope="module")
def model():
    return get_body_model()


def _step_in(T: int) -> list:
    """Two actors in the rest pose for ``T`` frames, no trackers: b stands 60 cm from a and steps in to
    10 cm at frame ``T // 2`` and back out, so only the frames around it collide."""
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (T, 23, 1))
    pelvis = np.tile([0.0, 0.95, 0.0], (T, 1))
    x = 0.6 - 0.5 * np.exp(-(((np.arange(T) - T // 2) / 3.0) ** 2))
    return [ActorInput(name, {}, quat, pelvis + np.stack([dx, 0 * dx, 0 * dx], 1), np.ones(T, bool), np.zeros((T, 0, 3)),
                       np.zeros((T, 0), bool), np.zeros(0, np.int64), np.zeros((0, 3)),
                       np.tile([[0.1, 0.1, 0.0], [-0.1, 0.1, 0.0]], (T, 1, 1)))
            for name, dx in (("a", np.zeros(T)), ("b", x))]  # fmt: skip


CFG = FitConfig(solver="take", iterations=4, take_iterations=4, collision_rounds=3, hand_opening=False)


@pytest.mark.parametrize("step", ["shared", "runs"])
def test_the_take_solver_pushes_the_bodies_apart_and_leaves_the_frames_far_from_contact_alone(model, monkeypatch, step):
    """The collision rounds move the frames over a tolerance and the two on either side of them; every
    other frame keeps the skeleton pass's answer bit for bit (the fit without the collision term), and
    the deepest penetration falls: with one L-BFGS run over the moving frames and with one per block."""
    T = 40
    inputs = _step_in(T)
    cfg = dataclasses.replace(CFG, take_step=step)
    off = fit_actors(model, inputs, FPS, dataclasses.replace(cfg, collision=False))
    rounds = []
    real = TakeFitter._round

    def spy(self, rows, termed, mult, exact, variables):
        rounds.append(rows.copy())
        return real(self, rows, termed, mult, exact, variables)

    monkeypatch.setattr(TakeFitter, "_round", spy)
    on = fit_actors(model, inputs, FPS, cfg)
    s = on.summary
    assert s["segments"] == 1 and s["processes"] == 1 and s["seams_fitted_again"] == []
    hit = np.flatnonzero(on.frames["penetration depth (mm)/without collision term"] > 0)
    assert len(hit) and hit[0] > 8 and hit[-1] < T - 9  # a few frames in the middle collide
    assert rounds and s["collision_rounds_used"] == len(rounds)
    moved = np.unique(np.concatenate(rounds))
    assert moved.min() >= hit[0] - 2 and moved.max() <= hit[-1] + 2  # over a tolerance, and 2 frames around
    still = np.setdiff1d(np.arange(T), moved)
    for a, b in zip(on.sequence.actors, off.sequence.actors):
        assert np.array_equal(np.asarray(a.pose)[still], np.asarray(b.pose)[still])
        assert np.array_equal(np.asarray(a.transl)[still], np.asarray(b.transl)[still])
    assert s["max_penetration_after_mm"] < 0.5 * s["max_penetration_before_mm"]
    assert s["collision_frames"] == len(hit)


def test_a_frame_left_over_the_tolerance_weighs_one_step_more_in_the_next_round(model, monkeypatch):
    """The schedule is per frame: a frame's collision weight starts at ``collision_weight`` (a step
    ahead where deeper than ``collision_deep_m``) and grows by ``collision_weight_step`` after each round
    that leaves it over a tolerance; a frame that settled keeps its weight and holds still."""
    T = 12
    inputs = _step_in(T)
    seen = []
    real = TakeFitter._round

    def spy(self, rows, termed, mult, exact, variables):
        seen.append((rows.copy(), mult.copy()))
        return real(self, rows, termed, mult, exact, variables)

    monkeypatch.setattr(TakeFitter, "_round", spy)
    # a weak term, so that the first round leaves frames over the tolerance
    cfg = dataclasses.replace(CFG, collision_rounds=3, take_iterations=2, collision_deep_m=0.0, collision_weight=1e3)
    fit_actors(model, inputs, FPS, cfg)
    assert len(seen) >= 2
    (rows1, m1), (rows2, m2) = seen[0], seen[1]
    step = cfg.collision_weight_step
    assert set(np.unique(m1[m1 > 0])) == {1.0}  # every frame in contact starts at the base weight
    again = np.intersect1d(rows1, np.flatnonzero(m1 > 0))
    raised = (m1 > 0) & (m2 == m1 * step)
    assert raised.any() and np.isin(np.flatnonzero(raised), again).all()  # the frames still over went up one step
    assert (m2 >= m1).all()  # never lowered: a settled frame keeps its term
    # round 2 moves the frames over a tolerance (raised, or pushed into contact by round 1 and raised
    # from its level) and the SMOOTH_REACH frames on either side; the settled ones hold still
    over = raised | ((m1 == 0) & (m2 == step))
    assert np.array_equal(rows2, np.flatnonzero(dilate(over, SMOOTH_REACH)))


def test_a_frame_a_round_leaves_deeper_goes_back_to_its_best_answer(model, monkeypatch):
    """Where a round leaves a frame over the tolerance and deeper than its best answer so far (here: the
    round's answer at the middle frame pushed 10 cm into the partner), that frame goes back to its best
    corrections bit for bit, and the round is reported; the round's other frames keep their answers. The
    contacts kept for each round are those of every frame's current pose (the one sent back included)."""
    T, f = 12, 6
    inputs = _step_in(T)
    seen = []
    real = TakeFitter._round

    def spy(self, rows, termed, mult, exact, variables):
        kept = dict(self.located)  # the contacts kept for the round, each of its frame's current pose
        seen.append(([p.detach().clone() for p in self.params], self._measure(np.arange(T))[0]))
        for g, located in kept.items():
            was, now = located.take([g]), self.located[g].take([g])
            assert (was.max_depth_m[0], was.share[0]) == (now.max_depth_m[0], now.share[0]), g
        self.located = kept
        ok = real(self, rows, termed, mult, exact, variables)
        if len(seen) == 2:  # the second round's answer: actor b's middle frame pushed into actor a
            assert f in rows
            with torch.no_grad():
                self.params[PARAMS_PER_ACTOR + 1][f, 0] -= 0.1
        return ok

    monkeypatch.setattr(TakeFitter, "_round", spy)
    cfg = dataclasses.replace(CFG, collision_rounds=3, take_iterations=2, collision_deep_m=0.0, collision_weight=1e3,
                              collision_restart=False)  # fmt: skip
    res = fit_actors(model, inputs, FPS, cfg)
    assert len(seen) == 3
    (p2, d2), (p3, d3) = seen[1], seen[2]
    assert d2[f] > cfg.collision_tolerance_m and d3[f] == d2[f]
    for a, b in zip(p2, p3):
        assert torch.equal(a[f], b[f])
    assert any(w.startswith("take: collision round 2, ") for w in res.summary["collision_worsened"])
    moved_on = [not torch.equal(a[g], b[g]) for a, b in zip(p2, p3) for g in range(T) if g != f]
    assert any(moved_on)


def test_a_round_that_steps_to_non_finite_corrections_is_undone(model, monkeypatch):
    """A poisoned collision loss sends the line search to NaN: the round is undone (the skeleton pass's
    answer kept), reported, and the bodies stay finite."""
    from dualhuman_builder.geometry import collision

    inputs = _step_in(20)
    real = collision.CollisionTerm.linear_loss
    monkeypatch.setattr(collision.CollisionTerm, "linear_loss", lambda self, lin, points, device=None, dtype=None:
                        real(self, lin, points, device) * float("nan"))  # fmt: skip
    res = fit_actors(model, inputs, FPS, CFG)
    (label,) = res.summary["collision_diverged"]
    assert label.startswith("take: collision round 1, ") and res.summary["collision_rounds_used"] == 0
    assert res.summary["max_penetration_after_mm"] == pytest.approx(res.summary["max_penetration_before_mm"])
    for track in res.sequence.actors:
        assert np.isfinite(np.asarray(track.pose)).all() and np.isfinite(np.asarray(track.transl)).all()


def test_an_unknown_solver_is_refused(model):
    with pytest.raises(FitError, match="unknown fit solver 'segments'"):
        fit_actors(model, _step_in(4), FPS, FitConfig(solver="segments"))
    with pytest.raises(FitError, match="unknown take solver step 'each'; choose one of shared, runs"):
        fit_actors(model, _step_in(4), FPS, FitConfig(solver="take", take_step="each"))
    assert solver_fields("take:runs") == {"solver": "take", "take_step": "runs"} and solver_fields("take") == {"solver": "take"}
    for bad in ("windows:runs", "take:each", "segments"):
        with pytest.raises(ValueError, match=f"unknown fit solver '{bad}'; choose one of windows, take or take:shared"):
            solver_fields(bad)


def test_the_hands_pass_comes_first_and_moves_the_openings_alone(model, monkeypatch):
    """With hand openings on, the first collision pass optimises only the openings (they have no data term,
    so they give way before any bone the suit holds); the full rounds after it move the bones too."""
    T = 20
    seen = []
    real = TakeFitter._round

    def spy(self, rows, termed, mult, exact, variables):
        seen.append([tuple(v.shape) for v in variables])
        return real(self, rows, termed, mult, exact, variables)

    monkeypatch.setattr(TakeFitter, "_round", spy)
    res = fit_actors(model, _step_in(T), FPS, dataclasses.replace(CFG, hand_opening=True))
    assert len(seen) >= 2
    assert seen[0] == [(T, 4), (T, 4)]  # both actors' openings, nothing else
    assert (T, 23, 3) in seen[1] and (T, 3) in seen[1] and (T, 4) in seen[1]
    assert res.summary["collision_rounds_used"] == len(seen) - 1  # the hands' pass is not a full round


def test_the_contacts_a_measurement_located_serve_the_next_round(model, monkeypatch):
    """The depths after a round come from the same query that locates the contacts, and the next round
    holds those contacts for the frames that have not moved since, instead of locating them again: the
    fit is the same bit for bit as one that locates every round's contacts afresh, with fewer frames
    located."""
    from dualhuman_builder.geometry import collision

    T = 30
    inputs = _step_in(T)
    located = []
    real = collision.CollisionTerm.linearise

    def spy(self, va, vb, keys=None, margin_m=0.005):
        located.append(len(keys))
        return real(self, va, vb, keys=keys, margin_m=margin_m)

    monkeypatch.setattr(collision.CollisionTerm, "linearise", spy)
    cfg = dataclasses.replace(CFG, collision_rounds=3, take_iterations=2, collision_deep_m=0.0, collision_weight=1e3)
    kept = fit_actors(model, inputs, FPS, cfg)
    n_kept = sum(located)
    real_locate = TakeFitter._locate

    def afresh(self, rows):  # every frame's contacts located again at the round's start
        self.located.clear()
        return real_locate(self, rows)

    monkeypatch.setattr(TakeFitter, "_locate", afresh)
    located.clear()
    fresh = fit_actors(model, inputs, FPS, cfg)
    assert kept.summary["collision_rounds_used"] >= 2
    for a, b in zip(kept.sequence.actors, fresh.sequence.actors):
        assert np.array_equal(np.asarray(a.pose), np.asarray(b.pose))
        assert np.array_equal(np.asarray(a.transl), np.asarray(b.transl))
    assert n_kept < sum(located)


def test_the_per_frame_skeleton_energy_sums_to_the_energy_and_each_frame_reads_its_neighbours_only(model):
    """``per_frame``: the frames' energies (:func:`~dualhuman_builder.fit.energy.summer`) add up to the
    summed energy, and moving frame 10 changes only frames 9-11 (second differences counted to their
    middle frame, the sole's step to its later one), so a block of frames 2 or more apart from another
    reads none of its variables (:func:`~dualhuman_builder.fit.block_lbfgs.frame_blocks`)."""
    T = 20
    fitter = TakeFitter(model, _step_in(T), FPS, dataclasses.replace(CFG, hand_opening=True))
    torch.manual_seed(0)
    ps = [(0.05 * torch.randn(T, *shape)) for _ in fitter.acts for shape in ((23, 3), (3,), (4,))]
    sl, none = slice(0, T), [None, None]
    with torch.no_grad():
        total = fitter.energy(ps, sl, none, none)[0]
        frames = fitter.energy(ps, sl, none, none, per_frame=True)[0]
        assert frames.shape == (T,) and float(frames.sum()) == pytest.approx(float(total), rel=1e-5)
        for p in ps:
            p[10] += 0.05
        moved = fitter.energy(ps, sl, none, none, per_frame=True)[0]
    changed = np.flatnonzero((moved != frames).numpy())
    assert changed.tolist() == [9, 10, 11]
    with pytest.raises(ValueError, match="no context"):
        skeleton_energy(fitter.stack, *(torch.stack(ps[j::3]) for j in range(3)), sl, ("a context",), fitter.cfg, FPS,
                        per_frame=True)  # fmt: skip

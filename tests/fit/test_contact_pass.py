"""The fit's contact pass (:mod:`dualhuman_builder.fit.contact_pass`): a contact the inputs support is kept
(two bodies the data puts a few millimetres apart are brought to touching), and it adds no penetration."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dualhuman_builder.body.model import get_body_model
from dualhuman_builder.contacts.compute import contacts_from_vertices
from dualhuman_builder.contacts.topology import ContactTopology
from dualhuman_builder.fit.contact_pass import nearest_pairs
from dualhuman_builder.fit.fitter import ActorInput, FitConfig, fit_actors

T, FPS = 4, 15.0


@pytest.fixture(scope="module")
def model():
    return get_body_model()


def _inputs(dx: float) -> list:
    """Fit inputs of two actors in the rest pose for :data:`T` frames, pelvises ``dx`` apart along x, no trackers."""
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (T, 23, 1))
    pelvis = np.tile([0.0, 0.95, 0.0], (T, 1))
    return [ActorInput(name, {}, quat, pelvis + [x, 0, 0], np.ones(T, bool), np.zeros((T, 0, 3)),
                       np.zeros((T, 0), bool), np.zeros(0, np.int64), np.zeros((0, 3)),
                       np.tile([[0.1, 0.1, 0.0], [-0.1, 0.1, 0.0]], (T, 1, 1)))
            for name, x in (("a", 0.0), ("b", dx))]  # fmt: skip


@pytest.fixture(scope="module")
def rest(model) -> np.ndarray:
    """The fitted rest body's vertices ``(V, 3)`` (both actors get the same body, ``b`` shifted along x)."""
    res = fit_actors(model, _inputs(1.0), FPS, FitConfig(window=T, iterations=1, collision=False))
    return res.sequence.actors[0].vertices()[0]


def _min_distance(model, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per frame the smallest signed distance (m) between bodies ``a``, ``b`` ``(n, V, 3)`` by the contacts
    code (negative: penetrating; +inf: beyond its 5 cm band)."""
    c = contacts_from_vertices(a, b, ContactTopology.for_model(model), threshold_m=0.02, band_m=0.05, workers=1)
    d = c.distances.astype(np.float64)
    d[np.isneginf(d)] = -1.0
    d[np.isnan(d)] = np.inf
    return d.min(axis=(0, 2))


def _side_by_side(model, rest: np.ndarray, gap_m: float) -> list:
    """:func:`_inputs` with the pelvises as far apart along x as leaves ``gap_m`` (to 0.1 mm) between the
    nearest surfaces of the rest bodies (bisection)."""
    lo, hi = 0.0, 1.0
    while hi - lo > 1e-4:
        dx = 0.5 * (lo + hi)
        gap = _min_distance(model, rest[None], (rest + [dx, 0.0, 0.0])[None])[0]
        lo, hi = (dx, hi) if gap < gap_m else (lo, dx)
    return _inputs(hi)


def _gaps(model, res) -> np.ndarray:
    """Per frame the smallest signed distance (m) between the fitted bodies of ``res``."""
    return _min_distance(model, *(t.vertices() for t in res.sequence.actors))


def test_a_contact_the_inputs_support_is_kept_without_penetration(model, rest):
    """The inputs put the bodies' nearest surfaces ~5 mm apart: without the contact pass the fit leaves
    them there (nothing pulls them together); with it they touch (within ``contact_gap_m`` and a little
    slack), none inside the other beyond the collision tolerance, and the summary counts no penetration
    beyond the goals."""
    inputs = _side_by_side(model, rest, 0.005)
    cfg = FitConfig(window=T, iterations=4, collision_iterations=3, collision_rounds=1, contact_iterations=10)
    off = fit_actors(model, inputs, FPS, dataclasses.replace(cfg, contact_reach_m=0.0))
    on = fit_actors(model, inputs, FPS, cfg)
    g_off, g_on = _gaps(model, off), _gaps(model, on)
    assert (g_off > 0.003).all() and (g_off < 0.008).all()  # the data's gap, kept by the fit without the pass
    assert (g_on < cfg.contact_gap_m + 0.0015).all()  # brought to touching ...
    assert (g_on > -cfg.collision_tolerance_m).all()  # ... not into each other
    assert on.summary["max_penetration_after_mm"] <= 1000 * cfg.collision_tolerance_m
    assert on.summary["penetrating_share_after"] <= 0.001


def test_far_bodies_are_left_alone(model, rest):
    """Bodies 3 cm apart (beyond ``contact_reach_m``): the data supports no contact, the pass moves nothing."""
    inputs = _side_by_side(model, rest, 0.03)
    cfg = FitConfig(window=T, iterations=4, collision_iterations=3, collision_rounds=1)
    off = fit_actors(model, inputs, FPS, dataclasses.replace(cfg, contact_reach_m=0.0))
    on = fit_actors(model, inputs, FPS, cfg)
    for a, b in zip(on.sequence.actors, off.sequence.actors):
        assert np.array_equal(np.asarray(a.pose), np.asarray(b.pose))
        assert np.array_equal(np.asarray(a.transl), np.asarray(b.transl))


def test_nearest_pairs_picks_the_nearest_outside_vertices_of_frames_within_reach():
    from dualhuman_builder.geometry.collision.locate import Contacts

    class Lin:  # the two fields nearest_pairs reads of a Linearised
        pass

    lin = Lin()
    frame = np.array([0, 0, 0, 1, 1, 2, 2, 3])
    depth = -np.array([0.004, 0.002, 0.006, 0.0005, 0.003, -0.001, 0.002, 0.009])  # negative depth: outside
    z = np.zeros(len(frame), np.int64)
    lin.contacts = Contacts(frame=frame, side=z, vert=np.arange(len(frame)), depth=depth, face=z,
                            bary=np.zeros((len(frame), 3)))
    # frame 0: within reach, two nearest; frame 1: already touching; frame 2: one inside; frame 3: beyond reach
    assert nearest_pairs(lin, 0.008, 2, 0.001).tolist() == [0, 1]

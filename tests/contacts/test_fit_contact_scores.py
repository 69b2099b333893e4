"""The fitted pair's contacts scored against the ground truth's (:mod:`dualhuman_builder.evaluation.contacts`):
known answers (the truth against itself, a body moved out of reach), per-region scores and the events'
onset and offset errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dualhuman_builder.contacts import ContactTopology
from dualhuman_builder.evaluation.contacts import (
    count_scores,
    event_timing,
    fit_contact_scores,
    label_scores,
)

FPS = 30.0


@pytest.fixture(scope="module")
def topo(body_model):
    return ContactTopology.for_model(body_model)


@pytest.fixture(scope="module")
def truth(body_model):
    """Rest-pose bodies face to face (B turned about +Y), 25 cm between the roots: touching on 4
    frames, then 3 m apart sideways on 2 (no contact). ``(va, vb)`` each ``(6, V, 3)`` float32."""
    import torch

    at = [(0.0, 0.25)] * 4 + [(3.0, 0.25)] * 2
    pose = torch.zeros(len(at), body_model.num_bones, 3)
    with torch.no_grad():
        va = body_model.forward(pose, None, torch.tensor([[0.0, 0.95, 0.0]] * len(at))).vertices.numpy()
        pose[:, 0, 1] = math.pi
        vb = body_model.forward(pose, None, torch.tensor([[x, 0.95, z] for x, z in at])).vertices.numpy()
    return va, vb


def test_truth_against_itself_scores_one(truth, topo):
    s = fit_contact_scores(truth, truth, FPS, topology=topo)
    assert s["tp"] > 0 and s["fp"] == 0 and s["fn"] == 0
    assert s["f1"] == s["precision"] == s["recall"] == 1.0
    assert s["regions"] and all(r["f1"] == 1.0 for r in s["regions"].values())
    assert s["frames_in_contact"] == s["frames_in_contact_truth"] == 4
    ev = s["events"]
    assert ev["matched"] > 0 and ev["missed"] == ev["spurious"] == 0
    assert ev["onset_ms"] == ev["offset_ms"] == 0.0
    assert s["any_events"]["onset_ms"] == s["any_events"]["offset_ms"] == 0.0


def test_a_body_moved_beyond_the_threshold_scores_zero(truth, topo):
    va, vb = truth
    moved = vb + np.array([3.0, 0.0, 0.0], np.float32)  # out of reach: farther than the threshold and the band
    s = fit_contact_scores((va, moved), truth, FPS, topology=topo)
    assert s["tp"] == 0 and s["fn"] > 0
    assert s["f1"] == 0.0 and s["recall"] == 0.0
    assert s["frames_in_contact"] == 0
    assert s["events"]["missed"] > 0 and s["events"]["matched"] == 0
    assert math.isnan(s["events"]["onset_ms"])


def test_late_contact_onset_in_ms(truth, topo):
    """The fitted pair touching from frame 2 (the truth from frame 0): the onset is 2 frames late
    (66.7 ms at 30 fps), the offset right; the vertices of frames 0 and 1 are missed."""
    va, vb = truth
    late = vb.copy()
    late[:2] += np.array([3.0, 0.0, 0.0], np.float32)
    s = fit_contact_scores((va, late), truth, FPS, topology=topo)
    assert s["precision"] == 1.0 and 0.4 < s["recall"] < 0.6
    assert s["any_events"]["onset_ms"] == pytest.approx(2000 / FPS)
    assert s["any_events"]["offset_ms"] == 0.0
    assert s["events"]["onset_ms"] == pytest.approx(2000 / FPS)


def test_event_timing_matches_by_region_pair_and_overlap():
    ev = lambda a, b, s, e: {"region_a": a, "region_b": b, "start": s, "end": e}
    truth = [ev("right_hand", "right_hand", 10, 40), ev("chest", "chest", 50, 60), ev("head", "head", 0, 5)]
    fitted = [ev("right_hand", "right_hand", 12, 37), ev("chest", "chest", 45, 61), ev("left_hand", "chest", 0, 3)]
    t = event_timing(fitted, truth, 10.0)
    assert t["matched"] == 2 and t["missed"] == 1 and t["spurious"] == 1
    assert t["onset_ms"] == pytest.approx((200 + 500) / 2) and t["offset_ms"] == pytest.approx((300 + 100) / 2)
    assert t["onset_max_ms"] == pytest.approx(500)


def test_label_scores_conventions():
    assert label_scores(np.zeros((2, 3, 4), bool), np.zeros((2, 3, 4), bool))["f1"] == 1.0  # nothing to find
    assert count_scores(3, 1, 2) == {"precision": 0.75, "recall": 0.6, "f1": 6 / 9, "tp": 3, "fp": 1, "fn": 2}
    with pytest.raises(ValueError, match="differ in shape"):
        label_scores(np.zeros(3, bool), np.zeros(4, bool))

"""The metrics of :mod:`dualhuman_builder.models.metrics`: each against a case computed by hand (the
derivation in the comment), plus the invariances that define them (Hypothesis)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.models import metrics as M

seeds = st.integers(0, 2**32 - 1)


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])  # fmt: skip


# ------------------------------------------------------------------------------------ joint errors
def test_mpjpe_hand_case():
    # truth: root at the origin, joint 1 at x = 0.1 m. pred: everything 0.5 m along x, joint 1 also
    # off by (0, 3, 4) mm. Root-relative: joint 0 error 0, joint 1 error 5 mm -> MPJPE 2.5 mm.
    # World (root=None): joint 0 error 500 mm, joint 1 sqrt(500^2 + 3^2 + 4^2) = sqrt(250025) mm.
    truth = np.array([[[0.0, 0, 0], [0.1, 0, 0]]])
    pred = np.array([[[0.5, 0, 0], [0.6, 0.003, 0.004]]])
    assert M.mpjpe(pred, truth) == pytest.approx(2.5)
    assert M.mpjpe(pred, truth, root=None) == pytest.approx((500 + math.sqrt(250025)) / 2)
    assert M.joint_errors(pred, truth).shape == (1, 2)


def test_translation_error_hand_case():
    # Root (joint 0) off by (3, 4, 0) mm in frame 0 and exact in frame 1: errors 5 and 0 mm, mean 2.5.
    truth = np.zeros((2, 3, 3))
    pred = truth.copy()
    pred[0, 0] = [0.003, 0.004, 0.0]
    pred[1, 2] = [1.0, 1.0, 1.0]  # another joint: not the root's error
    assert M.translation_error(pred, truth) == pytest.approx(2.5)
    # root=None: the inputs are root positions (T, 3) themselves
    assert M.translation_error(pred[:, 0], truth[:, 0], root=None) == pytest.approx(2.5)


def test_pa_mpjpe_hand_case():
    # truth: (-u, 0, 0), (0, 0, 0), (u, 0, 0); pred: the middle point lifted to (0, u, 0), u = 0.1 m.
    # Centred, pred is (-u, -u/3), (0, 2u/3), (u, -u/3) in (x, y); the cross-covariance with truth has
    # only its xx entry (2u^2), so R is the identity about x and the scale is 2u^2 / (2u^2 + 2u^2/3) = 3/4.
    # Aligned errors: outer points sqrt((u - 3u/4)^2 + (3/4 * u/3)^2) = sqrt(2) u / 4, middle 3/4 * 2u/3 = u/2.
    # PA-MPJPE = (2 * sqrt(2)/4 + 1/2) / 3 * u = (1 + sqrt(2)) / 6 * 100 mm = 40.237 mm.
    u = 0.1
    truth = np.array([[[-u, 0, 0], [0, 0, 0], [u, 0, 0]]])
    pred = np.array([[[-u, 0, 0], [0, u, 0], [u, 0, 0]]])
    assert M.pa_mpjpe(pred, truth) == pytest.approx((1 + math.sqrt(2)) / 6 * 100)
    assert M.pa_joint_errors(pred, truth)[0] == pytest.approx([math.sqrt(2) / 4 * 100, 50, math.sqrt(2) / 4 * 100])


def _volume(p: np.ndarray) -> float:
    """Signed volume of the tetrahedron of the first four points (its sign is the handedness)."""
    return float(np.linalg.det(p[1:4] - p[0]))


def test_pa_mpjpe_never_reflects():
    # A chiral set and its mirror image: a reflection would map one onto the other exactly (what an
    # alignment without the determinant fix finds), a rotation cannot.
    truth = np.array([[[0.0, 0, 0], [0.3, 0, 0], [0, 0.2, 0], [0, 0, 0.1]]])
    mirror = truth * np.array([-1.0, 1, 1])
    x, y = mirror[0] - mirror[0].mean(0), truth[0] - truth[0].mean(0)
    u, s, vt = np.linalg.svd(x.T @ y)
    unfixed = s.sum() / (x**2).sum() * x @ (u @ vt) + truth[0].mean(0)
    assert np.abs(unfixed - truth[0]).max() < 1e-12  # without the fix: a perfect (reflected) fit
    assert M.pa_mpjpe(mirror, truth) > 10.0
    aligned = M.procrustes_align(mirror, truth)[0]
    # the aligned shape is a rotated, scaled copy of the mirror: same handedness as the mirror
    assert np.sign(_volume(aligned)) == np.sign(_volume(mirror[0])) != np.sign(_volume(truth[0]))


@given(seeds, st.floats(0.1, 10.0), st.integers(3, 22))
def test_pa_mpjpe_invariant_to_similarity_transforms_of_the_prediction(seed, scale, joints):
    rng = np.random.default_rng(seed)
    truth, pred = rng.normal(size=(2, 2, joints, 3)) * 0.3
    moved = scale * pred @ _rotation(rng).T + rng.normal(size=3)
    assert M.pa_mpjpe(moved, truth) == pytest.approx(M.pa_mpjpe(pred, truth), rel=1e-7, abs=1e-7)
    # and a prediction that is such a transform of the truth scores 0
    assert M.pa_mpjpe(scale * truth @ _rotation(rng).T + rng.normal(size=3), truth) < 1e-6


@given(seeds, st.integers(2, 22))
def test_root_relative_mpjpe_invariant_to_translation(seed, joints):
    rng = np.random.default_rng(seed)
    truth, pred = rng.normal(size=(2, 4, joints, 3))
    shifted = pred + rng.normal(size=(4, 1, 3)) * 5  # a different translation per frame
    assert M.mpjpe(shifted, truth) == pytest.approx(M.mpjpe(pred, truth), rel=1e-9, abs=1e-9)


def test_pose_errors_gathers_the_three_pose_figures():
    # the hand case of test_mpjpe_hand_case: root-relative 2.5 mm, root error 500 mm
    truth = np.array([[[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]]])
    pred = truth + [0.5, 0, 0]
    pred[0, 1] += [0, 0.003, 0.004]
    out = M.pose_errors(pred, truth)
    assert out["mpjpe_mm"] == pytest.approx(5 / 3) and out["translation_mm"] == pytest.approx(500.0)
    assert out["pa_mpjpe_mm"] == pytest.approx(M.pa_mpjpe(pred, truth)) and out["pa_mpjpe_mm"] < out["mpjpe_mm"]
    with pytest.raises(M.MetricInputError, match="finite"):
        M.pa_mpjpe(pred * np.nan, truth)


def test_torch_tensors_and_float32_are_scored_in_float64():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(2, 5, 22, 3))
    expect = M.mpjpe(a, b)
    assert M.mpjpe(torch.tensor(a), torch.tensor(b, requires_grad=True)) == pytest.approx(expect, rel=1e-12)
    assert M.as_array(torch.tensor(a, dtype=torch.float32)).dtype == np.float64


@pytest.mark.parametrize("call", [
    lambda: M.mpjpe(np.zeros((5, 22, 3)), np.zeros((4, 22, 3))),
    lambda: M.pa_mpjpe(np.zeros((5, 22, 3)), np.zeros((5, 21, 3))),
    lambda: M.mpjpe(np.zeros((5, 22, 2)), np.zeros((5, 22, 2))),
    lambda: M.translation_error(np.zeros((5, 3)), np.zeros((4, 3)), root=None),
    lambda: M.frechet_distance(np.zeros((5, 3)), np.zeros((5, 4))),
    lambda: M.diversity(np.zeros((10, 3)), pairs=300),
    lambda: M.contact_scores(np.zeros((2, 3, 5)), np.zeros((2, 3, 6))),
    lambda: M.summarize([]),
])  # fmt: skip
def test_bad_shapes_raise_a_clear_value_error(call):
    with pytest.raises(ValueError) as e:
        call()
    assert isinstance(e.value, DualhumanError)


# ------------------------------------------------------------------------------------ Fréchet distance
def test_frechet_distance_hand_case():
    # 1-D: feats1 = {0, 2}: mean 1, variance (1 + 1) / 1 = 2; feats2 = {3, 5, 7}: mean 5, variance
    # (4 + 0 + 4) / 2 = 4. FD = (1 - 5)^2 + 2 + 4 - 2 sqrt(2 * 4) = 22 - 4 sqrt(2).
    assert M.frechet_distance([[0.0], [2.0]], [[3.0], [5.0], [7.0]]) == pytest.approx(22 - 4 * math.sqrt(2))
    # 2-D with independent axes: the sum of the axes' FDs. Axis y: {0, 0} vs {1, 1, 1}: variances 0,
    # means 0 and 1: FD 1. Total 22 - 4 sqrt(2) + 1.
    f1, f2 = [[0.0, 0], [2.0, 0]], [[3.0, 1], [5.0, 1], [7.0, 1]]
    assert M.frechet_distance(f1, f2) == pytest.approx(23 - 4 * math.sqrt(2))


def test_frechet_distance_epsilon_fallback():
    # sigma1 = I, sigma2 = [[0, 1], [0, 0]]: the product is nilpotent, its square root does not exist
    # (sqrtm gives inf). With eps on both diagonals the product is [[l, 1 + eps], [0, l]],
    # l = eps (1 + eps), whose root is [[sqrt l, .], [0, sqrt l]]: trace 2 sqrt(l).
    # FD = 0 + tr(I) + tr(sigma2) - 2 * 2 sqrt(l) = 2 - 4 sqrt(eps (1 + eps)) = 1.996 for eps 1e-6.
    eps = 1e-6
    fd = M.frechet_distance_from_stats(np.zeros(2), np.eye(2), np.zeros(2), np.array([[0.0, 1], [0, 0]]), eps=eps)
    assert fd == pytest.approx(2 - 4 * math.sqrt(eps * (1 + eps)), abs=1e-9)


@settings(max_examples=50)
@given(seeds, st.integers(1, 6))
def test_frechet_distance_of_a_set_with_itself_is_zero_and_symmetric(seed, dims):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(40, dims)) @ rng.normal(size=(dims, dims))
    b = rng.normal(size=(30, dims)) + rng.normal(size=dims)
    assert abs(M.frechet_distance(a, a)) < 1e-6 * (1 + np.trace(np.atleast_2d(np.cov(a, rowvar=False))))
    ab, ba = M.frechet_distance(a, b), M.frechet_distance(b, a)
    assert ab == pytest.approx(ba, rel=1e-6, abs=1e-9)
    assert ab > -1e-9


def test_frechet_distance_scales_with_the_units_of_a_low_rank_set():
    # A decoder's outputs span few dimensions (a singular covariance), and in mm the covariances are
    # large: sqrtm's rounding then leaves imaginary residues well above 1e-3 in absolute terms. FD is
    # quadratic in the units, so the same sets in units 1000 times smaller give FD / 1e6.
    rng = np.random.default_rng(0)
    a = rng.normal(size=(500, 4)) @ rng.normal(size=(4, 30))
    b = rng.normal(size=(400, 30))
    assert M.frechet_distance(a * 1e3, b * 1e3) == pytest.approx(1e6 * M.frechet_distance(a, b), rel=1e-6)


def test_joint_positions_fd_hand_case():
    # Set 2 is set 1 with every joint moved 1 mm along x: the covariances are equal, the means differ
    # by 1 mm in each of the J = 2 x-coordinates: FD = 2 * 1^2 = 2 mm^2. Frames are the samples, so the
    # two leading axes (3 windows of 20 frames) pool into 60 samples of 6 coordinates.
    rng = np.random.default_rng(1)
    j1 = rng.normal(size=(3, 20, 2, 3)) * 0.05
    j2 = j1 + np.array([0.001, 0, 0])
    assert M.joint_positions_fd(j1, j2) == pytest.approx(2.0, rel=1e-5)
    assert M.joint_positions_fd(j1, j1) == pytest.approx(0.0, abs=1e-5)
    # root-relative: the shift vanishes
    assert M.joint_positions_fd(j1, j2, root=0) == pytest.approx(0.0, abs=1e-5)


def test_paired_fd_hand_case_and_synchrony():
    # The reactor moved 1 mm along x in pair 2: per person FD 0 (actor) and 2 mm^2 (reactor, J = 2),
    # paired FD on the concatenated 12 coordinates the same 2 mm^2.
    rng = np.random.default_rng(2)
    actor = rng.normal(size=(200, 2, 3)) * 0.05
    reactor = actor + rng.normal(size=(200, 2, 3)) * 0.005  # follows the actor closely
    assert M.paired_fd(actor, reactor, actor, reactor + [0.001, 0, 0]) == pytest.approx(2.0, rel=1e-4)
    # the reactor's frames shuffled: each person's distribution is unchanged (FD 0), the pair's is not
    late = reactor[rng.permutation(200)]
    assert M.joint_positions_fd(late, reactor) == pytest.approx(0.0, abs=1e-4)
    assert M.paired_fd(actor, late, actor, reactor) > 100.0


# ------------------------------------------------------------------------------------ diversity
def test_diversity_hand_case():
    # Rows k * e_i (a regular simplex): two different rows are k sqrt(2) apart, a row and itself 0.
    # T2M-GPT draws the two index lists independently (each without replacement) from the seeded
    # generator, so diversity = k sqrt(2) * (share of the pairs with different rows).
    k, n, pairs = 0.5, 12, 10
    feats = np.eye(n) * k
    rng = np.random.default_rng(7)
    first, second = rng.choice(n, pairs, replace=False), rng.choice(n, pairs, replace=False)
    assert M.diversity(feats, pairs=pairs, seed=7) == pytest.approx(k * math.sqrt(2) * np.mean(first != second))
    # per-window joints: one sample per window, in mm. Windows 0 and 1 differ by 3 mm in one
    # coordinate of one frame, so every drawn pair is 0 or 3 mm apart.
    w = np.zeros((4, 2, 22, 3))
    w[1::2, 0, 0, 0] = 0.003
    d = M.joint_positions_diversity(w, pairs=3, seed=0)
    r = np.random.default_rng(0)
    i, j = r.choice(4, 3, replace=False), r.choice(4, 3, replace=False)
    assert d == pytest.approx(3.0 * np.mean(i % 2 != j % 2))


@given(seeds, st.floats(0.1, 10.0))
def test_diversity_is_seeded_and_invariant_to_translation(seed, scale):
    rng = np.random.default_rng(seed)
    f = rng.normal(size=(40, 5))
    d = M.diversity(f, pairs=30, seed=seed)
    assert d == M.diversity(f, pairs=30, seed=seed) >= 0
    assert M.diversity(f + rng.normal(size=5), pairs=30, seed=seed) == pytest.approx(d, rel=1e-9)
    assert M.diversity(f * scale, pairs=30, seed=seed) == pytest.approx(d * scale, rel=1e-9)


# ------------------------------------------------------------------------------------ foot skating
def test_foot_skating_hand_case():
    # 3 frames at 30 fps, every joint at the origin but the feet (joints 10, 11). Left foot on the
    # floor, moving 1 mm per frame along x: 30 mm/s = 0.03 m/s < 0.15, in stance on both frame pairs.
    # Right foot still on the floor: 0 mm/s on both pairs. Mean over the 4 pairs: 15 mm/s.
    j = np.zeros((3, 22, 3))
    j[:, 10, 0] = [0.0, 0.001, 0.002]
    assert M.foot_skating(j, fps=30) == pytest.approx(15.0)
    # the right foot moving 10 mm per frame (0.3 m/s) is not in stance: only the left foot counts
    j[:, 11, 2] = [0.0, 0.01, 0.02]
    assert M.foot_skating(j, fps=30) == pytest.approx(30.0)
    # the vertical part of a step is not slide; a foot high above its lowest point is not in stance
    j[:, 10, 1] = [0.0, 0.0005, 0.001]
    assert M.foot_skating(j, fps=30) == pytest.approx(30.0)
    j[:, 11] = [[0, 0.5, 0], [0, 0.5, 0.001], [0, 0.0, 0.001]]
    assert M.foot_skating(j, fps=30) == pytest.approx(30.0)
    assert math.isnan(M.foot_skating(np.zeros((1, 22, 3)), fps=30))


def test_foot_skating_keeps_the_toolkits_definition():
    from dualhuman_builder.fit.config import FitConfig
    from dualhuman_builder.quality.gates import foot_slide_mm_s

    cfg = FitConfig()
    assert (M.STANCE_SPEED_M_S, M.STANCE_HEIGHT_M) == (cfg.stance_speed_m_s, cfg.stance_height_m)
    rng = np.random.default_rng(3)
    j = np.cumsum(rng.normal(size=(40, 22, 3)) * 0.002, axis=0)
    j[..., 1] = np.abs(j[..., 1])
    assert M.foot_skating(j, fps=30) == pytest.approx(foot_slide_mm_s(j, 30, cfg.stance_speed_m_s, cfg.stance_height_m))
    # windows are judged one by one and pooled: two copies score as one
    assert M.foot_skating(np.stack([j, j]), fps=30) == pytest.approx(M.foot_skating(j, fps=30))


# ------------------------------------------------------------------------------------ AFD
def test_average_frame_distance_hand_case():
    # T = 2 frames, J = 1 joint: the pose differs by (3, 4, 0) mm in frame 0 and not in frame 1:
    # |d| = 5 and 0 -> AFD 2.5 mm; squared: (25 + 0) / 2 = 12.5 mm^2.
    truth = np.zeros((2, 1, 3))
    pred = truth.copy()
    pred[0, 0] = [0.003, 0.004, 0]
    assert M.average_frame_distance(pred, truth) == pytest.approx(2.5)
    assert M.average_frame_distance(pred, truth, squared=True) == pytest.approx(12.5)
    # per class: "hug" has motions with AFD 2.5 and 0.0 (mean 1.25), "push" one with 2.5: mean over
    # classes (1.25 + 2.5) / 2
    out = M.afd_per_class([pred, truth, pred], [truth, truth, truth], ["hug", "hug", "push"])
    assert out == pytest.approx({"hug": 1.25, "push": 2.5, "mean": 1.875})


# ------------------------------------------------------------------------------------ contacts and the proxy
def test_contact_scores_hand_case():
    # pred 1100, ref 1010: tp 1 (first), fp 1 (second), fn 1 (third): precision = recall = F1 = 1/2.
    s = M.contact_scores([[[1, 1, 0, 0]]], [[[1, 0, 1, 0]]])
    assert (s["precision"], s["recall"], s["f1"], s["tp"], s["fp"], s["fn"]) == (0.5, 0.5, 0.5, 1, 1, 1)
    # nothing to find and nothing claimed: every score 1; claims without truth: precision 0
    assert M.contact_scores(np.zeros(4), np.zeros(4))["f1"] == 1.0
    s = M.contact_scores([1, 0], [0, 0])
    assert (s["precision"], s["recall"], s["f1"]) == (0.0, 1.0, 0.0)


def test_segment_distances_hand_cases():
    x0, x1 = np.array([[0.0, 0, 0]]), np.array([[1.0, 0, 0]])
    cases = [
        ((0, 1, 0), (1, 1, 0), 1.0),  # parallel, overlapping: the gap between the lines
        ((0.5, -1, 2), (0.5, 1, 2), 2.0),  # skew, crossing 2 above the middle
        ((2, 1, 0), (3, 1, 0), math.sqrt(2)),  # parallel, apart: endpoint (1,0,0) to (2,1,0)
        ((3, 0, 0), (4, 0, 0), 2.0),  # collinear, apart
        ((0.5, 1, 0), (0.5, 1, 0), 1.0),  # a point above the middle
        ((-1, -1, 0), (-1, 1, 0), 1.0),  # perpendicular, beyond the start
    ]
    for q0, q1, expect in cases:
        d = M.segment_distances(x0, x1, np.array([q0], float), np.array([q1], float))
        assert d.shape == (1, 1) and d[0, 0] == pytest.approx(expect), (q0, q1)
        # symmetric in the two segments
        assert M.segment_distances(np.array([q0], float), np.array([q1], float), x0, x1)[0, 0] == pytest.approx(expect)
    # both segments points: the points' distance
    p = np.array([[1.0, 2, 2]])
    assert M.segment_distances(p, p, np.zeros((1, 3)), np.zeros((1, 3)))[0, 0] == pytest.approx(3.0)


@given(seeds, st.booleans())
def test_segment_distances_agree_with_dense_sampling(seed, parallel):
    rng = np.random.default_rng(seed)
    p0, p1, q0 = rng.normal(size=(3, 3))
    q1 = q0 + (p1 - p0) * rng.uniform(-2, 2) if parallel else rng.normal(size=3)
    d = M.segment_distances(p0[None], p1[None], q0[None], q1[None])[0, 0]
    s = np.linspace(0, 1, 201)
    a, b = p0 + s[:, None] * (p1 - p0), q0 + s[:, None] * (q1 - q0)
    sampled = np.linalg.norm(a[:, None] - b[None], axis=-1).min()
    step = (np.linalg.norm(p1 - p0) + np.linalg.norm(q1 - q0)) / 200
    assert d <= sampled + 1e-9
    assert sampled - d <= step


def _blob(offset: float) -> np.ndarray:
    """22 joints all at one point (x = offset): every capsule a sphere there (the hand and head
    capsules too: their direction from the parent joint is zero)."""
    j = np.zeros((1, 22, 3))
    j[..., 0] = offset
    return j


def test_proxy_penetration_and_contacts_hand_case():
    # Two blobs (all capsules spheres at one point) 0.2 m apart: the widest spheres (spine, r = 0.125)
    # overlap by 2 * 0.125 - 0.2 = 0.05 m = 50 mm. At 0.3 m apart nothing overlaps.
    r = {c[0]: c[3] for c in M.CAPSULES}
    assert max(r.values()) == r["spine"] == 0.125
    pen = M.proxy_penetration(_blob(0), _blob(0.2))
    assert pen["max_depth_mm"] == pytest.approx(50.0) and pen["frames_penetrating"] == 1.0
    assert M.proxy_penetration(_blob(0), _blob(0.3))["max_depth_mm"] == 0.0
    # 0.26 m apart: capsule i touches (gap < 20 mm) when 0.26 - r_i - 0.125 < 0.02, i.e. r_i > 0.115:
    # only the spine, on both people.
    labels = M.proxy_contact_labels(_blob(0), _blob(0.26))
    spine = [c[0] for c in M.CAPSULES].index("spine")
    expect = np.zeros((2, 1, len(M.CAPSULES)), bool)
    expect[:, :, spine] = True
    assert labels.shape == expect.shape and (labels == expect).all()
    # scored against a ground truth 0.3 m apart (no contact): 2 false positives, nothing to find
    s = M.proxy_contact_scores(_blob(0), _blob(0.26), _blob(0), _blob(0.3))
    assert (s["tp"], s["fp"], s["fn"], s["precision"], s["recall"]) == (0, 2, 0, 0.0, 1.0)


def test_proxy_penetration_leaves_gripping_hands_out():
    # Two right arms along x reaching for each other, every other joint 1 m away. a: elbow at 0,
    # wrist at 0.25, so its hand runs 0.25 -> 0.38; b: elbow at 0.75, wrist at 0.5, hand 0.5 -> 0.37.
    # The hands' axes meet (distance 0): round hands would overlap by 2 * 0.045 = 90 mm, but hands do
    # not count for penetration: 0. They do touch: both right hands in contact, nothing else (a's
    # forearm ends 0.12 m from b's hand: gap 0.12 - 0.025 - 0.045 = 0.05 m, above the 0.02 m threshold).
    a, b = np.full((1, 22, 3), 0.0), np.full((1, 22, 3), 0.0)
    a[..., 0], b[..., 0] = -1.0, 2.0
    a[0, 19, 0], a[0, 21, 0] = 0.0, 0.25
    b[0, 19, 0], b[0, 21, 0] = 0.75, 0.5
    assert M.proxy_penetration(a, b)["max_depth_mm"] == 0.0
    names = [c[0] for c in M.CAPSULES]
    gaps = M._capsule_gaps(a, b)[0]
    hand = names.index("right_hand")
    assert gaps[hand, hand] == pytest.approx(-0.09)
    labels = M.proxy_contact_labels(a, b)
    touching = [[names[i] for i in np.flatnonzero(labels[k, 0])] for k in (0, 1)]
    assert touching == [["right_hand"], ["right_hand"]]


def test_proxy_interaction_and_its_blocks(monkeypatch):
    # a prediction equal to the truth: contact F1 1, its penetration the truth's (50 mm, the hand
    # case above, in frame 0 of 3; frames 1 and 2 apart): mean 50 / 3 mm
    a = np.concatenate([_blob(0), _blob(0), _blob(0)])
    b = np.concatenate([_blob(0.2), _blob(0.3), _blob(0.4)])
    out = M.proxy_interaction(a, b, a, b)
    assert out["contact_f1"] == 1.0 and out["penetration_mm"] == pytest.approx(50 / 3)
    assert out["penetration_max_mm"] == out["truth_penetration_max_mm"] == pytest.approx(50.0)
    # blocks of one frame give the same answer as one block
    whole = M.proxy_contact_labels(a, b)
    monkeypatch.setattr(M, "PROXY_CHUNK", 1)
    assert (M.proxy_contact_labels(a, b) == whole).all()
    assert M.proxy_penetration(a[None], b[None])["depth_mm"].shape == (1, 3)


def test_hand_and_head_capsules_extend_their_limb():
    # a straight arm along +x: elbow at x = 0.3, wrist at 0.55: the hand capsule runs on to
    # 0.55 + HAND_LENGTH_M; the head capsule continues the neck -> head direction by HEAD_LENGTH_M.
    j = np.zeros((22, 3))
    j[18], j[20] = [0.3, 0, 0], [0.55, 0, 0]
    j[12], j[15] = [0, 0.5, 0], [0, 0.6, 0]
    _, e = M.capsule_segments(j)
    names = [c[0] for c in M.CAPSULES]
    assert e[names.index("left_hand")] == pytest.approx([0.55 + M.HAND_LENGTH_M, 0, 0])
    assert e[names.index("head")] == pytest.approx([0, 0.6 + M.HEAD_LENGTH_M, 0])


def test_capsule_radii_fit_the_average_body(body_model):
    # The radii are the median distance, from each capsule's axis, of the vertices of anny's average
    # body (rest pose) nearest that axis (rounded to 5 mm): measured again here.
    with torch.no_grad():
        out = body_model.forward(batch_size=1)
    v, j = out.vertices[0].double().numpy(), out.joints[0].double().numpy()
    s, e = M.capsule_segments(j)
    V = len(v)
    # every vertex as a segment of zero length against every capsule axis: (V, C)
    dist = M.segment_distances(v[:, None], v[:, None], np.broadcast_to(s, (V, *s.shape)),
                               np.broadcast_to(e, (V, *e.shape)))[:, 0]  # fmt: skip
    near = dist.argmin(1)
    medians = np.array([np.median(dist[near == k, k]) for k in range(len(M.CAPSULES))])
    assert np.abs(medians - M.capsule_radii()).max() <= 0.005


# ------------------------------------------------------------------------------------ meshes
def test_mesh_penetration_and_contacts(body_model):
    # Two average bodies at rest, both facing +z, the second 0.6, 0.25, 0.22 and 0.15 m in front of the
    # first: apart, touching (front against back, no overlap), then overlapping more and more.
    J = body_model.num_bones
    shape = np.full(len(body_model.shape_names), 0.5)
    transl_b = np.zeros((4, 3))
    transl_b[:, 2] = [0.6, 0.25, 0.22, 0.15]
    va = M.body_vertices(np.zeros((4, J, 3)), np.zeros((4, 3)), shape, body_model)
    vb = M.body_vertices(np.zeros((4, J, 3)), transl_b, shape, body_model)
    pen = M.mesh_penetration(va, vb)
    d = pen["depth_mm"]
    assert d[0] == d[1] == 0.0 and 0 < d[2] < d[3]
    # a vertex inside the other body leaves it when the second body moves back to 0.25 m (where they do
    # not overlap), so it lies at most that far from the surface: 30 and 100 mm
    assert d[2] <= 30.0 + 1e-3 and d[3] <= 100.0 + 1e-3
    assert pen["max_depth_mm"] == d[3] and pen["frames_penetrating"] == 0.5 and pen["share"] > 0
    # contacts: the touching pair is the truth; a prediction apart finds none of it: recall 0,
    # precision 1 (nothing claimed), F1 0; the truth against itself: 1.
    truth = M.mesh_contact_labels(va[1:2], vb[1:2])
    assert truth.shape == (2, 1, body_model.num_vertices) and truth[0].any() and truth[1].any()
    s = M.mesh_contact_scores(va[:1], vb[:1], va[1:2], vb[1:2])
    assert (s["precision"], s["recall"], s["f1"], s["tp"], s["fn"]) == (1.0, 0.0, 0.0, 0, int(truth.sum()))
    assert M.contact_scores(truth, truth)["f1"] == 1.0


def test_motion_vertices_reads_the_export_layout(body_model):
    J, P = body_model.num_bones, len(body_model.shape_names)
    motion = {"a.pose": np.zeros((3, J, 3), np.float32), "a.transl": np.zeros((3, 3), np.float32),
              "a.shape": np.full(P, 0.5, np.float32)}  # fmt: skip
    v = M.motion_vertices(motion, "a", frames=slice(0, 1), model=body_model)
    assert v.shape == (1, body_model.num_vertices, 3)
    with pytest.raises(M.MetricInputError, match="no body parameters"):
        M.motion_vertices(motion, "b", model=body_model)


# ------------------------------------------------------------------------------------ summaries
def test_summarize_hand_case():
    # mean of 1, 2, 3 is 2; sample std sqrt(((1)^2 + 0 + (1)^2) / 2) = 1
    assert M.summarize([1.0, 2.0, 3.0]) == (2.0, 1.0)
    assert M.summarize(np.array([5.0])) == (5.0, 0.0)
    assert M.summarize([torch.tensor(1.0), torch.tensor(3.0)]) == (2.0, pytest.approx(math.sqrt(2)))

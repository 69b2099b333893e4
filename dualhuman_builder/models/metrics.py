"""The papers' metrics, in one module: joint errors, distribution distances, diversity, foot skating,
and the interaction figures (penetration between the two people, contacts against the ground truth).

Units and shapes, for every function here:

* Positions come in **metres** in the export's world frame (Y up; :mod:`dualhuman_builder.conventions`)
  and errors go out in **millimetres** (speeds in mm/s, Fréchet distances of positions in mm²), so a
  figure reads the same whichever function produced it.
* Joints are ``(..., J, 3)`` arrays: any leading axes (frames, windows, batches), ``J = 22`` in
  HumanML3D's order (:data:`~dualhuman_builder.body.joints.JOINT22_NAMES`) where a function needs named
  joints (root 0, feet 10 and 11).
* Inputs may be numpy arrays or torch tensors (detached and copied to the CPU); everything is computed
  in float64 and returned as numpy float64 arrays or Python floats.
* Bad input (shapes that differ, a wrong last axis, too few samples) raises :class:`MetricInputError`,
  a ``ValueError`` and a :class:`~dualhuman_builder.errors.DualhumanError` naming the shapes.

Which public definition each metric follows is said in its docstring (facts in
``shared/reference/models-and-metrics.md``); where no public code exists the definition is stated.

* pose: :func:`mpjpe` (root-relative), :func:`pa_mpjpe`, :func:`translation_error`, :func:`pose_errors`;
* distributions: :func:`frechet_distance` (any features), :func:`joint_positions_fd` (one sample per
  frame), :func:`paired_fd` (both people), :func:`diversity`, :func:`joint_positions_diversity`
  (one sample per window), :func:`afd_per_class` (Mix and Match);
* physical plausibility: :func:`foot_skating`;
* interaction, on meshes where body parameters exist (:func:`motion_vertices`,
  :func:`mesh_penetration`, :func:`mesh_contact_labels`, :func:`mesh_contact_scores`) and on a
  capsule proxy for joints only (:data:`CAPSULES`, :func:`proxy_penetration`,
  :func:`proxy_contact_labels`, :func:`proxy_interaction`); :func:`contact_scores` for any labels;
* runs: :func:`summarize` (mean and sample std over seeds).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
from scipy import linalg

from dualhuman_builder.body.joints import JOINT22_NAMES, JOINT22_PARENTS
from dualhuman_builder.errors import DualhumanError

MM = 1000.0  #: millimetres per metre

#: HumanML3D joint indices of the feet (the ball of each foot), as the quality gates use them.
FEET = (JOINT22_NAMES.index("left_foot"), JOINT22_NAMES.index("right_foot"))

#: Foot-stance thresholds of the fit and its foot-slide gate (``FitConfig.stance_speed_m_s`` and
#: ``stance_height_m``; ``tests/models/test_metrics.py`` keeps them equal).
STANCE_SPEED_M_S = 0.15
STANCE_HEIGHT_M = 0.03

#: Pairs of random draws of T2M-GPT's diversity (``diversity_times``).
DIVERSITY_PAIRS = 300

#: Contact distance of the contacts stage (metres): a vertex (or capsule) closer than this to the
#: other body is in contact, penetration included (:data:`~dualhuman_builder.contacts.frames.DEFAULT_THRESHOLD_M`).
CONTACT_THRESHOLD_M = 0.02


class MetricInputError(DualhumanError, ValueError):
    """Arrays a metric cannot score: mismatched shapes, a wrong last axis, too few samples."""


# ---------------------------------------------------------------------------------------- input
def as_array(x: Any, name: str = "array") -> np.ndarray:
    """``x`` (numpy array, torch tensor, nested sequence) as a float64 numpy array; a tensor is
    detached and copied to the CPU first."""
    if hasattr(x, "detach") and hasattr(x, "cpu"):  # a torch tensor, without importing torch here
        x = x.detach().cpu().numpy()
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise MetricInputError(f"{name} is not an array of numbers ({type(x).__name__}: {e})") from None
    return a


def _joints(x: Any, name: str) -> np.ndarray:
    a = as_array(x, name)
    if a.ndim < 2 or a.shape[-1] != 3:
        raise MetricInputError(f"{name} must have shape (..., J, 3) (joint positions in metres), got {a.shape}",
                               fix="pass joints as (frames, joints, 3) or (windows, frames, joints, 3)")  # fmt: skip
    return a


def _pair(pred: Any, truth: Any, names: tuple[str, str] = ("pred", "truth")) -> tuple[np.ndarray, np.ndarray]:
    p, t = _joints(pred, names[0]), _joints(truth, names[1])
    if p.shape != t.shape:
        raise MetricInputError(f"{names[0]} {p.shape} and {names[1]} {t.shape} differ in shape",
                               fix="score arrays of the same frames and joints")  # fmt: skip
    return p, t


def _root_relative(j: np.ndarray, root: int | None) -> np.ndarray:
    if root is None:
        return j
    if not -j.shape[-2] <= root < j.shape[-2]:
        raise MetricInputError(f"root joint {root} is outside the {j.shape[-2]} joints")
    return j - j[..., root : root + 1, :]


# ---------------------------------------------------------------------------------------- joint errors
def joint_errors(pred: Any, truth: Any, root: int | None = 0) -> np.ndarray:
    """Per-joint Euclidean errors ``(..., J)`` in mm of ``pred`` against ``truth`` ``(..., J, 3)`` m.

    ``root``: the joint both skeletons are made relative to first (0, the pelvis: the pose's error
    without its placement, as the Dual-Human paper's "3D root-relative pose"); ``None`` compares
    world positions."""
    p, t = _pair(pred, truth)
    return np.linalg.norm(_root_relative(p, root) - _root_relative(t, root), axis=-1) * MM


def mpjpe(pred: Any, truth: Any, root: int | None = 0) -> float:
    """Mean per-joint position error (mm): the mean of :func:`joint_errors` over every joint and
    frame. Root-relative by default (``root=0``); ``root=None`` for world positions."""
    return float(joint_errors(pred, truth, root).mean())


def procrustes_align(pred: Any, truth: Any) -> np.ndarray:
    """``pred (..., J, 3)`` aligned to ``truth`` frame by frame by the similarity transform
    (rotation, uniform scale, translation) minimising the summed squared joint distances, in metres.

    Umeyama's closed form as SmoothNet's ``lib/utils/eval_metrics.py`` computes it (HMR's
    ``compute_similarity_transform``): centre both, SVD of the cross-covariance ``K = P^T Q = U S V^T``,
    ``R = U diag(1, 1, d) V^T`` with ``d = sign det(U V^T)`` (never a reflection), scale
    ``tr(diag(1, 1, d) S) / |P|^2``. A frame whose prediction has every joint at one point gets scale 0
    (all joints on the truth's centroid)."""
    p, t = _pair(pred, truth)
    if not (np.isfinite(p).all() and np.isfinite(t).all()):
        raise MetricInputError("Procrustes alignment needs finite joints; pred or truth holds NaN or inf")
    lead = p.shape[:-2]
    p, t = p.reshape(-1, *p.shape[-2:]), t.reshape(-1, *t.shape[-2:])
    mp, mt = p.mean(1, keepdims=True), t.mean(1, keepdims=True)
    x, y = p - mp, t - mt
    u, s, vt = np.linalg.svd(np.einsum("nji,njk->nik", x, y))
    d = np.sign(np.linalg.det(u @ vt))
    d[d == 0] = 1.0
    u[:, :, -1] *= d[:, None]
    s[:, -1] *= d
    rot = u @ vt  # x @ rot ~ y
    var = (x**2).sum((1, 2))
    scale = np.where(var > 0, s.sum(1) / np.where(var > 0, var, 1.0), 0.0)
    out = scale[:, None, None] * (x @ rot) + mt
    return out.reshape(*lead, *out.shape[-2:])


def pa_joint_errors(pred: Any, truth: Any) -> np.ndarray:
    """Per-joint errors ``(..., J)`` in mm after :func:`procrustes_align` (per frame)."""
    p, t = _pair(pred, truth)
    return np.linalg.norm(procrustes_align(p, t) - t, axis=-1) * MM


def pa_mpjpe(pred: Any, truth: Any) -> float:
    """Procrustes-aligned MPJPE (mm): the mean of :func:`pa_joint_errors`, the pose's error without its
    placement, orientation and size (similarity Procrustes with scale and the reflection fix)."""
    return float(pa_joint_errors(pred, truth).mean())


def translation_error(pred: Any, truth: Any, root: int | None = 0) -> float:
    """Mean Euclidean error (mm) of the root's world position, over frames.

    The Dual-Human paper's "Translation Error ... the root joint error measured by Euclidean
    distance" (no public code): with ``root`` an index, ``pred``/``truth`` are joints
    ``(..., J, 3)`` m and joint ``root`` (0, the pelvis) is compared; with ``root=None`` they are the
    root positions themselves, ``(..., 3)`` m (e.g. the export's ``transl``)."""
    if root is None:
        p, t = as_array(pred, "pred"), as_array(truth, "truth")
        if p.shape != t.shape or p.ndim < 1 or p.shape[-1] != 3:
            raise MetricInputError(f"root positions pred {p.shape} and truth {t.shape} must both be (..., 3)")
        return float(np.linalg.norm(p - t, axis=-1).mean() * MM)
    p, t = _pair(pred, truth)
    if not -p.shape[-2] <= root < p.shape[-2]:
        raise MetricInputError(f"root joint {root} is outside the {p.shape[-2]} joints")
    return float(np.linalg.norm(p[..., root, :] - t[..., root, :], axis=-1).mean() * MM)


def pose_errors(pred: Any, truth: Any, root: int = 0) -> dict[str, float]:
    """The Dual-Human paper's three pose figures (its Tables 2-4), mm: ``mpjpe_mm`` (root-relative),
    ``pa_mpjpe_mm`` and ``translation_mm`` (the root's world error), of ``(..., J, 3)`` m joints."""
    return {"mpjpe_mm": mpjpe(pred, truth, root), "pa_mpjpe_mm": pa_mpjpe(pred, truth),
            "translation_mm": translation_error(pred, truth, root)}  # fmt: skip


# ---------------------------------------------------------------------------------------- Fréchet distance
def feature_stats(feats: Any, name: str = "feats") -> tuple[np.ndarray, np.ndarray]:
    """Mean ``(D,)`` and covariance ``(D, D)`` (``np.cov``, rows are samples, ddof 1) of ``feats (N, D)``,
    as T2M-GPT's ``calculate_activation_statistics``."""
    f = as_array(feats, name)
    if f.ndim != 2 or f.shape[0] < 2:
        raise MetricInputError(f"{name} must be (N, D) with at least 2 samples, got {f.shape}")
    if not np.isfinite(f).all():
        raise MetricInputError(f"{name} holds NaN or infinite values")
    return f.mean(0), np.atleast_2d(np.cov(f, rowvar=False))


def frechet_distance_from_stats(mu1: Any, sigma1: Any, mu2: Any, sigma2: Any, eps: float = 1e-6) -> float:
    """``|mu1 - mu2|^2 + tr(sigma1 + sigma2 - 2 (sigma1 sigma2)^(1/2))``, the Fréchet distance of two
    Gaussians, as T2M-GPT's ``utils/eval_trans.py`` ``calculate_frechet_distance`` computes it: the
    matrix square root by ``scipy.linalg.sqrtm``; where it is not finite (a singular product), again
    with ``eps`` added to both diagonals; an imaginary part left by rounding is dropped, one larger
    than 1e-3 on the diagonal is an error. That bound is T2M-GPT's for its unit-scale features; here it
    scales with the largest diagonal entry above 1, because the residue grows with the covariance:
    joint positions in mm from a decoder (a near-singular covariance) were refused by the absolute
    bound. Units: those of the features, squared."""
    mu1, mu2 = np.atleast_1d(as_array(mu1, "mu1")), np.atleast_1d(as_array(mu2, "mu2"))
    s1, s2 = np.atleast_2d(as_array(sigma1, "sigma1")), np.atleast_2d(as_array(sigma2, "sigma2"))
    D = mu1.shape[0]
    if mu1.shape != (D,) or mu2.shape != (D,) or s1.shape != (D, D) or s2.shape != (D, D):
        raise MetricInputError(f"Fréchet statistics disagree in shape: mu1 {mu1.shape}, sigma1 {s1.shape}, "
                               f"mu2 {mu2.shape}, sigma2 {s2.shape}")  # fmt: skip
    diff = mu1 - mu2
    covmean = _sqrtm(s1 @ s2)
    if not np.isfinite(covmean).all():
        offset = np.eye(D) * eps
        covmean = _sqrtm((s1 + offset) @ (s2 + offset))
    if np.iscomplexobj(covmean):
        scale = max(1.0, float(np.abs(np.diagonal(covmean).real).max()))
        if not np.allclose(np.diagonal(covmean).imag, 0, atol=1e-3 * scale):
            raise MetricInputError(f"the covariances' product has no real square root (imaginary part up to "
                                   f"{np.abs(covmean.imag).max():.3g})",
                                   fix="use more samples than feature dimensions")  # fmt: skip
        covmean = covmean.real
    return float(diff @ diff + np.trace(s1) + np.trace(s2) - 2 * np.trace(covmean))


def _sqrtm(m: np.ndarray) -> np.ndarray:
    import warnings

    with warnings.catch_warnings():  # a singular product warns; the caller checks finiteness itself
        warnings.simplefilter("ignore")
        out = linalg.sqrtm(m)
    return out[0] if isinstance(out, tuple) else out


def frechet_distance(feats1: Any, feats2: Any, eps: float = 1e-6) -> float:
    """Fréchet distance between the Gaussians fitted to ``feats1 (N1, D)`` and ``feats2 (N2, D)``
    (:func:`feature_stats`, :func:`frechet_distance_from_stats`): FID's formula on whatever features
    are given (a model's learned ones, or joint positions through :func:`joint_positions_fd`)."""
    f1, f2 = as_array(feats1, "feats1"), as_array(feats2, "feats2")
    if f1.ndim != 2 or f2.ndim != 2 or f1.shape[1] != f2.shape[1]:
        raise MetricInputError(f"feats1 {f1.shape} and feats2 {f2.shape} must be (N, D) with the same D")
    return frechet_distance_from_stats(*feature_stats(f1, "feats1"), *feature_stats(f2, "feats2"), eps=eps)


def _frames_mm(joints: Any, name: str, root: int | None) -> np.ndarray:
    """``(N, J * 3)`` mm: every frame of ``joints (..., J, 3)`` m as one sample."""
    j = _root_relative(_joints(joints, name), root)
    return j.reshape(-1, j.shape[-2] * 3) * MM


def joint_positions_fd(joints1: Any, joints2: Any, root: int | None = None, eps: float = 1e-6) -> float:
    """FD (mm²) on 3-D joint positions, as the synchrony paper computes it ("directly on the 3D joint
    locations"): **every frame is one sample** of ``J * 3`` coordinates (mm), pooled over all leading
    axes of ``joints1``/``joints2`` ``(..., J, 3)`` m (the two sets may differ in frame count). World
    positions by default (placement counts: a reaction in the wrong place is unrealistic);
    ``root=0`` scores root-relative poses."""
    a, b = _frames_mm(joints1, "joints1", root), _frames_mm(joints2, "joints2", root)
    if a.shape[1] != b.shape[1]:
        raise MetricInputError(f"joints1 and joints2 differ in joint count ({a.shape[1] // 3} and {b.shape[1] // 3})")
    return frechet_distance(a, b, eps)


def paired_fd(actor1: Any, reactor1: Any, actor2: Any, reactor2: Any, root: int | None = None,
              eps: float = 1e-6) -> float:  # fmt: skip
    """Paired FD (P-FD, mm²) of the synchrony paper: FD on the concatenated poses of both people, per
    frame (``2 * J * 3`` coordinates, mm). Pair 1 is ``actor1``/``reactor1`` (e.g. generated), pair 2
    ``actor2``/``reactor2`` (the ground truth), each ``(..., J, 3)`` m with the actor's and reactor's
    shapes equal within a pair. It scores the two people's placement and timing together, which FD
    on each person alone does not see."""
    for a, r, k in ((actor1, reactor1, 1), (actor2, reactor2, 2)):
        _pair(a, r, (f"actor{k}", f"reactor{k}"))
    p1 = np.concatenate([_frames_mm(actor1, "actor1", root), _frames_mm(reactor1, "reactor1", root)], axis=1)
    p2 = np.concatenate([_frames_mm(actor2, "actor2", root), _frames_mm(reactor2, "reactor2", root)], axis=1)
    if p1.shape[1] != p2.shape[1]:
        raise MetricInputError(f"the pairs differ in joint count ({p1.shape[1] // 6} and {p2.shape[1] // 6})")
    return frechet_distance(p1, p2, eps)


# ---------------------------------------------------------------------------------------- diversity
def diversity(feats: Any, pairs: int = DIVERSITY_PAIRS, seed: int = 0) -> float:
    """Mean Euclidean distance between ``pairs`` random pairs of rows of ``feats (N, D)``, T2M-GPT's
    ``calculate_diversity``: two independent draws of ``pairs`` indices, each without replacement
    (so a pair may be a row with itself), from ``numpy.random.default_rng(seed)``; needs ``N > pairs``.
    Units: the features'. Not halved: InterGen's evaluation reports half of this distance, so halve
    before comparing with its tables."""
    f = as_array(feats, "feats")
    if f.ndim != 2:
        raise MetricInputError(f"feats must be (N, D), got {f.shape}")
    if pairs < 1 or f.shape[0] <= pairs:
        raise MetricInputError(f"diversity draws {pairs} pairs without replacement from {f.shape[0]} samples; "
                               "it needs more samples than pairs",
                               fix="pass pairs= below the sample count")  # fmt: skip
    rng = np.random.default_rng(seed)
    first = rng.choice(f.shape[0], pairs, replace=False)
    second = rng.choice(f.shape[0], pairs, replace=False)
    return float(np.linalg.norm(f[first] - f[second], axis=1).mean())


def joint_positions_diversity(windows: Any, pairs: int = DIVERSITY_PAIRS, seed: int = 0,
                              root: int | None = None) -> float:  # fmt: skip
    """:func:`diversity` (mm) of motions given as joints ``(N, L, J, 3)`` m: **each window is one
    sample**, its ``L * J * 3`` coordinates in mm (world positions, or root-relative with ``root=0``)."""
    w = _root_relative(_joints(windows, "windows"), root)
    if w.ndim != 4:
        raise MetricInputError(f"windows must be (N, L, J, 3), got {w.shape}")
    return diversity(w.reshape(w.shape[0], -1) * MM, pairs, seed)


# ---------------------------------------------------------------------------------------- foot skating
def foot_skating(joints: Any, fps: float, stance_speed_m_s: float = STANCE_SPEED_M_S,
                 stance_height_m: float = STANCE_HEIGHT_M) -> float:  # fmt: skip
    """Mean horizontal speed (mm/s) of the feet over the frame pairs where a foot is in stance at
    both ends; NaN when no foot is ever in stance.

    The toolkit's foot-slide definition (the quality gate's ``foot_slide_mm_s``, the same thresholds
    as the fit's stance term): per foot joint (the balls of the feet, :data:`FEET`), a frame is in
    stance when the foot moves slower than ``stance_speed_m_s`` (its speed from the previous frame;
    frame 0 takes frame 1's) and lies within ``stance_height_m`` of its lowest height in the motion;
    the speed counted is the horizontal (x, z) one. ``joints``: ``(T, 22, 3)`` m, Y up, or
    ``(N, T, 22, 3)`` windows, each judged on its own and their frame pairs pooled."""
    j = _joints(joints, "joints")
    if j.shape[-2] != len(JOINT22_NAMES):
        raise MetricInputError(f"foot skating reads HumanML3D's 22 joints, got {j.shape[-2]}")
    if not (math.isfinite(fps) and fps > 0):
        raise MetricInputError(f"fps must be positive, got {fps!r}")
    motions = j.reshape(-1, *j.shape[-3:]) if j.ndim >= 3 else j[None]
    speeds = []
    for m in motions:
        for f in FEET:
            p = m[:, f]
            if len(p) < 2:
                continue
            speed = np.linalg.norm(np.diff(p, axis=0), axis=1) * fps
            stance = np.zeros(len(p), bool)
            stance[1:] = speed < stance_speed_m_s
            stance[0] = stance[1]
            stance &= p[:, 1] - p[:, 1].min() < stance_height_m
            both = stance[1:] & stance[:-1]
            speeds.append(np.linalg.norm(np.diff(p[:, [0, 2]], axis=0), axis=1)[both] * fps)
    s = np.concatenate(speeds) if speeds else np.zeros(0)
    return float(s.mean() * MM) if s.size else float("nan")


# ---------------------------------------------------------------------------------------- Mix and Match's AFD
def average_frame_distance(pred: Any, truth: Any, squared: bool = False) -> float:
    """Interaction Mix and Match's AFD of one motion (mm): ``1/T sum_t |x'_t - x_t|``, the Euclidean
    norm of the whole pose's difference (all ``J * 3`` coordinates, mm) averaged over the ``T``
    frames; ``pred``/``truth`` ``(T, J, 3)`` m (world positions). ``squared=True`` averages the
    squared norm instead (mm², the per-frame summed squared joint error), the reading of the
    paper's equation (6) that some re-implementations take."""
    p, t = _pair(pred, truth)
    d = np.linalg.norm((p - t).reshape(*p.shape[:-2], -1) * MM, axis=-1)
    return float((d**2 if squared else d).mean())


def afd_per_class(preds: Sequence[Any], truths: Sequence[Any], classes: Sequence[str],
                  squared: bool = False) -> dict[str, float]:  # fmt: skip
    """AFD per interaction class (Mix and Match's Table 1): the mean over the motions of each class of
    :func:`average_frame_distance`; motions may differ in length. Key ``"mean"``: the mean over
    classes."""
    if not (len(preds) == len(truths) == len(classes)) or not len(preds):
        raise MetricInputError(f"afd_per_class needs as many predictions ({len(preds)}), truths ({len(truths)}) "
                               f"and classes ({len(classes)}), at least one")  # fmt: skip
    by: dict[str, list[float]] = {}
    for p, t, c in zip(preds, truths, classes):
        by.setdefault(str(c), []).append(average_frame_distance(p, t, squared))
    out = {c: float(np.mean(v)) for c, v in sorted(by.items())}
    out["mean"] = float(np.mean(list(out.values())))
    return out


# ---------------------------------------------------------------------------------------- contacts: scores
def contact_scores(pred: Any, ref: Any) -> dict[str, float]:
    """Precision, recall and F1 of bool contact labels ``pred`` against the reference ``ref`` (same
    shape: per vertex ``(2, T, V)`` or per capsule ``(2, T, C)``), with the counts ``tp``, ``fp``,
    ``fn``; each score is 1.0 when its denominator is empty (nothing to find, nothing claimed). The
    definition of the toolkit's contact evaluation (``evaluation.contacts.label_scores``)."""
    p, r = np.asarray(as_array(pred, "pred")).astype(bool), np.asarray(as_array(ref, "ref")).astype(bool)
    if p.shape != r.shape:
        raise MetricInputError(f"contact labels {p.shape} and reference {r.shape} differ in shape")
    tp, fp, fn = int(np.sum(p & r)), int(np.sum(p & ~r)), int(np.sum(~p & r))
    return {"precision": tp / (tp + fp) if tp + fp else 1.0, "recall": tp / (tp + fn) if tp + fn else 1.0,
            "f1": 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 1.0, "tp": tp, "fp": fp, "fn": fn}  # fmt: skip


# ---------------------------------------------------------------------------------------- the capsule proxy
#: The capsule proxy of a body given only its 22 joints: ``(name, start joint, end joint, radius m)``.
#: One capsule per bone of HumanML3D's tree (:data:`~dualhuman_builder.body.joints.JOINT22_PARENTS`)
#: plus two that the joints do not bound: each hand (from the wrist along the forearm's direction,
#: :data:`HAND_LENGTH_M`) and the head (from the head joint along the neck's direction,
#: :data:`HEAD_LENGTH_M`). Radii: the median distance from each capsule's axis of the vertices of
#: anny's average body (rest pose) nearest to that axis, rounded to 5 mm
#: (``tests/models/test_metrics.py::test_capsule_radii_fit_the_average_body`` measures them again).
CAPSULES: tuple[tuple[str, int, int, float], ...] = (
    ("left_hip", 0, 1, 0.1), ("right_hip", 0, 2, 0.1), ("pelvis", 0, 3, 0.095),
    ("left_thigh", 1, 4, 0.07), ("right_thigh", 2, 5, 0.07), ("spine", 3, 6, 0.125),
    ("left_shin", 4, 7, 0.045), ("right_shin", 5, 8, 0.045), ("chest", 6, 9, 0.11),
    ("left_foot", 7, 10, 0.035), ("right_foot", 8, 11, 0.035), ("upper_chest", 9, 12, 0.055),
    ("left_collar", 9, 13, 0.095), ("right_collar", 9, 14, 0.095), ("neck", 12, 15, 0.065),
    ("left_shoulder", 13, 16, 0.085), ("right_shoulder", 14, 17, 0.085), ("left_upper_arm", 16, 18, 0.045),
    ("right_upper_arm", 17, 19, 0.045), ("left_forearm", 18, 20, 0.025), ("right_forearm", 19, 21, 0.025),
    ("left_hand", 20, -1, 0.045), ("right_hand", 21, -1, 0.045), ("head", 15, -1, 0.08),
)  # fmt: skip
#: Capsules :func:`proxy_penetration` leaves out (see there).
HANDS_NOT_PENETRATING = ("left_hand", "right_hand")
HAND_LENGTH_M = 0.13  #: wrist to the fingers' middle (m), along the forearm; the fingertips end about one radius beyond
HEAD_LENGTH_M = 0.07  #: head joint (the skull's base) to the centre of the crown's cap (m), along the neck


def capsule_radii() -> np.ndarray:
    """``(C,)`` radii (m) of :data:`CAPSULES`."""
    return np.array([c[3] for c in CAPSULES])


def capsule_segments(joints: Any) -> tuple[np.ndarray, np.ndarray]:
    """Axes of the :data:`CAPSULES` of ``joints (..., 22, 3)`` m: ``(starts, ends)`` each ``(..., C, 3)``."""
    j = _joints(joints, "joints")
    if j.shape[-2] != len(JOINT22_NAMES):
        raise MetricInputError(f"the capsule proxy reads HumanML3D's 22 joints, got {j.shape[-2]}")
    starts = j[..., [c[1] for c in CAPSULES], :]
    ends = np.empty_like(starts)
    for k, (name, s, e, _) in enumerate(CAPSULES):
        if e >= 0:
            ends[..., k, :] = j[..., e, :]
            continue
        parent = JOINT22_PARENTS[s]
        direction = j[..., s, :] - j[..., parent, :]
        n = np.linalg.norm(direction, axis=-1, keepdims=True)
        direction = np.divide(direction, n, out=np.zeros_like(direction), where=n > 0)
        ends[..., k, :] = j[..., s, :] + direction * (HEAD_LENGTH_M if name == "head" else HAND_LENGTH_M)
    return starts, ends


def segment_distances(p0: Any, p1: Any, q0: Any, q1: Any) -> np.ndarray:
    """Shortest distances ``(..., M, N)`` between every segment ``p0[..., m] -> p1[..., m]`` and every
    ``q0[..., n] -> q1[..., n]`` (``(..., M, 3)`` and ``(..., N, 3)``, any unit; a segment of zero
    length is its point). Clamped closed form of the closest points of two segments (Ericson,
    Real-Time Collision Detection, 5.1.9)."""
    p0, p1, q0, q1 = (as_array(x, n) for x, n in ((p0, "p0"), (p1, "p1"), (q0, "q0"), (q1, "q1")))
    if p0.shape != p1.shape or q0.shape != q1.shape or p0.shape[:-2] != q0.shape[:-2] or p0.shape[-1] != 3:
        raise MetricInputError(f"segments disagree in shape: {p0.shape}, {p1.shape} and {q0.shape}, {q1.shape}")
    P0, d1 = p0[..., :, None, :], (p1 - p0)[..., :, None, :]
    Q0, d2 = q0[..., None, :, :], (q1 - q0)[..., None, :, :]
    r = P0 - Q0
    a = (d1 * d1).sum(-1)
    e = (d2 * d2).sum(-1)
    f = (d2 * r).sum(-1)
    c = (d1 * r).sum(-1)
    b = (d1 * d2).sum(-1)
    tiny = 1e-18
    a, e = np.broadcast_to(a, b.shape), np.broadcast_to(e, b.shape)
    denom = a * e - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(denom > 1e-12 * a * e, np.clip((b * f - c * e) / denom, 0, 1), 0.0)
        s = np.where(a <= tiny, 0.0, s)
        t = np.where(e > tiny, (b * s + f) / np.where(e > tiny, e, 1.0), 0.0)
        # t outside [0, 1]: clamp it and recompute s for the clamped t
        t_lo, t_hi = t < 0, t > 1
        t = np.clip(t, 0, 1)
        s_new = np.where(a > tiny, np.clip((b * t - c) / np.where(a > tiny, a, 1.0), 0, 1), 0.0)
        s = np.where(t_lo | t_hi, s_new, s)
        # q a point: t = 0 and s the closest point of p to it
        s = np.where((e <= tiny) & (a > tiny), np.clip(-c / np.where(a > tiny, a, 1.0), 0, 1), s)
        t = np.where(e <= tiny, 0.0, t)
    c1 = P0 + d1 * s[..., None]
    c2 = Q0 + d2 * t[..., None]
    return np.linalg.norm(c1 - c2, axis=-1)


#: Frames per block of the capsule proxy's pairwise distances (bounds its memory: ~10 MB a temporary).
PROXY_CHUNK = 2048


def _capsule_gaps(joints_a: Any, joints_b: Any) -> np.ndarray:
    """``(..., C, C)`` m: surface gap of every capsule of a against every capsule of b (axis distance
    minus both radii; negative where they overlap), computed :data:`PROXY_CHUNK` frames at a time."""
    a, b = _pair(joints_a, joints_b, ("joints_a", "joints_b"))
    lead = a.shape[:-2]
    a, b = a.reshape(-1, *a.shape[-2:]), b.reshape(-1, *b.shape[-2:])
    r = capsule_radii()
    out = np.empty((len(a), len(r), len(r)))
    for i in range(0, len(a), PROXY_CHUNK):
        sa, ea = capsule_segments(a[i : i + PROXY_CHUNK])
        sb, eb = capsule_segments(b[i : i + PROXY_CHUNK])
        out[i : i + PROXY_CHUNK] = segment_distances(sa, ea, sb, eb) - r[:, None] - r[None, :]
    return out.reshape(*lead, len(r), len(r))


def proxy_penetration(joints_a: Any, joints_b: Any) -> dict[str, Any]:
    """Penetration between two people given as joints ``(T, 22, 3)`` m (or ``(..., 22, 3)``), on the
    capsule proxy (:data:`CAPSULES`): the depth of a frame is the largest overlap of a capsule of one
    person with a capsule of the other (``r_i + r_j - axis distance``, 0 when none overlap), mm.

    Returns ``depth_mm`` (per frame, the leading shape), ``max_depth_mm`` (worst frame),
    ``mean_depth_mm`` (mean over frames) and ``frames_penetrating`` (share of frames with a depth
    above 0). A proxy: capsules round every limb and miss the torso's width, so compare figures of
    the proxy with figures of the proxy (e.g. generated against ground truth), never with meshes'.
    The hand capsules (:data:`HANDS_NOT_PENETRATING`) are left out: a hand is flat and closes
    around what it holds, so round hands overlap wherever two people hold hands (as in the demo's
    handshake, whose meshes do not overlap); they still count for contacts."""
    gaps = _capsule_gaps(joints_a, joints_b)
    names = [c[0] for c in CAPSULES]
    hands = [names.index(n) for n in HANDS_NOT_PENETRATING]
    gaps[..., hands, :] = np.inf
    gaps[..., :, hands] = np.inf
    depth = np.maximum(-gaps.min(axis=(-1, -2)), 0.0) * MM
    return {"depth_mm": depth, "max_depth_mm": float(depth.max()), "mean_depth_mm": float(depth.mean()),
            "frames_penetrating": float((depth > 0).mean())}  # fmt: skip


def proxy_contact_labels(joints_a: Any, joints_b: Any, threshold_m: float = CONTACT_THRESHOLD_M) -> np.ndarray:
    """Per-capsule contacts ``(2, ..., C)`` bool of two people given as joints ``(..., 22, 3)`` m: a
    capsule of one person is in contact when its surface comes closer than ``threshold_m`` to a
    capsule of the other (penetration included), the contacts stage's rule on the capsule proxy.
    Index 0: a's capsules, 1: b's, as in the contacts stage's ``(2, T, V)`` labels."""
    if not (math.isfinite(threshold_m) and threshold_m > 0):
        raise MetricInputError(f"threshold_m must be a positive distance in metres, got {threshold_m!r}")
    close = _capsule_gaps(joints_a, joints_b) < threshold_m
    return np.stack([close.any(axis=-1), close.any(axis=-2)])


def proxy_contact_scores(pred_a: Any, pred_b: Any, truth_a: Any, truth_b: Any,
                         threshold_m: float = CONTACT_THRESHOLD_M) -> dict[str, float]:  # fmt: skip
    """:func:`contact_scores` of the capsule contacts (:func:`proxy_contact_labels`) of a predicted
    pair against those of the ground-truth pair, all ``(..., 22, 3)`` m on the same frames."""
    _pair(pred_a, truth_a, ("pred_a", "truth_a"))
    return contact_scores(proxy_contact_labels(pred_a, pred_b, threshold_m),
                          proxy_contact_labels(truth_a, truth_b, threshold_m))  # fmt: skip


def proxy_interaction(pred_actor: Any, pred_reactor: Any, truth_actor: Any, truth_reactor: Any,
                      threshold_m: float = CONTACT_THRESHOLD_M) -> dict[str, float]:  # fmt: skip
    """The interaction figures of a predicted pair against the ground-truth pair on the capsule proxy,
    all ``(..., 22, 3)`` m on the same frames: ``penetration_mm`` / ``penetration_max_mm`` (mean and
    worst per-frame depth of the prediction, :func:`proxy_penetration`), the same of the truth
    (``truth_penetration_mm``, ``truth_penetration_max_mm``: the proxy's own level on real motion), and
    ``contact_precision``, ``contact_recall``, ``contact_f1`` (:func:`proxy_contact_scores`)."""
    pred, truth = proxy_penetration(pred_actor, pred_reactor), proxy_penetration(truth_actor, truth_reactor)
    c = proxy_contact_scores(pred_actor, pred_reactor, truth_actor, truth_reactor, threshold_m)
    return {"penetration_mm": pred["mean_depth_mm"], "penetration_max_mm": pred["max_depth_mm"],
            "truth_penetration_mm": truth["mean_depth_mm"], "truth_penetration_max_mm": truth["max_depth_mm"],
            "contact_precision": c["precision"], "contact_recall": c["recall"], "contact_f1": c["f1"]}  # fmt: skip


# ---------------------------------------------------------------------------------------- meshes
def body_vertices(pose: Any, transl: Any, shape: Any, model=None, batch: int = 64) -> np.ndarray:
    """anny's vertices ``(T, V, 3)`` float32 m posed from body parameters as the export stores them
    (``motion.npz``: ``pose (T, J, 3)`` rotation vectors, ``transl (T, 3)`` m, ``shape (P,)``;
    :mod:`dualhuman_builder.body.model`), ``batch`` frames per call. ``model`` defaults to the
    process-wide anny."""
    import torch

    from dualhuman_builder.body.model import get_body_model

    model = model or get_body_model()
    pose, transl, shape = as_array(pose, "pose"), as_array(transl, "transl"), as_array(shape, "shape")
    if pose.ndim != 3 or pose.shape[-1] != 3 or transl.shape != (pose.shape[0], 3) or shape.ndim != 1:
        raise MetricInputError(f"body parameters pose {pose.shape}, transl {transl.shape}, shape {shape.shape}: "
                               "expected (T, J, 3), (T, 3) and (P,)")  # fmt: skip
    out = np.empty((pose.shape[0], model.num_vertices, 3), np.float32)
    sh = torch.as_tensor(shape, dtype=model.dtype, device=model.device)
    with torch.no_grad():
        for i in range(0, pose.shape[0], max(1, int(batch))):
            p = torch.as_tensor(pose[i : i + batch], dtype=model.dtype, device=model.device)
            t = torch.as_tensor(transl[i : i + batch], dtype=model.dtype, device=model.device)
            out[i : i + len(p)] = model(p, sh, t).vertices.cpu().numpy()
    return out


def motion_vertices(motion: dict[str, np.ndarray], person: str, frames: Any = None, model=None) -> np.ndarray:
    """:func:`body_vertices` of person ``"a"`` or ``"b"`` of an export's ``motion.npz`` (as
    :func:`~dualhuman_builder.export.files.load_motion` reads it), on ``frames`` (indices or a slice;
    default all). An export imported from joints only has no body parameters: MetricInputError (score
    it with the capsule proxy)."""
    keys = [f"{person}.pose", f"{person}.transl", f"{person}.shape"]
    if any(k not in motion for k in keys):
        raise MetricInputError(f"motion has no body parameters for person {person!r} (needs {keys})",
                               fix="score joints-only data with proxy_penetration / proxy_contact_labels")  # fmt: skip
    sel = slice(None) if frames is None else frames
    return body_vertices(np.asarray(motion[keys[0]])[sel], np.asarray(motion[keys[1]])[sel], motion[keys[2]], model)


@functools.lru_cache(maxsize=2)
def _collision_term(sign: str):
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.geometry.collision import CollisionTerm

    return CollisionTerm(get_body_model().faces.cpu().numpy(), sign=sign, threads=1)


def mesh_penetration(verts_a: Any, verts_b: Any, sign: str = "winding") -> dict[str, Any]:
    """Penetration between two anny meshes ``(T, V, 3)`` m, exact (the toolkit's collision kernels,
    :class:`~dualhuman_builder.geometry.collision.CollisionTerm` ``.penetration``): per frame, the
    depth of the deepest vertex of either body inside the other and the share of both bodies'
    vertices inside the other. ``sign="winding"`` decides inside by the generalised winding number
    (right where a posed body crosses itself; ``"normal"`` is faster and exact on a body that does not).

    Returns ``depth_mm (T,)``, ``max_depth_mm``, ``mean_depth_mm``, ``frames_penetrating`` (share of
    frames with any vertex inside) and ``share`` (penetrating vertices over both bodies' ``2V``,
    mean over frames)."""
    a, b = _pair(verts_a, verts_b, ("verts_a", "verts_b"))
    if a.ndim == 2:
        a, b = a[None], b[None]
    pen = _collision_term(sign).penetration(a.astype(np.float32), b.astype(np.float32))
    depth = np.asarray(pen["max_depth_m"], np.float64) * MM
    return {"depth_mm": depth, "max_depth_mm": float(depth.max()), "mean_depth_mm": float(depth.mean()),
            "frames_penetrating": float((depth > 0).mean()), "share": float(np.mean(pen["share"]))}  # fmt: skip


def mesh_contact_labels(verts_a: Any, verts_b: Any, threshold_m: float = CONTACT_THRESHOLD_M,
                        band_m: float | None = None) -> np.ndarray:  # fmt: skip
    """Per-vertex contacts ``(2, T, V)`` bool of two anny meshes ``(T, V, 3)`` m, computed by the
    contacts stage's own code (:func:`~dualhuman_builder.contacts.compute.contacts_from_vertices`,
    one process) at ``threshold_m``: the labels an export's ``contacts.npz`` holds when made at the
    same threshold (``export.files.load_contacts(path)["labels"]``)."""
    from dualhuman_builder.contacts.compute import (
        DEFAULT_BAND_M,
        contacts_from_vertices,
        default_topology,
    )

    a, b = _pair(verts_a, verts_b, ("verts_a", "verts_b"))
    band = max(DEFAULT_BAND_M, threshold_m) if band_m is None else band_m
    res = contacts_from_vertices(a, b, default_topology(), threshold_m=threshold_m, band_m=band, workers=1)
    return res.labels


def mesh_contact_scores(pred_a: Any, pred_b: Any, truth_a: Any, truth_b: Any,
                        threshold_m: float = CONTACT_THRESHOLD_M) -> dict[str, float]:  # fmt: skip
    """:func:`contact_scores` of the per-vertex contacts of a predicted pair of meshes against the
    ground-truth pair's (:func:`mesh_contact_labels` of both), ``(T, V, 3)`` m on the same frames."""
    _pair(pred_a, truth_a, ("pred_a", "truth_a"))
    return contact_scores(mesh_contact_labels(pred_a, pred_b, threshold_m),
                          mesh_contact_labels(truth_a, truth_b, threshold_m))  # fmt: skip


# ---------------------------------------------------------------------------------------- summaries
def summarize(values: Iterable[Any]) -> tuple[float, float]:
    """``(mean, std)`` of a figure over runs (seeds), for "mean ± std": the sample standard deviation
    (ddof 1; 0.0 for a single value). NaN values propagate."""
    v = as_array(list(values), "values").ravel()
    if v.size == 0:
        raise MetricInputError("summarize needs at least one value")
    return float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else 0.0

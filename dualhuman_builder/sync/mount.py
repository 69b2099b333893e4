"""Mounting of VIVE trackers on suit segments, and the suit world against the tracker world.

Model, for ``K`` trackers on one actor, tracker ``k`` strapped to suit segment ``k``, every sample
on one common timeline ``t``::

    R_tr,k(t) = Y(t) R_seg,k(t) M_k
    p_tr,k(t) = Y(t) p_seg,k(t) + d(t) + Y(t) R_seg,k(t) m_k  [+ Y(t) sum_a [dp_a]x R_a eps_a]

* ``R_seg``, ``p_seg``: the suit's segment orientation (segment -> suit world) and origin (suit
  world, m); ``R_tr``, ``p_tr``: the tracker's pose in the tracker world (drift-free reference);
* ``M_k``: tracker frame in the segment frame (rotation), ``m_k``: tracker origin in the segment
  frame (m) — the mount, constant;
* ``Y(t)``: rotation about world +Y by ``psi(t)`` (rad), the suit's heading in the tracker world (a
  constant offset plus a slow drift), piecewise linear on knots;
* ``d(t)``: translation (m, tracker world), the suit's position drift plus any constant offset
  between the worlds, piecewise linear on finer knots with a random-walk prior;
* optional (:class:`SuitChain`): ``eps_a``, the constant misalignment of each suit segment ``a`` on
  the chain from the root to tracker ``k``'s segment, moving it by ``[dp_a]x R_a eps_a`` (first
  order; ``dp_a`` the bone from ``a`` towards the tracker, ``R_a`` its measured orientation).

:func:`calibrate_mounts` estimates all of these; :class:`MountCalibration` carries them and maps
suit poses into the tracker world and tracker poses back onto their segments.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.linalg import solveh_banded
from scipy.spatial.transform import Rotation

_MIN_DURATION_S = 2.0
_MIN_SAMPLES = 10
#: Rotation / translation residuals above max(6 x median, floor) are rejected as outliers.
_ROT_FLOOR_RAD = math.radians(2.0)
_TRANS_FLOOR_M = 0.02
_OUTLIER_FACTOR = 6.0
#: Prior std of a mount translation (m) when no tracker sites are given: the "tiny ridge" for
#: segments that hardly rotate.
_MOUNT_PRIOR_M = 1.0
#: Prior std per axis (m) of a mount translation around its site, when sites are given.
SITE_PRIOR_M = 0.02
#: Heading-offset search (module docstring): a coarse grid of +-_SCAN_RANGE_DEG, then a parabola
#: through the best grid point's neighbours at +-_SCAN_FINE_DEG.
_SCAN_RANGE_DEG = 20.0
_SCAN_STEP_DEG = 2.0
_SCAN_FINE_DEG = 0.5
#: Block length (s) used to account for correlated residuals in the uncertainties.
_BLOCK_S = 1.0
#: A carried mount (:class:`CarriedMounts`) whose rotation residuals on this take have a median
#: above this (deg) is taken for a tracker strapped again since the calibration take, and solved
#: afresh (residuals are ~1 deg for a tracker that stayed put).
MOVED_DEG = 3.0
#: Floor (m, per axis) of a carried mount translation's prior std: the calibration take's own
#: uncertainty, but never trusted below this (the simulated calibration takes' offsets came out 7.3
#: and 5.6 mm RMS off, ~3.8 mm per axis, more than their stated 1-sigma: bench_fit_accuracy.py
#: --calibration).
CARRIED_FLOOR_M = 0.004


@dataclass(frozen=True, eq=False)
class MountCalibration:
    """Result of :func:`calibrate_mounts` (``T`` samples, ``K`` trackers).

    Mounts (tracker in segment frame): ``rotations (K, 4)`` xyzw (``M_k``), ``translations (K, 3)`` m
    (``m_k``). Suit world -> tracker world: ``heading_rad (T,)`` (``psi``, rotation about +Y) and
    ``drift (T, 3)`` m (``d``) at the input times, and the knots they are interpolated from
    (``heading_knots_s``/``heading_knots_rad``, ``drift_knots_s``/``drift_knots_m``; seconds on the
    input timeline). Fit quality per tracker, over the inlier samples: ``rotation_rms_deg (K,)``
    (RMS angle of ``(Y R_seg M)^T R_tr``), ``translation_rms_m (K,)`` (RMS norm of the position
    residual); 1-sigma uncertainties of the mounts ``rotation_std_deg (K,)`` and
    ``translation_std_m (K,)`` (norms: sqrt of the covariance trace, inflated for residuals
    correlated over ~1 s; with tracker sites they include ``heading_std_deg``). With sites,
    ``heading_offset_deg`` is the constant heading correction the constellation search applied and
    ``heading_std_deg`` its 1-sigma (both 0 without sites). With a :class:`SuitChain`:
    ``chain_segments (A,)`` the suit segments whose misalignment was solved,
    ``chain_misalignment_rad (A, 3)`` each one's ``eps`` (rotation vector in the segment's measured
    frame: ``R_true = R_meas exp(-[eps]x)``) and ``chain_std_deg (A,)`` its spread (norm) under the
    solve's covariance, like ``translation_std_m`` before its inflation: too small where the prior
    decides; empty without. With :class:`CarriedMounts`: ``carried (K,)`` the trackers whose mount
    came from the calibration take (their rotation is that take's, their translation its value
    refined by this take under its uncertainty), ``carry_rejected (K,)`` those offered but found
    strapped again (solved afresh); both empty (or all False) without. ``common_offset_std_m``: 1-sigma (m, norm) of the part all trackers' offsets share, seen
    in the world over the take (their mean world position relative to their segments): what the
    actor's root is known to. An actor who turns no segment cannot tell it from the suit's drift, so
    it rests on the sites' prior (about ``site_prior_m * sqrt(3 / K)``). ``outliers (T, K)``: valid samples
    rejected (origin jumps, rotation or
    position residual above max(6 x median, 2 deg / 2 cm)). ``calibrated (K,)``: False where a
    tracker had fewer than 10 usable samples; its entries are NaN.
    """

    rotations: np.ndarray
    translations: np.ndarray
    heading_rad: np.ndarray
    drift: np.ndarray
    rotation_rms_deg: np.ndarray
    translation_rms_m: np.ndarray
    rotation_std_deg: np.ndarray
    translation_std_m: np.ndarray
    outliers: np.ndarray
    calibrated: np.ndarray
    heading_knots_s: np.ndarray
    heading_knots_rad: np.ndarray
    drift_knots_s: np.ndarray
    drift_knots_m: np.ndarray
    heading_offset_deg: np.ndarray = field(default_factory=lambda: np.asarray(0.0))
    heading_std_deg: np.ndarray = field(default_factory=lambda: np.asarray(0.0))
    chain_segments: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    chain_misalignment_rad: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    chain_std_deg: np.ndarray = field(default_factory=lambda: np.zeros(0))
    common_offset_std_m: np.ndarray = field(default_factory=lambda: np.asarray(float("nan")))
    carried: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    carry_rejected: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    def __post_init__(self):
        for name in self.__dataclass_fields__:
            getattr(self, name).setflags(write=False)

    @property
    def num_trackers(self) -> int:
        return self.rotations.shape[0]

    def heading_at(self, times_s) -> np.ndarray:
        """``psi`` (rad) at ``times_s`` (any shape, s on the calibration's timeline); linear
        between knots, held constant beyond the first and last knot."""
        t = np.asarray(times_s, dtype=np.float64)
        return np.interp(t, self.heading_knots_s, self.heading_knots_rad)

    def drift_at(self, times_s) -> np.ndarray:
        """``d`` (m, tracker world) at ``times_s`` ``(...)`` -> ``(..., 3)``; linear between knots,
        constant beyond the ends."""
        t = np.asarray(times_s, dtype=np.float64)
        return np.stack([np.interp(t, self.drift_knots_s, self.drift_knots_m[:, a]) for a in range(3)], axis=-1)

    def suit_to_tracker_world(self, times_s, rot, pos) -> tuple[np.ndarray, np.ndarray]:
        """Suit poses into the tracker world: ``(Y(t) R, Y(t) p + d(t))``.

        ``times_s (T,)``; ``rot (T, ..., 4)`` xyzw orientations (suit world), ``pos (T, ..., 3)``
        positions (suit world, m), any number of middle axes (e.g. segments). Returns the
        orientations ``(T, ..., 4)`` and positions ``(T, ..., 3)`` in the tracker world.
        """
        t = np.asarray(times_s, dtype=np.float64)
        rot = np.asarray(rot, dtype=np.float64)
        pos = np.asarray(pos, dtype=np.float64)
        if t.ndim != 1 or rot.shape[:1] != t.shape or pos.shape[:1] != t.shape or rot.shape[-1] != 4 \
                or pos.shape[-1] != 3 or rot.shape[:-1] != pos.shape[:-1]:  # fmt: skip
            raise ValueError(f"expected times (T,), rot (T, ..., 4), pos (T, ..., 3); got {t.shape}, {rot.shape}, "
                             f"{pos.shape}")  # fmt: skip
        mid = rot.shape[1:-1]
        n_mid = int(np.prod(mid)) if mid else 1
        psi = np.repeat(self.heading_at(t), n_mid)
        Y = Rotation.from_rotvec(psi[:, None] * np.array([0.0, 1.0, 0.0]))
        out_rot = (Y * Rotation.from_quat(rot.reshape(-1, 4))).as_quat().reshape(rot.shape)
        d = np.repeat(self.drift_at(t), n_mid, axis=0)
        out_pos = (Y.apply(pos.reshape(-1, 3)) + d).reshape(pos.shape)
        return out_rot, out_pos

    def segment_from_tracker(self, trk_rot, trk_pos, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Segment pose implied by tracker ``k``'s pose, in the **tracker world**:
        ``R = R_tr M_k^-1``, ``p = p_tr - R m_k`` (this equals ``Y R_seg`` and ``Y p_seg + d``).
        ``trk_rot (..., 4)`` xyzw, ``trk_pos (..., 3)`` m -> ``(rot (..., 4), pos (..., 3))``."""
        if not 0 <= k < self.num_trackers:
            raise ValueError(f"tracker index {k} out of range 0..{self.num_trackers - 1}")
        if not self.calibrated[k]:
            raise ValueError(f"tracker {k} is not calibrated (no usable samples)")
        q = np.asarray(trk_rot, dtype=np.float64)
        p = np.asarray(trk_pos, dtype=np.float64)
        if q.shape[-1] != 4 or p.shape[-1] != 3 or q.shape[:-1] != p.shape[:-1]:
            raise ValueError(f"expected trk_rot (..., 4) and trk_pos (..., 3), got {q.shape} and {p.shape}")
        r = Rotation.from_quat(q.reshape(-1, 4)) * Rotation.from_quat(self.rotations[k]).inv()
        pos = p.reshape(-1, 3) - r.apply(np.array(self.translations[k]))
        return r.as_quat().reshape(q.shape), pos.reshape(p.shape)

    def as_dict(self) -> dict:
        """JSON-able summary: mounts, fit quality, outlier counts and the heading/drift knots."""

        def lst(a):  # NaN (uncalibrated trackers) -> None, for strict JSON
            return np.where(np.isfinite(a), a, None).tolist()

        return {
            "rotations_xyzw": lst(self.rotations),
            "translations_m": lst(self.translations),
            "calibrated": self.calibrated.tolist(),
            "rotation_rms_deg": lst(self.rotation_rms_deg),
            "translation_rms_m": lst(self.translation_rms_m),
            "rotation_std_deg": lst(self.rotation_std_deg),
            "translation_std_m": lst(self.translation_std_m),
            "outliers_per_tracker": self.outliers.sum(axis=0).astype(int).tolist(),
            "heading_knots_s": self.heading_knots_s.tolist(),
            "heading_knots_rad": self.heading_knots_rad.tolist(),
            "drift_knots_s": self.drift_knots_s.tolist(),
            "drift_knots_m": self.drift_knots_m.tolist(),
            "heading_offset_deg": float(self.heading_offset_deg),
            "heading_std_deg": float(self.heading_std_deg) if np.isfinite(self.heading_std_deg) else None,
            "chain_segments": self.chain_segments.tolist(),
            "chain_misalignment_deg": np.degrees(self.chain_misalignment_rad).tolist(),
            "chain_std_deg": self.chain_std_deg.tolist(),
            "common_offset_std_mm": round(float(self.common_offset_std_m) * 1000, 3) if np.isfinite(self.common_offset_std_m) else None,
            "carried": self.carried.tolist(),
            "carry_rejected": self.carry_rejected.tolist(),
        }


@dataclass(frozen=True, eq=False)
class CarriedMounts:
    """Mounts solved on a calibration take of the same session, for :func:`calibrate_mounts` on
    another take (``K`` trackers, in that take's order): trackers strapped on once per session
    keep their mounts, and the suit's segment misalignments (its sensor-to-segment calibration)
    are the session's too.

    A take whose actor hardly turns a segment cannot tell a tracker's mounting rotation from the
    suit's heading, nor the trackers' shared offset from the suit's position drift; a calibration
    take whose actors bow, twist, raise their arms and turn on the spot can. ``carried (K,)``
    bool: which trackers have a mount here; ``rotations (K, 4)`` xyzw and ``translations (K, 3)``
    m (segment frame), ``rotation_std_deg (K,)`` and ``translation_std_m (K,)`` (1-sigma, norms),
    NaN where not carried; ``chain``: suit segment index (MVN order) -> misalignment ``eps (3,)``
    rad (:class:`SuitChain`); ``source``: the calibration take's name, for reports.
    :meth:`from_calibration` picks a calibration's mounts by tracker serial."""

    carried: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    rotation_std_deg: np.ndarray
    translation_std_m: np.ndarray
    chain: dict = field(default_factory=dict)
    source: str = ""

    @classmethod
    def empty(cls, K: int, source: str = "") -> "CarriedMounts":
        """Nothing carried for ``K`` trackers (the calibration take had none of them)."""
        return cls(np.zeros(K, bool), np.full((K, 4), np.nan), np.full((K, 3), np.nan), np.full(K, np.nan),
                   np.full(K, np.nan), {}, source)  # fmt: skip

    @classmethod
    def from_calibration(cls, cal: "MountCalibration", cal_keys, keys, source: str = "") -> "CarriedMounts":
        """The mounts of ``cal`` (a :class:`MountCalibration` of trackers ``cal_keys``, e.g.
        ``(serial, segment)`` pairs) for trackers ``keys`` of another take: a tracker is carried
        where its key appears in ``cal_keys`` and ``cal`` calibrated it."""
        cal_keys, keys = list(cal_keys), list(keys)
        out = cls.empty(len(keys), source)
        for k, key in enumerate(keys):
            if key in cal_keys:
                j = cal_keys.index(key)
                if cal.calibrated[j] and np.all(np.isfinite(cal.rotations[j])) and np.all(np.isfinite(cal.translations[j])):
                    out.carried[k] = True
                    for name in ("rotations", "translations", "rotation_std_deg", "translation_std_m"):
                        getattr(out, name)[k] = getattr(cal, name)[j]
        out.chain.update({int(g): np.asarray(e, np.float64).copy() for g, e in zip(cal.chain_segments, cal.chain_misalignment_rad)})
        return out

    def check(self, K: int) -> None:
        if self.carried.shape != (K,) or self.rotations.shape != (K, 4) or self.translations.shape != (K, 3) \
                or self.rotation_std_deg.shape != (K,) or self.translation_std_m.shape != (K,):  # fmt: skip
            raise ValueError(f"carried mounts are for {self.carried.shape[0]} trackers with shapes "
                             f"{self.rotations.shape}, {self.translations.shape}; this take has {K}")  # fmt: skip
        c = self.carried
        if not (np.all(np.isfinite(self.rotations[c])) and np.all(np.isfinite(self.translations[c]))):
            raise ValueError("carried mounts must be finite where carried")
        if np.any(np.abs(np.linalg.norm(self.rotations[c], axis=-1) - 1.0) > 1e-3):
            raise ValueError("carried mount rotations must be unit quaternions")


@dataclass(frozen=True, eq=False)
class SuitChain:
    """The suit's kinematic chain from its root to each tracked segment, so that
    :func:`calibrate_mounts` can solve the suit's segment misalignments with the mounts.

    An inertial suit places each segment at its parent's origin plus the bone vector turned by the
    parent's *measured* orientation, so a constant misalignment ``eps_a`` of segment ``a`` (its
    measured frame is the true one turned by ``exp([eps_a]x)``: ``R_a = R_true exp([eps_a]x)``; rad,
    in its own frame) puts every segment past it off by the same vector: the true position is the
    measured one plus ``[dp]x R_a eps_a`` to first order (``dp`` the bone from ``a`` to the next
    segment towards the tracker, world). A hand tracker sees the sum of its arm's and spine's
    misalignments: tens of millimetres, which without this model the tracker's mount offset and
    the suit's drift absorb (they then carry those errors into the fit).

    ``rot (T, S, 4)`` xyzw and ``pos (T, S, 3)`` m: every suit segment, suit world, on the
    calibration's timeline (values at samples no tracker uses are ignored); ``paths``: per tracker,
    the links ``(a, next)`` (segment indices into ``S``) from the root to its segment;
    ``prior_deg``: prior std of each misalignment, per axis (deg).
    """

    rot: np.ndarray
    pos: np.ndarray
    paths: tuple
    prior_deg: float = 2.0

    @classmethod
    def of(cls, rot, pos, tracked, parents, prior_deg: float = 2.0) -> "SuitChain":
        """Chain to the ``tracked (K,)`` segment indices; ``parents (S,)``: each segment's parent
        index (None or -1 for the root)."""
        paths = []
        for s in tracked:
            links, cur = [], int(s)
            while parents[cur] is not None and parents[cur] >= 0:
                links.append((int(parents[cur]), cur))
                cur = int(parents[cur])
                if len(links) > len(parents):
                    raise ValueError("parents have a cycle")
            paths.append(tuple(reversed(links)))
        return cls(np.asarray(rot, np.float64), np.asarray(pos, np.float64), tuple(paths), float(prior_deg))

    @property
    def segments(self) -> tuple[int, ...]:
        """The segments whose misalignment is solved (every ``a`` of a link), sorted."""
        return tuple(sorted({a for path in self.paths for a, _ in path}))


class _Design:
    """Parameters of the position solve: each tracker's mount ``m_k`` (first ``3K``) and, with a
    :class:`SuitChain`, each chain segment's misalignment ``eps_a`` (rad), with their priors and
    each tracker's design ``J_k(t)`` (:func:`_solve_translation`)."""

    def __init__(self, K, m0, m_prec, chain: SuitChain | None, rows: np.ndarray, obs_per_sample: float,
                 eps0: dict | None = None):  # fmt: skip
        """``m_prec``: the mounts' prior precision (1/m^2, per-sample units), one for all or one per
        tracker ``(K,)``; ``eps0``: chain segment -> prior mean of its misalignment (rad; default 0)."""
        self.K = K
        segs = chain.segments if chain is not None else ()
        self.segments = segs
        P = 3 * K + 3 * len(segs)
        self.prior_mean = np.zeros(P)
        self.prior_mean[: 3 * K] = np.asarray(m0, np.float64).ravel()
        self.prior_prec = np.zeros(P)
        self.prior_prec[: 3 * K] = np.repeat(np.broadcast_to(np.asarray(m_prec, np.float64), (K,)), 3)
        for i, a in enumerate(segs):
            if eps0 and a in eps0:
                self.prior_mean[3 * K + 3 * i: 3 * K + 3 * i + 3] = eps0[a]
        self.links: dict[tuple[int, int], np.ndarray] = {}
        self.paths: list[list[tuple[tuple[int, int], int]]] = [[] for _ in range(K)]
        if chain is None:
            return
        T = rows.shape[0]
        if chain.rot.shape[:1] != (T,) or chain.pos.shape[:1] != (T,) or chain.rot.shape[-1] != 4 \
                or chain.pos.shape[-1] != 3 or chain.rot.shape[1] != chain.pos.shape[1]:  # fmt: skip
            raise ValueError(f"chain rot/pos must have shapes (T={T}, S, 4) and (T, S, 3), got {chain.rot.shape} "
                             f"and {chain.pos.shape}")  # fmt: skip
        if len(chain.paths) != K:
            raise ValueError(f"chain has paths for {len(chain.paths)} trackers, not {K}")
        if not (chain.prior_deg > 0 and math.isfinite(chain.prior_deg)):
            raise ValueError(f"chain prior_deg must be positive and finite, got {chain.prior_deg}")
        self.prior_prec[3 * K:] = 1.0 / (math.radians(chain.prior_deg) ** 2 * obs_per_sample)
        S = chain.rot.shape[1]
        used = sorted({x for path in chain.paths for link in path for x in link})
        ok = rows[:, None] & np.ones((1, S), bool)
        ok[:, [x for x in range(S) if x not in used]] = False
        if not np.all(np.isfinite(chain.pos[ok])):
            raise ValueError("chain pos has non-finite values at used samples")
        Ra = _matrices("chain rot", chain.rot, ok)
        index = {a: i for i, a in enumerate(segs)}
        for k, path in enumerate(chain.paths):
            for a, nxt in path:
                if (a, nxt) not in self.links:
                    dp = np.where(rows[:, None], chain.pos[:, nxt] - chain.pos[:, a], 0.0)
                    self.links[(a, nxt)] = _skew(dp) @ Ra[:, a]  # suit world; Y(t) is applied per heading
                self.paths[k].append(((a, nxt), index[a]))

    def blocks(self, G: np.ndarray, Yt: np.ndarray) -> list:
        """Per tracker ``(cols, J (T, 3, P_k))`` for ``G = Y R_seg (T, K, 3, 3)``, heading ``Yt (T, 3, 3)``."""
        turned = {link: Yt @ U for link, U in self.links.items()}
        out = []
        for k in range(self.K):
            cols = [np.arange(3 * k, 3 * k + 3)]
            mats = [G[:, k]]
            for link, i in self.paths[k]:
                cols.append(np.arange(3 * self.K + 3 * i, 3 * self.K + 3 * i + 3))
                mats.append(turned[link])
            out.append((np.concatenate(cols), np.concatenate(mats, axis=-1)))
        return out

    def solve(self, knots, j, u, G, Yt, y, w, rate):
        """``(m (K, 3), eps (A, 3), d_knots, cov (P, P), e (T, K, 3))``: the solve and its residuals."""
        blocks = self.blocks(G, Yt)
        theta, d_knots, cov = _solve_translation(knots, j, u, blocks, y, w, rate, self.prior_mean, self.prior_prec)
        d_t = _at_knots(d_knots, j, u)
        e = y - d_t[:, None] - np.stack([Jk @ theta[cols] for cols, Jk in blocks], axis=1)
        return theta[: 3 * self.K].reshape(self.K, 3), theta[3 * self.K:].reshape(-1, 3), d_knots, cov, e

    def prior_cost(self, m, eps) -> float:
        """Sum of the squared prior residuals over their variances (per-sample units)."""
        theta = np.concatenate([np.ravel(m), np.ravel(eps)])
        return float(np.sum(self.prior_prec * (theta - self.prior_mean) ** 2))

    def mount_covariances(self, cov) -> np.ndarray:
        return np.stack([cov[3 * k: 3 * k + 3, 3 * k: 3 * k + 3] for k in range(self.K)])

    def common_std_m(self, G, Yt, cov, inl) -> float:
        """``sqrt(tr(A cov A^T))`` (m): the spread of the trackers' mean world offset from their
        segments (mount and chain terms, averaged over the inlier samples) under ``cov``, in the
        solve's per-sample units (divide by ``sqrt(obs_per_sample)`` for a 1-sigma)."""
        A = np.zeros((3, self.prior_mean.shape[0]))
        w = inl.astype(np.float64)
        for k, (cols, Jk) in enumerate(self.blocks(G, Yt)):
            if w[:, k].sum() > 0:
                A[:, cols] += np.einsum("t,tap->ap", w[:, k], Jk) / w[:, k].sum() / self.K
        return math.sqrt(max(float(np.trace(A @ cov @ A.T)), 0.0))

    def chain_std_deg(self, cov) -> np.ndarray:
        """Spread (deg, sqrt of the covariance trace) of each chain segment's misalignment under the
        solve's covariance (per-sample units: too small where the prior decides)."""
        o = 3 * self.K
        return np.array([math.degrees(math.sqrt(max(float(np.trace(cov[o + 3 * i: o + 3 * i + 3, o + 3 * i: o + 3 * i + 3])), 0.0)))
                         for i in range(len(self.segments))])  # fmt: skip


def _skew(v: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` cross-product matrices of ``v (..., 3)``."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


# ---------------------------------------------------------------------------------------------
class _Knots:
    """Evenly spaced knots over ``[t0, t1]`` (spacing at most ``spacing``) and the hat-function
    weights of times on them."""

    def __init__(self, t0: float, t1: float, spacing: float):
        span = t1 - t0
        self.n = max(2, math.ceil(span / spacing - 1e-9) + 1)
        self.t = np.linspace(t0, t1, self.n)
        self.step = span / (self.n - 1)
        self.t0 = t0

    def locate(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = (times - self.t0) / self.step
        j = np.clip(np.floor(x).astype(np.int64), 0, self.n - 2)
        u = np.clip(x - j, 0.0, 1.0)
        return j, u

    def normal(self, j, u, w, y=None):
        """Banded normal matrix (diag, off1) of ``sum w (B c - y)^2`` and its right-hand side."""
        n = self.n
        diag = np.bincount(j, w * (1 - u) ** 2, n) + np.bincount(j + 1, w * u * u, n)
        off1 = np.bincount(j, w * u * (1 - u), n)[: n - 1]
        rhs = None
        if y is not None:
            rhs = np.bincount(j, w * (1 - u) * y, n) + np.bincount(j + 1, w * u * y, n)
        return diag, off1, rhs


def _at_knots(values: np.ndarray, j: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Linear interpolation of knot ``values (J, ...)`` at samples located by :meth:`_Knots.locate`
    (knot ``j (T,)``, fraction ``u (T,)``): ``(T, ...)``."""
    u = u.reshape(u.shape + (1,) * (values.ndim - 1))
    return values[j] * (1 - u) + values[j + 1] * u


def _yaw_matrices(psi: np.ndarray) -> np.ndarray:
    c, s = np.cos(psi), np.sin(psi)
    Y = np.zeros(psi.shape + (3, 3))
    Y[..., 0, 0] = c
    Y[..., 0, 2] = s
    Y[..., 1, 1] = 1.0
    Y[..., 2, 0] = -s
    Y[..., 2, 2] = c
    return Y


def _project_so3(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest rotations ``(..., 3, 3)`` to ``A`` (maximising ``tr(R^T A)``) and that maximum."""
    U, S, Vt = np.linalg.svd(A)
    det = np.linalg.det(U @ Vt)
    D = np.ones(A.shape[:-2] + (3,))
    D[..., 2] = np.sign(det)
    D[D == 0] = 1.0
    R = (U * D[..., None, :]) @ Vt
    return R, np.sum(S * D, axis=-1)


def _rot_residual(E: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angle (rad) and rotation vector of rotation matrices ``E (..., 3, 3)`` (accurate near 0)."""
    v = 0.5 * np.stack([E[..., 2, 1] - E[..., 1, 2], E[..., 0, 2] - E[..., 2, 0], E[..., 1, 0] - E[..., 0, 1]], -1)
    sin = np.linalg.norm(v, axis=-1)
    cos = 0.5 * (np.trace(E, axis1=-2, axis2=-1) - 1.0)
    ang = np.arctan2(sin, cos)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(sin > 1e-12, ang / sin, 1.0)
    return ang, v * scale[..., None]


def _matrices(name: str, q: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(T, K, 3, 3)`` rotation matrices of quaternions ``(T, K, 4)``; identity where not valid."""
    qv = q[valid]
    norm = np.linalg.norm(qv, axis=-1)
    if not np.all(np.isfinite(qv)) or np.any(norm < 1e-9):
        raise ValueError(f"{name} has non-finite or zero-norm quaternions at valid samples")
    out = np.broadcast_to(np.eye(3), q.shape[:-1] + (3, 3)).copy()
    out[valid] = Rotation.from_quat(qv).as_matrix()
    return out


def _flag(residual: np.ndarray, pool: np.ndarray, floor: float) -> np.ndarray:
    """Per tracker: samples of ``pool`` whose ``residual`` exceeds max(6 x median, floor)."""
    out = np.zeros_like(pool)
    for k in range(pool.shape[1]):
        r = residual[pool[:, k], k]
        if r.size == 0:
            continue
        thr = max(_OUTLIER_FACTOR * float(np.median(r)), floor)
        out[:, k] = pool[:, k] & (residual[:, k] > thr)
    return out


def _mean_cov(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Covariance ``(D, D)`` of the mean of samples ``v (n, D)`` at times ``t (n,)``: the white
    estimate, inflated when ~1-s block means scatter more than white noise would."""
    n = v.shape[0]
    if n < 2:
        return np.full((v.shape[1], v.shape[1]), np.nan)
    white = np.atleast_2d(np.cov(v, rowvar=False)) / n
    blk = np.floor((t - t[0]) / _BLOCK_S).astype(np.int64)
    nb = int(blk.max()) + 1
    counts = np.bincount(blk, minlength=nb)
    ok = counts > 0
    if ok.sum() >= 8:
        means = np.stack([np.bincount(blk, v[:, d], nb)[ok] / counts[ok] for d in range(v.shape[1])], -1)
        cnt = counts[ok].astype(np.float64)
        dev = means - np.average(means, axis=0, weights=cnt)
        cov_blocks = (dev * cnt[:, None]).T @ dev / n / (ok.sum() - 1)
        tr_w, tr_b = np.trace(white), np.trace(cov_blocks)
        if tr_w > 0 and tr_b > tr_w:
            white = white * (tr_b / tr_w)
    return white


def _init_heading(Rs: np.ndarray, Rt: np.ndarray, w: np.ndarray) -> float:
    """Constant heading maximising the summed chordal agreement with every tracker's best mount:
    ``sum_k max_M tr(M^T sum_t (Y R_seg)^T R_tr)``, on a 0.5-degree grid."""
    Cm = np.diag([1.0, 0.0, 1.0])
    Sm = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    Em = np.diag([0.0, 1.0, 0.0])
    # Y(psi)^T = cos(psi) Cm + sin(psi) Sm + Em
    parts = [np.einsum("tk,tkji,jl,tklm->kim", w, Rs, P, Rt, optimize=True) for P in (Cm, Sm, Em)]
    psi = np.linspace(-math.pi, math.pi, 720, endpoint=False)
    A = (np.cos(psi)[:, None, None, None] * parts[0] + np.sin(psi)[:, None, None, None] * parts[1]
         + parts[2][None])  # fmt: skip
    _, score = _project_so3(A)
    return float(psi[int(np.argmax(score.sum(axis=1)))])


def _fit_heading(knots: _Knots, j, u, Q: np.ndarray, w: np.ndarray, psi_now: np.ndarray) -> np.ndarray:
    """Piecewise-linear heading (knot values, rad) from ``Q (T, K, 3, 3) ≈ Y(psi)`` per sample:
    each sample's best yaw ``atan2(Q02 - Q20, Q00 + Q22)``, unwrapped next to ``psi_now (T,)``,
    weighted least squares with a tiny second-difference regulariser."""
    a = Q[..., 0, 0] + Q[..., 2, 2]
    b = Q[..., 0, 2] - Q[..., 2, 0]
    yaw = np.arctan2(b, a)
    ww = w * 0.5 * np.hypot(a, b)
    target = psi_now[:, None] + (yaw - psi_now[:, None] + math.pi) % (2 * math.pi) - math.pi
    K = w.shape[1]
    jj, uu = np.repeat(j, K), np.repeat(u, K)
    diag, off1, rhs = knots.normal(jj, uu, ww.ravel(), target.ravel())
    n = knots.n
    off2 = np.zeros(max(n - 2, 0))
    lam = 1e-3 * max(float(diag.sum()) / n, 1e-12)
    if n >= 3:  # second differences: D2^T D2
        d2 = np.zeros(n)
        o1 = np.zeros(n - 1)
        for c, e in ((0, 1.0), (1, -2.0), (2, 1.0)):
            d2[c: n - 2 + c] += e * e
        o1[: n - 2] += -2.0
        o1[1: n - 1] += -2.0
        diag = diag + lam * d2
        off1 = off1 + lam * o1
        off2 = off2 + lam * 1.0
    diag = diag + 1e-9 * lam
    ab = np.zeros((3, n))
    ab[2] = diag
    ab[1, 1:] = off1
    if n >= 3:
        ab[0, 2:] = off2
    return solveh_banded(ab, rhs)


def _check_inputs(times_s, seg_rot, seg_pos, trk_rot, trk_pos, valid):
    t = np.asarray(times_s, dtype=np.float64)
    if t.ndim != 1:
        raise ValueError(f"times_s must be 1-D (T,), got shape {t.shape}")
    T = t.shape[0]
    arrays = {}
    for name, arr, last in (("seg_rot", seg_rot, 4), ("seg_pos", seg_pos, 3), ("trk_rot", trk_rot, 4),
                            ("trk_pos", trk_pos, 3)):  # fmt: skip
        a = np.asarray(arr, dtype=np.float64)
        if a.ndim != 3 or a.shape[0] != T or a.shape[2] != last:
            raise ValueError(f"{name} must have shape (T={T}, K, {last}), got {a.shape}")
        arrays[name] = a
    K = arrays["seg_rot"].shape[1]
    if K == 0:
        raise ValueError("need at least one tracker (K = 0)")
    for name, a in arrays.items():
        if a.shape[1] != K:
            raise ValueError(f"{name} has {a.shape[1]} trackers, seg_rot has {K}")
    v = np.asarray(valid)
    if v.dtype != bool or v.shape != (T, K):
        raise ValueError(f"valid must be a bool array of shape ({T}, {K}), got {v.dtype} {v.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("times_s has non-finite values")
    if T >= 2 and np.any(np.diff(t) <= 0):
        raise ValueError("times_s must increase strictly")
    for name in ("seg_pos", "trk_pos"):
        if not np.all(np.isfinite(arrays[name][v])):
            raise ValueError(f"{name} has non-finite values at valid samples")
    return t, arrays["seg_rot"], arrays["seg_pos"], arrays["trk_rot"], arrays["trk_pos"], v


def calibrate_mounts(times_s, seg_rot, seg_pos, trk_rot, trk_pos, valid, knot_spacing_s: float = 1.0,
                     drift_knot_spacing_s: float = 0.1, drift_rate_m_per_sqrt_s: float = 0.05 / math.sqrt(60.0),
                     rounds: int = 4, sites=None, site_prior_m: float = SITE_PRIOR_M,
                     chain: SuitChain | None = None, carried: CarriedMounts | None = None) -> MountCalibration:  # fmt: skip
    """Estimate tracker mounts, the suit's heading and its position drift (model in the module
    docstring).

    Inputs, ``T`` samples on one timeline, ``K`` trackers (tracker ``k`` on segment ``k``):
    ``times_s (T,)`` s, strictly increasing; ``seg_rot (T, K, 4)`` xyzw segment -> suit world and
    ``seg_pos (T, K, 3)`` segment origins (suit world, m); ``trk_rot (T, K, 4)`` xyzw and
    ``trk_pos (T, K, 3)`` m tracker poses in the tracker world; ``valid (T, K)`` bool (suit and
    tracker sample both usable). Values at invalid samples are ignored (may be NaN).

    Method: the heading starts from the best constant (grid search over the summed chordal fit);
    then ``rounds`` times (a) ``M_k`` = chordal mean of ``(Y R_seg)^-1 R_tr`` and (b) ``psi`` =
    piecewise-linear fit (knots every ``knot_spacing_s``) of the yaw of ``R_tr M_k^-1 R_seg^-1``,
    with rotation outliers rejected; then ``m_k`` and ``d`` (knots every ``drift_knot_spacing_s``,
    random-walk prior of ``drift_rate_m_per_sqrt_s`` per axis, the MAP for a drifting position) by
    sparse linear least squares with Huber reweighting, rejecting position outliers; the whole is
    repeated once if new outliers appeared. Samples at exactly the origin with ``valid`` True
    (trackers that lost tracking) are outliers from the start. A weak prior (``m ~ N(0, 1 m^2)``)
    keeps a segment that hardly rotates solvable, with a large ``translation_std_m``.

    ``sites (K, 3)`` (m, segment frame; optional): where each tracker is strapped on its segment
    (the capture protocol's site, e.g. :data:`~dualhuman_builder.rig.TRACKER_SITES`). Orientations
    alone cannot tell the heading from a yaw shared by all mounts while the segments do not turn
    (an actor standing still): then the tracker constellation decides. With sites, ``m_k ~ N(site_k, site_prior_m^2)``
    per axis, and a constant heading offset is searched (a 2-degree grid over +-20 degrees, then a
    parabola) minimising the negative log-likelihood of the orientation and position residuals
    plus that prior, with the mounts and drift re-solved at each offset; residuals are counted
    as one independent observation per ~1 s (they are correlated over that time), so a
    well-turning actor is decided by its data and a still one by its constellation. The offset's
    1-sigma (from the parabola's curvature) is ``heading_std_deg``, added in quadrature to every
    ``rotation_std_deg``.

    ``chain`` (:class:`SuitChain`, optional): the suit's segments from its root to each tracker's;
    each one's constant misalignment ``eps`` (prior ``N(0, chain.prior_deg^2)`` per axis) is solved
    with the mounts and the drift, so that a limb the suit places with misaligned orientations
    does not end up in the offsets (the ``chain_*`` fields of the result).

    ``carried`` (:class:`CarriedMounts`, optional): mounts solved on a calibration take of the same
    session. A carried tracker keeps its mounting rotation; the heading is fitted to the carried
    trackers' orientations alone (no constellation search: the carried rotations fix it, to
    ``heading_std_deg`` = their spread over sqrt(count)); its translation's prior is centred on the
    carried one with the calibration's uncertainty (per axis ``translation_std_m / sqrt(3)``, at
    least :data:`CARRIED_FLOOR_M`) instead of the site's; the chain's misalignment priors are
    centred on the calibration's. A carried tracker whose rotation residuals have a median above
    :data:`MOVED_DEG` was strapped again since: it is solved afresh and flagged in
    ``carry_rejected`` (one at a time, the worst first, since one moved tracker tilts the heading
    the others see). Trackers not carried are solved as without it, with the heading the carried
    ones give.

    Returns a :class:`MountCalibration`. A tracker with fewer than 10 usable samples gets NaN
    entries and ``calibrated[k] = False``. Raises ``ValueError`` on malformed input (shapes, NaN
    at valid samples, non-increasing times) or if fewer than 2 s of valid data remain.
    """
    t, q_seg, p_seg, q_trk, p_trk, valid = _check_inputs(times_s, seg_rot, seg_pos, trk_rot, trk_pos, valid)
    for name, val in (("knot_spacing_s", knot_spacing_s), ("drift_knot_spacing_s", drift_knot_spacing_s),
                      ("drift_rate_m_per_sqrt_s", drift_rate_m_per_sqrt_s)):  # fmt: skip
        if not (val > 0 and math.isfinite(val)):
            raise ValueError(f"{name} must be positive and finite, got {val}")
    T, K = valid.shape
    frames = np.flatnonzero(valid.any(axis=1))
    dt = float(np.median(np.diff(t))) if T >= 2 else 0.0
    duration = frames.size * dt
    if T < 2 or duration < _MIN_DURATION_S:
        raise ValueError(f"only {duration:.2f} s of valid data; need at least {_MIN_DURATION_S} s to calibrate mounts")

    Rs = _matrices("seg_rot", q_seg, valid)
    Rt = _matrices("trk_rot", q_trk, valid)
    origin = valid & np.all(p_trk == 0.0, axis=-1)
    use = valid & ~origin
    if use.sum() < _MIN_SAMPLES:
        raise ValueError("no tracker has usable samples (all invalid or at the origin)")

    hk = _Knots(float(t[0]), float(t[-1]), knot_spacing_s)
    hj, hu = hk.locate(t)
    dk = _Knots(float(t[0]), float(t[-1]), drift_knot_spacing_s)
    dj, du = dk.locate(t)

    obs_per_sample = min(1.0, dt / _BLOCK_S) if dt > 0 else 1.0  # ~one independent observation per second
    if sites is None:
        m0, m_prec = np.zeros((K, 3)), 1.0 / _MOUNT_PRIOR_M**2
    else:
        m0 = np.asarray(sites, dtype=np.float64)
        if m0.shape != (K, 3) or not np.all(np.isfinite(m0)):
            raise ValueError(f"sites must be finite with shape ({K}, 3), got {m0.shape}")
        if not (site_prior_m > 0 and math.isfinite(site_prior_m)):
            raise ValueError(f"site_prior_m must be positive and finite, got {site_prior_m}")
        m_prec = 1.0 / (site_prior_m**2 * obs_per_sample)
    fixed = np.zeros(K, bool)
    M_carried = np.broadcast_to(np.eye(3), (K, 3, 3)).copy()
    if carried is not None:
        carried.check(K)
        fixed = carried.carried.copy()
        M_carried[fixed] = Rotation.from_quat(carried.rotations[fixed]).as_matrix()
    offered = fixed.copy()
    rejected = np.zeros(K, bool)
    while True:  # once, or again after a carried tracker is found strapped again
        psi_knots, rot_out, M, moved = _rotation_rounds(Rs, Rt, use, np.zeros_like(valid), hk, hj, hu, rounds, fixed,
                                                        M_carried)  # fmt: skip
        if moved is None:
            break
        fixed[moved] = False
        rejected[moved] = True
    m_prec = np.broadcast_to(np.asarray(m_prec, np.float64), (K,)).copy()
    m0 = np.broadcast_to(m0, (K, 3)).copy()
    if fixed.any():
        m0[fixed] = carried.translations[fixed]
        std = np.maximum(np.nan_to_num(carried.translation_std_m[fixed], nan=0.0) / math.sqrt(3.0), CARRIED_FLOOR_M)
        m_prec[fixed] = 1.0 / (std**2 * obs_per_sample)
    design = _Design(K, m0, m_prec, chain, valid.any(axis=1), obs_per_sample,
                     eps0=carried.chain if carried is not None and fixed.any() else None)  # fmt: skip
    trans_out = np.zeros_like(valid)
    m = np.zeros((K, 3))
    eps = np.zeros((len(design.segments), 3))
    d_knots = np.zeros((dk.n, 3))
    cov_m = np.full((K, 3, 3), np.nan)
    for outer in range(2):
        if outer:
            psi_knots, rot_out, M, _ = _rotation_rounds(Rs, Rt, use, trans_out, hk, hj, hu, rounds, fixed, M_carried,
                                                        psi_knots, rot_out)  # fmt: skip
        psi = _at_knots(psi_knots, hj, hu)
        G = _yaw_matrices(psi)[:, None] @ Rs

        # translations: y = p_tr - Y p_seg = d(t) + G m_k
        Yt = _yaw_matrices(psi)
        y = np.where(valid[..., None], p_trk - np.einsum("tij,tkj->tki", Yt, np.where(valid[..., None], p_seg, 0.0)),
                     0.0)  # fmt: skip
        sigma = np.full(K, 0.01)
        huber = np.ones((T, K))
        prev_trans = trans_out.copy()
        for _ in range(4):
            inl = use & ~rot_out & ~trans_out
            w = inl * huber / sigma[None] ** 2
            m, eps, d_knots, cov, e = design.solve(dk, dj, du, G, Yt, y, w, drift_rate_m_per_sqrt_s)
            cov_m = design.mount_covariances(cov)
            d_t = _at_knots(d_knots, dj, du)
            en = np.linalg.norm(e, axis=-1)
            trans_out = _flag(en, use & ~rot_out, _TRANS_FLOOR_M)
            inl = use & ~rot_out & ~trans_out
            for k in range(K):
                ek = e[inl[:, k], k]
                if ek.shape[0] >= _MIN_SAMPLES:
                    sigma[k] = max(1.4826 * float(np.median(np.abs(ek))), 1e-4)
                    c = 3.0 * float(np.median(en[inl[:, k], k]))
                    huber[:, k] = np.minimum(1.0, c / np.maximum(en[:, k], 1e-12))
        if np.array_equal(trans_out, prev_trans) or outer == 1:
            break

    inl = use & ~rot_out & ~trans_out
    heading_std = 0.0
    offset = 0.0
    if fixed.any():
        heading_std = math.sqrt(float(np.nanmean(carried.rotation_std_deg[fixed] ** 2)) / int(fixed.sum()))
    elif sites is not None:
        problem = _HeadingProblem(Rs, Rt, p_seg, p_trk, valid, inl, huber / sigma[None] ** 2, dk, dj, du,
                                  drift_rate_m_per_sqrt_s, design, obs_per_sample)  # fmt: skip
        offset, heading_std = problem.search(psi)
        psi_knots = psi_knots + offset
        psi = psi + offset
        G, M, m, eps, d_knots, cov, e, en = problem.solve(psi)
        cov_m = design.mount_covariances(cov)
        d_t = _at_knots(d_knots, dj, du)
    counts = inl.sum(axis=0)
    calibrated = counts >= _MIN_SAMPLES
    ang, rv = _rot_residual(np.swapaxes(G @ M[None], -1, -2) @ Rt)
    rot_rms = np.full(K, np.nan)
    rot_std = np.full(K, np.nan)
    tr_rms = np.full(K, np.nan)
    tr_std = np.full(K, np.nan)
    for k in np.flatnonzero(calibrated):
        sel = inl[:, k]
        rot_rms[k] = math.degrees(math.sqrt(float(np.mean(ang[sel, k] ** 2))))
        rot_std[k] = math.hypot(math.degrees(math.sqrt(max(float(np.trace(_mean_cov(rv[sel, k], t[sel]))), 0.0))),
                                heading_std)  # fmt: skip
        if fixed[k]:
            rot_std[k] = float(carried.rotation_std_deg[k])
        tr_rms[k] = math.sqrt(float(np.mean(en[sel, k] ** 2)))
        ek = e[sel, k]
        white = np.atleast_2d(np.cov(ek, rowvar=False)) / ek.shape[0]
        infl = float(np.trace(_mean_cov(ek, t[sel])) / np.trace(white)) if np.trace(white) > 0 else 1.0
        tr_std[k] = math.sqrt(max(float(np.trace(cov_m[k])), 0.0) * max(infl, 1.0))
    rotations = Rotation.from_matrix(M).as_quat()
    if fixed.any():
        rotations[fixed] = carried.rotations[fixed]  # as carried, to the bit
    translations = m.copy()
    rotations[~calibrated] = np.nan
    translations[~calibrated] = np.nan
    return MountCalibration(
        rotations=rotations, translations=translations, heading_rad=psi.copy(), drift=d_t.copy(),
        rotation_rms_deg=rot_rms, translation_rms_m=tr_rms, rotation_std_deg=rot_std, translation_std_m=tr_std,
        outliers=valid & ~inl, calibrated=calibrated, heading_knots_s=hk.t.copy(), heading_knots_rad=psi_knots.copy(),
        drift_knots_s=dk.t.copy(), drift_knots_m=d_knots.copy(),
        heading_offset_deg=np.asarray(math.degrees(offset)), heading_std_deg=np.asarray(heading_std),
        chain_segments=np.asarray(design.segments, np.int64), chain_misalignment_rad=eps.copy(),
        chain_std_deg=design.chain_std_deg(cov),
        common_offset_std_m=np.asarray(design.common_std_m(G, _yaw_matrices(psi), cov, inl) / math.sqrt(obs_per_sample)),
        carried=fixed & calibrated, carry_rejected=rejected & offered,
    )  # fmt: skip


def _rotation_rounds(Rs, Rt, use, trans_out, hk: _Knots, hj, hu, rounds: int, fixed: np.ndarray, M_fixed,
                     psi_knots: np.ndarray | None = None, rot_out: np.ndarray | None = None):  # fmt: skip
    """The rotation part of :func:`calibrate_mounts`: ``rounds`` times the mounts ``M (K, 3, 3)``
    by the closed form (the ``fixed (K,)`` ones kept at ``M_fixed``) and the heading knots fitted to
    the trackers' orientations (to the fixed ones' alone when there are any), rejecting rotation
    outliers among ``use & ~trans_out``. Starts from ``psi_knots`` (default: the best constant)
    and the rotation outliers ``rot_out`` (default: none).
    Returns ``(psi_knots, rot_out (T, K), M, moved)``: ``moved`` the fixed tracker whose median
    residual angle is the largest above :data:`MOVED_DEG`, or None."""
    K = use.shape[1]
    anchor = fixed if fixed.any() else np.ones(K, bool)
    if psi_knots is None:
        if fixed.any():
            Q = Rt @ np.swapaxes(M_fixed, -1, -2)[None] @ np.swapaxes(Rs, -1, -2)
            w = (use & fixed[None]).astype(np.float64)
            yaw0 = math.atan2(float(np.sum(w * (Q[..., 0, 2] - Q[..., 2, 0]))), float(np.sum(w * (Q[..., 0, 0] + Q[..., 2, 2]))))
        else:
            yaw0 = _init_heading(Rs, Rt, use.astype(np.float64))
        psi_knots = np.full(hk.n, yaw0)
    rot_out = np.zeros_like(use) if rot_out is None else rot_out
    inl = use & ~rot_out & ~trans_out
    for _ in range(max(1, int(rounds))):
        psi = _at_knots(psi_knots, hj, hu)
        G = _yaw_matrices(psi)[:, None] @ Rs  # Y R_seg (T, K, 3, 3)
        M, _ = _project_so3(np.einsum("tk,tkji,tkjl->kil", inl.astype(np.float64), G, Rt, optimize=True))
        if fixed.any():
            M[fixed] = M_fixed[fixed]
        Q = Rt @ np.swapaxes(M, -1, -2)[None] @ np.swapaxes(Rs, -1, -2)
        psi_knots = _fit_heading(hk, hj, hu, Q, (inl & anchor[None]).astype(np.float64), psi)
        psi = _at_knots(psi_knots, hj, hu)
        G = _yaw_matrices(psi)[:, None] @ Rs
        ang, _ = _rot_residual(np.swapaxes(G @ M[None], -1, -2) @ Rt)
        rot_out = _flag(ang, use & ~trans_out, _ROT_FLOOR_RAD)
        inl = use & ~rot_out & ~trans_out
    M, _ = _project_so3(np.einsum("tk,tkji,tkjl->kil", inl.astype(np.float64), G, Rt, optimize=True))
    moved = None
    if fixed.any():
        M[fixed] = M_fixed[fixed]
        ang, _ = _rot_residual(np.swapaxes(G @ M[None], -1, -2) @ Rt)
        med = np.array([float(np.median(ang[use[:, k], k])) if fixed[k] and use[:, k].any() else 0.0 for k in range(K)])
        if med.max() > math.radians(MOVED_DEG):
            moved = int(np.argmax(med))
    return psi_knots, rot_out, M, moved


class _HeadingProblem:
    """The mounts and drift re-solved for a given heading trajectory, and the negative
    log-likelihood of the result, for :func:`calibrate_mounts`' heading-offset search. Inlier set
    and per-sample position weights (``w_pos (T, K)``, 1/m^2) are those of the main solve; each
    sample counts ``obs_per_sample`` of an independent observation."""

    def __init__(self, Rs, Rt, p_seg, p_trk, valid, inl, w_pos, dk, dj, du, rate, design: _Design, obs_per_sample):
        self.Rs, self.Rt, self.inl, self.dk, self.dj, self.du = Rs, Rt, inl, dk, dj, du
        self.p_seg = np.where(valid[..., None], p_seg, 0.0)
        self.p_trk = np.where(valid[..., None], p_trk, 0.0)
        self.w_pos = np.where(inl, w_pos, 0.0)
        self.rate, self.design, self.scale = rate, design, obs_per_sample
        self.inl_f = inl.astype(np.float64)
        self.sig_rot: np.ndarray | None = None  # per tracker, rad: set by search()

    def solve(self, psi):
        """``(G, M, m, eps, d_knots, cov, e, |e|)`` for heading ``psi (T,)``: ``G = Y R_seg``, mounts
        by the closed form and the translation solve (with the chain's misalignments ``eps`` and the
        covariance ``cov`` of all its parameters), position residuals ``e (T, K, 3)``."""
        Yt = _yaw_matrices(psi)
        G = Yt[:, None] @ self.Rs
        M, _ = _project_so3(np.einsum("tk,tkji,tkjl->kil", self.inl_f, G, self.Rt, optimize=True))
        y = self.p_trk - np.einsum("tij,tkj->tki", Yt, self.p_seg)
        m, eps, d_knots, cov, e = self.design.solve(self.dk, self.dj, self.du, G, Yt, y, self.w_pos, self.rate)
        return G, M, m, eps, d_knots, cov, e, np.linalg.norm(e, axis=-1)

    def _orientation_residuals(self, psi):
        """``(solve(psi), angles (T, K) rad, rotation vectors (T, K, 3) rad)``: the re-solved mounts
        and each sample's rotation residual."""
        solved = self.solve(psi)
        G, M = solved[0], solved[1]
        return (solved, *_rot_residual(np.swapaxes(G @ M[None], -1, -2) @ self.Rt))

    def nll(self, psi) -> float:
        """Negative log-likelihood (up to a constant) at heading ``psi``: orientation residuals
        (over each tracker's robust per-axis scale ``sig_rot``, set by :meth:`search`), position residuals,
        drift random walk, mount-site prior."""
        (G, M, m, eps, d_knots, _, _, en), ang, _ = self._orientation_residuals(psi)
        rot = float(np.sum(self.inl_f * (ang / self.sig_rot[None]) ** 2))
        pos = float(np.sum(self.w_pos * en**2))
        walk = float(np.sum(np.diff(d_knots, axis=0) ** 2)) / (self.rate**2 * self.dk.step)
        prior = self.design.prior_cost(m, eps)
        return 0.5 * self.scale * (rot + pos + walk + prior)  # scale * m_prec = 1 / site_prior_m^2

    def search(self, psi) -> tuple[float, float]:
        """``(offset rad, 1-sigma deg)``: the constant heading offset minimising :meth:`nll`. Each
        tracker's orientation scale is measured once, at ``psi`` (the heading the orientations
        chose): measured at an offset heading it would swell and mute the orientations. It is a
        per-axis sigma (1.4826 x the median absolute component of the residual rotation vectors), as
        the positions' is: :meth:`nll` sums squared 3-D residuals over it. (1.4826 x the median
        *angle* would be 2.28 sigma, the angle of a 3-D normal residual having its median at 1.54
        sigma, and would weigh the orientations 5.2x too little against the constellation.)"""
        self.sig_rot = _axis_sigma(self._orientation_residuals(psi)[2], self.inl)
        step, fine = math.radians(_SCAN_STEP_DEG), math.radians(_SCAN_FINE_DEG)
        grid = np.arange(-_SCAN_RANGE_DEG, _SCAN_RANGE_DEG + 1e-9, _SCAN_STEP_DEG)
        costs = np.array([self.nll(psi + math.radians(g)) for g in grid])
        best = math.radians(float(grid[int(np.argmin(costs))]))
        x = best + np.array([-step, -fine, 0.0, fine, step])
        f = np.array([self.nll(psi + v) for v in x])
        a, b, _ = np.polyfit(x - best, f, 2)
        if a <= 0:  # flat or concave: keep the best point; no curvature, no information
            return float(x[int(np.argmin(f))]), float("inf")
        off = best + float(np.clip(-b / (2 * a), -step, step))
        return off, math.degrees(1.0 / math.sqrt(2.0 * a))


def _axis_sigma(rv: np.ndarray, inl: np.ndarray) -> np.ndarray:
    """Per tracker, the robust per-axis scale (rad) of residual rotation vectors ``rv (T, K, 3)``
    over its inliers ``inl (T, K)``: 1.4826 x the median absolute component (the normal's sigma
    for a normal residual), at least 1e-4; 1.0 for a tracker without inliers."""
    return np.array([max(1.4826 * float(np.median(np.abs(rv[inl[:, k], k]))), 1e-4) if inl[:, k].any() else 1.0
                     for k in range(rv.shape[1])])  # fmt: skip


def _solve_translation(knots: _Knots, j, u, blocks, y, w, rate, prior_mean: np.ndarray, prior_precision: np.ndarray):
    """Weighted least squares for the dense parameters ``theta (P,)`` and drift knots ``(J, 3)`` in
    ``y_tk ≈ d(t) + J_k(t) theta[cols_k]`` (weights ``w (T, K)`` in 1/m^2), with a random-walk prior on
    the knots (increment std ``rate * sqrt(step)``) and ``theta ~ N(prior_mean, 1 / prior_precision)``
    (both ``(P,)``; precisions in 1/unit^2). ``blocks``: per tracker ``k`` a pair ``(cols_k (P_k,)
    int, J_k (T, 3, P_k))``: which parameters its position depends on, and how (its mount ``m_k``
    through ``G_tk``, and the suit's segment misalignments on its chain). Returns ``theta``, the
    knots and the covariance ``(P, P)`` of ``theta``. The drift block is banded (same for each
    axis); ``theta`` comes from its Schur complement."""
    T, K = w.shape
    n = knots.n
    P = prior_mean.shape[0]
    jj, uu = np.repeat(j, K), np.repeat(u, K)
    diag, off1, _ = knots.normal(jj, uu, w.ravel())
    prior = 1.0 / (rate * rate * knots.step)
    diag = diag.copy()
    diag[:-1] += prior
    diag[1:] += prior
    off1 = off1 - prior
    diag += 1e-12 * max(float(diag.max()), 1.0)
    ab = np.zeros((2, n))
    ab[1] = diag
    ab[0, 1:] = off1
    # B (n, T): hat-function weights of the samples on the knots
    rows = np.concatenate([j, j + 1])
    B = sparse.csr_matrix((np.concatenate([1 - u, u]), (rows, np.concatenate([np.arange(T)] * 2))), shape=(n, T))
    Ndm = np.zeros((3, n, P))  # Ndm[a][knot, p] = sum w B_knot J[a, p]
    bd = B @ np.einsum("tk,tka->ta", w, y)  # (n, 3)
    S = np.diag(np.asarray(prior_precision, np.float64).copy())
    rhs = prior_precision * prior_mean
    for k, (cols, Jk) in enumerate(blocks):
        wJ = w[:, k, None, None] * Jk  # (T, 3, P_k)
        for a in range(3):
            Ndm[a][:, cols] += B @ wJ[:, a]
        S[np.ix_(cols, cols)] += np.einsum("tai,taj->ij", wJ, Jk, optimize=True)
        rhs[cols] += np.einsum("tai,ta->i", wJ, y[:, k], optimize=True)
    X = np.empty_like(Ndm)
    z = np.empty((3, n))
    for a in range(3):
        sol = solveh_banded(ab, np.column_stack([Ndm[a], bd[:, a]]))
        X[a], z[a] = sol[:, :-1], sol[:, -1]
        S -= Ndm[a].T @ X[a]
        rhs -= Ndm[a].T @ z[a]
    S = 0.5 * (S + S.T)
    cov = np.linalg.inv(S)
    theta = cov @ rhs
    d_knots = np.stack([z[a] - X[a] @ theta for a in range(3)], -1)
    return theta, d_knots, cov

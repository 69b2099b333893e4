"""The mount calibration's result and its optional inputs.

* :class:`MountCalibration`: what :func:`~.mount.calibrate_mounts` returns (mounts, the suit
  world's heading and drift against the tracker world, fit quality, uncertainties), and the maps
  between suit poses and tracker poses it implies;
* :class:`CarriedMounts`: mounts solved on a calibration take, carried into another take of the
  same studio day (``docs/decisions/0013-calibration-take.md``);
* :class:`SuitChain`: the suit's kinematic chain, so that the suit's segment misalignments are
  solved with the mounts (``docs/decisions/0012-suit-chain-misalignments.md``).

Quaternions are xyzw; positions metres; ``T`` samples, ``K`` trackers. The model and its symbols
(``M_k``, ``m_k``, ``psi``, ``d``, ``eps_a``) are in :mod:`.mount`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass(frozen=True, eq=False)
class MountCalibration:
    """Result of :func:`~.mount.calibrate_mounts` (``T`` samples, ``K`` trackers).

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
        """``K``."""
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
    """Mounts solved on the studio day's calibration take, for :func:`~.mount.calibrate_mounts` on
    another take of the day (``K`` trackers, in that take's order): trackers strapped on once a
    day keep their mounts, and the suit's segment misalignments (its sensor-to-segment
    calibration) hold for the day too.

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
        """ValueError unless these are mounts for ``K`` trackers, finite unit quaternions and
        finite offsets where carried."""
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
    :func:`~.mount.calibrate_mounts` can solve the suit's segment misalignments with the mounts.

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


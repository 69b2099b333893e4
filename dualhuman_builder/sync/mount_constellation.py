"""The suit's heading offset from the tracker constellation
(``docs/decisions/0011-heading-from-tracker-constellation.md``).

Orientations alone cannot tell the suit's heading from a yaw shared by all mounts while the
segments do not turn (an actor standing still). With the trackers' sites on their segments (a
prior on the mount offsets), the positions can: :class:`HeadingProblem` re-solves mounts and drift
for a constant heading offset and scores the result by its negative log-likelihood; its
:meth:`~HeadingProblem.search` scans offsets over +-:data:`SCAN_RANGE_DEG` and refines the best with
a parabola, whose curvature gives the offset's 1-sigma.
"""

from __future__ import annotations

import math

import numpy as np

from dualhuman_builder.sync.mount_rotation import project_so3, rotation_residual, yaw_matrices
from dualhuman_builder.sync.mount_translation import TranslationDesign

#: Heading-offset search: a grid of +-SCAN_RANGE_DEG in SCAN_STEP_DEG steps, then a parabola
#: through the best grid point and its neighbours at +-SCAN_FINE_DEG and +-SCAN_STEP_DEG (deg).
SCAN_RANGE_DEG = 20.0
SCAN_STEP_DEG = 2.0
SCAN_FINE_DEG = 0.5


class HeadingProblem:
    """The mounts and drift re-solved for a given heading trajectory, and the negative
    log-likelihood of the result, for :func:`~.mount.calibrate_mounts`' heading-offset search.
    Inlier set and per-sample position weights (``w_pos (T, K)``, 1/m^2) are those of the main
    solve; each sample counts ``obs_per_sample`` of an independent observation."""

    def __init__(self, Rs, Rt, p_seg, p_trk, valid, inl, w_pos, dk, dj, du, rate, design: TranslationDesign,
                 obs_per_sample):  # fmt: skip
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
        Yt = yaw_matrices(psi)
        G = Yt[:, None] @ self.Rs
        M, _ = project_so3(np.einsum("tk,tkji,tkjl->kil", self.inl_f, G, self.Rt, optimize=True))
        y = self.p_trk - np.einsum("tij,tkj->tki", Yt, self.p_seg)
        m, eps, d_knots, cov, e = self.design.solve(self.dk, self.dj, self.du, G, Yt, y, self.w_pos, self.rate)
        return G, M, m, eps, d_knots, cov, e, np.linalg.norm(e, axis=-1)

    def _orientation_residuals(self, psi):
        """``(solve(psi), angles (T, K) rad, rotation vectors (T, K, 3) rad)``: the re-solved mounts
        and each sample's rotation residual."""
        solved = self.solve(psi)
        G, M = solved[0], solved[1]
        return (solved, *rotation_residual(np.swapaxes(G @ M[None], -1, -2) @ self.Rt))

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
        self.sig_rot = axis_sigma(self._orientation_residuals(psi)[2], self.inl)
        step, fine = math.radians(SCAN_STEP_DEG), math.radians(SCAN_FINE_DEG)
        grid = np.arange(-SCAN_RANGE_DEG, SCAN_RANGE_DEG + 1e-9, SCAN_STEP_DEG)
        costs = np.array([self.nll(psi + math.radians(g)) for g in grid])
        best = math.radians(float(grid[int(np.argmin(costs))]))
        x = best + np.array([-step, -fine, 0.0, fine, step])
        f = np.array([self.nll(psi + v) for v in x])
        a, b, _ = np.polyfit(x - best, f, 2)
        if a <= 0:  # flat or concave: keep the best point; no curvature, no information
            return float(x[int(np.argmin(f))]), float("inf")
        off = best + float(np.clip(-b / (2 * a), -step, step))
        return off, math.degrees(1.0 / math.sqrt(2.0 * a))


def axis_sigma(rv: np.ndarray, inl: np.ndarray) -> np.ndarray:
    """Per tracker, the robust per-axis scale (rad) of residual rotation vectors ``rv (T, K, 3)``
    over its inliers ``inl (T, K)``: 1.4826 x the median absolute component (the normal's sigma
    for a normal residual), at least 1e-4; 1.0 for a tracker without inliers."""
    return np.array([max(1.4826 * float(np.median(np.abs(rv[inl[:, k], k]))), 1e-4) if inl[:, k].any() else 1.0
                     for k in range(rv.shape[1])])  # fmt: skip


"""Mount offsets, the suit's position drift and its chain misalignments: the position half of
:func:`~.mount.calibrate_mounts`.

Model (module :mod:`.mount`), with ``G_k(t) = Y(t) R_seg,k(t)`` from the rotation half::

    y_k(t) = p_tr,k(t) - Y(t) p_seg,k(t) = d(t) + G_k(t) m_k  [+ Y(t) sum_a [dp_a]x R_a eps_a]

``m_k`` (m, segment frame) the mount offset of tracker ``k``, ``d(t)`` (m, tracker world) the drift,
piecewise linear on knots with a random-walk prior, ``eps_a`` (rad) the misalignment of each suit
segment on a :class:`~.mount_types.SuitChain`, first order. :class:`TranslationDesign` holds the
dense parameters ``theta = (m_1..m_K, eps_1..eps_A)`` with their Gaussian priors and each tracker's
design; :func:`_solve_translation` solves the weighted least squares with the banded drift block
eliminated by its Schur complement.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import sparse
from scipy.linalg import solveh_banded

from dualhuman_builder.sync.knots import Knots, at_knots
from dualhuman_builder.sync.mount_rotation import quat_matrices
from dualhuman_builder.sync.mount_types import SuitChain


class TranslationDesign:
    """Parameters of the position solve: each tracker's mount ``m_k`` (first ``3K``) and, with a
    :class:`~.mount_types.SuitChain`, each chain segment's misalignment ``eps_a`` (rad), with their priors and
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
        Ra = quat_matrices("chain rot", chain.rot, ok)
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
        d_t = at_knots(d_knots, j, u)
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



def _solve_translation(knots: Knots, j, u, blocks, y, w, rate, prior_mean: np.ndarray, prior_precision: np.ndarray):
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

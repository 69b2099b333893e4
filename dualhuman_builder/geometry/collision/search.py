"""Exact inside/outside and depth of query vertices: banded query, sign flood fill, full queries.

One :class:`BandedSearch` answers one batch of problems (see :mod:`.kernels`) with method
``"warp"``, in three steps:

1. the candidates are queried with ``max_dist = band``: vertices near the obstacle get their exact
   signed distance, cheaply, since a query with a small radius visits a small part of the BVH;
2. the signs of the others (far) come from the sign flood fill (:mod:`.flood`), or from a full query
   each when fewer than ``flood_min`` are open; a flood-fill component whose known members disagree
   (a pseudonormal sign gone wrong where the obstacle crosses itself) gives each open member a full
   query, and a component with no known member gets one for its representative;
3. far vertices found inside get a full query for their depth.

Signs: +1 outside, -1 inside, 0 unknown. Bounds ``lb``: lower bounds of ``|distance|`` (metres), the
exact one near the obstacle, ``band`` or the distance to the obstacle's box farther out. The choice
of ``band`` and ``flood_min``: ``docs/decisions/0010-exact-collision-term.md`` and
``docs/decisions/0020-collision-term-cost.md``; ``benchmarks/bench_collision.py`` measures them on
fixed scenes, ``benchmarks/probes/probe_collision_band.py`` the band on a hug fit's calls.
"""

from __future__ import annotations

import numpy as np

from dualhuman_builder.geometry.collision.flood import CONFLICT, FOLLOWS, REPRESENTATIVE, SignFlood
from dualhuman_builder.geometry.collision.queries import MeshPool


class BandedSearch:
    """The search over problems ``Q (P, V, 3)`` (query vertices) against ``O (P, V, 3)`` (obstacle
    vertices), float32 metres, ``lo``, ``hi`` ``(P, 3)`` the obstacles' boxes. ``lb (P * V,)`` float32
    and ``sgn (P * V,)`` int8 start as the caller's bounds and signs (unknown signs as +1 until step 2),
    ``known (P * V,)`` bool marks the signs known before the search (remembered, :mod:`.memory`).
    The meshes of a problem are refit on its first query of the search."""

    def __init__(self, pool: MeshPool, Q: np.ndarray, O: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                 lb: np.ndarray, sgn: np.ndarray, known: np.ndarray):  # fmt: skip
        self.pool, self.Q, self.O = pool, Q, O
        self.P, self.V = Q.shape[:2]
        self.Qf = Q.reshape(-1, 3)
        self.lb, self.sgn, self.known = lb, sgn, known
        self.queried = np.zeros(self.P * self.V, bool)  # given a full query
        self.big = (np.linalg.norm(hi - lo, axis=1) + 1.0).astype(np.float32)  # > any inside distance
        self._refit = np.zeros(self.P, bool)  # meshes moved to this search's obstacles
        #: every query's answers so far: vertex index, signed distance, face, barycentric weights
        self.found: tuple[list, list, list, list] = ([], [], [], [])

    def _query(self, idx: np.ndarray, max_dist) -> tuple:
        V, P = self.V, self.P
        todo = np.flatnonzero((np.bincount(idx // V, minlength=P) > 0) & ~self._refit)
        self._refit[todo] = True
        ids = self.pool.meshes(self.O, todo)
        return self.pool.query(ids, (idx // V).astype(np.int32), self.Qf[idx], max_dist)

    def _record(self, idx, sd, face, bary) -> None:
        for out, x in zip(self.found, (idx, sd, face, bary)):
            out.append(x)

    def banded(self, flat: np.ndarray, band: float) -> tuple[np.ndarray, np.ndarray]:
        """Step 1 on the vertices ``flat`` (indices into ``P * V``): exact signs and bounds of those
        within ``band``; returns ``(near, far)``, ``near`` a mask over ``flat``, ``far`` the indices of
        the others, whose bound becomes at least ``band`` and whose sign, unless known, unknown."""
        sd, face, bary = self._query(flat, band)
        near = face >= 0
        self.sgn[flat[near]] = np.where(sd[near] < 0, -1, 1)
        self.lb[flat[near]] = np.abs(sd[near])
        far = flat[~near]
        self.lb[far] = np.maximum(self.lb[far], band)
        self.sgn[far[~self.known[far]]] = 0
        self._record(flat[near], sd[near], face[near], bary[near])
        return near, far

    def full(self, idx: np.ndarray) -> None:
        """A query without a radius for the vertices ``idx``: exact sign, bound and closest point."""
        sd, face, bary = self._query(idx, self.big[idx // self.V])
        self._record(idx, sd, face, bary)
        self.sgn[idx] = np.where((face >= 0) & (sd < 0), -1, 1)
        self.lb[idx] = np.where(face >= 0, np.abs(sd), self.lb[idx])
        self.queried[idx] = True

    def fill(self, flood: SignFlood) -> tuple[int, int]:
        """Step 2 for the vertices of unknown sign, by :class:`~.flood.SignFlood`; returns the number
        of representatives and of conflicted vertices given a full query."""
        P, V = self.P, self.V
        rows = np.flatnonzero((self.sgn == 0).reshape(P, V).any(axis=1))  # problems with something to fill
        code = flood(self.Q, self.lb.reshape(P, V), self.sgn.reshape(P, V), rows)
        t, v = np.nonzero(code)
        c, at = code[t, v], rows[t] * V + v
        n_conflict = n_rep = 0
        if (c == CONFLICT).any():  # no sign of such a component can be trusted: a query each
            self.full(at[c == CONFLICT])
            n_conflict = int((c == CONFLICT).sum())
        if (c == REPRESENTATIVE).any():  # a component with no known member: its first vertex decides it
            self.full(at[c == REPRESENTATIVE])
            n_rep = int((c == REPRESENTATIVE).sum())
        follow = c <= FOLLOWS  # the other members of such a component: their representative's sign
        self.sgn[at[follow]] = self.sgn[rows[t[follow]] * V + (FOLLOWS - c[follow])]
        return n_rep, n_conflict

    def result(self, margin: float) -> tuple:
        """``(problem, vertex, depth, face, bary)`` of the vertices found inside (``depth > 0``) or
        outside within ``margin`` (``depth`` minus the distance), in the order they were queried."""
        idx, sd = np.concatenate(self.found[0]), np.concatenate(self.found[1])
        face, bary = np.concatenate(self.found[2]), np.concatenate(self.found[3])
        ins = (face >= 0) & (sd < margin)
        idx = idx[ins]
        return idx // self.V, idx % self.V, -sd[ins], face[ins], bary[ins]


def search_contacts(pool: MeshPool, flood: SignFlood, Q, O, cand, dbox, lo, hi, band: float, flood_min: int,
                    prior=None, margin: float = 0.0) -> tuple:  # fmt: skip
    """The vertices of problems ``Q (P, V, 3)`` inside ``O`` (and those outside within ``margin``,
    metres) by a :class:`BandedSearch` over the candidates ``cand (P, V)`` bool; ``dbox (P, V)`` each
    query vertex's distance to its obstacle's box ``lo``, ``hi`` ``(P, 3)``; ``prior``: signs and
    bounds known to hold (:meth:`~.memory.SignMemory.prior`) or None.

    Returns ``(problem, vertex, depth, face, bary)`` (:meth:`BandedSearch.result`), the signs ``(P,
    V)`` int8 and bounds ``(P, V)`` float32 of every query vertex, and the search's counts."""
    P, V = Q.shape[:2]
    N = P * V
    lb = dbox.ravel().astype(np.float32)
    query = cand.ravel()
    if prior is not None:
        psgn, plb = prior[0].ravel(), prior[1].ravel()
        known = psgn != 0
        sgn = np.where(known, psgn, np.int8(1))
        lb = np.where(known, np.maximum(lb, plb), lb)
        query = query & ((psgn <= 0) | (plb < margin))  # known to be still outside, beyond the margin: done
    else:
        known = np.zeros(N, bool)
        sgn = np.ones(N, np.int8)
    s = BandedSearch(pool, Q, O, lo, hi, lb, sgn, known)
    near, far = s.banded(np.flatnonzero(query), band)
    open_ = far[~known[far]]
    n_rep = n_conflict = 0
    if 0 < len(open_) < flood_min:  # few: a full query each is cheaper than the flood fill
        s.full(open_)
    elif len(open_):
        n_rep, n_conflict = s.fill(flood)
    deep = far[(s.sgn[far] < 0) & ~s.queried[far]]  # step 3: the depth of far vertices inside
    if len(deep):
        s.full(deep)
    stats = {"candidates": int(cand.sum()), "near": int(near.sum()), "far": len(far),
             "representatives": n_rep, "conflicted": n_conflict,
             "full": int(s.queried[far].sum()) - n_rep - n_conflict, "reused": int((known & cand.ravel()).sum())}  # fmt: skip
    return s.result(margin), s.sgn.reshape(P, V), s.lb.reshape(P, V), stats

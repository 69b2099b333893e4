"""The scene generator's banded distance queries between two bodies: the answers of
:class:`~dualhuman_builder.geometry.distance.PairDistance`, bit for bit, at a fraction of its
Python cost.

:class:`FastPair` wraps the process-wide :func:`~dualhuman_builder.geometry.distance.get_pair_distance`
and uses its very meshes (so its BVHs, built on the first frame they are queried on and refit
after, are the ones every other caller shares). What it changes is the broad phase and what is
queried:

- the body-part boxes come from one ``np.minimum.reduceat`` over the vertices sorted by part
  instead of a Python loop over the parts, and a point is tested against the parts' boxes only
  when it lies in the box around all of them, one box at a time, largest first, each taking the
  points it holds out of the test (the same answer: a min/max is exact, a point outside the
  union's box is outside every box, and a point in one box needs no other);
- ``need_a`` / ``need_b`` name the vertices whose distances the caller reads: only those are
  queried, and a mesh is refit only when one of them passes the broad phase. A vertex's answer
  does not depend on which others are queried with it; where a point is equally close to two
  faces, which one's rounding it takes (the last bit) may depend on the frame the BVH was built on.

Distances are metres, float64, NaN beyond the band or not queried, as ``PairDistance`` returns them.
"""

from __future__ import annotations

import functools

import numpy as np


class FastPair:
    """``PairDistance``'s answers for a pair of bodies of anny's topology (see the module docstring)."""

    def __init__(self, pair):
        if pair.groups is None:
            raise ValueError("FastPair needs a PairDistance with body-part regions")
        self.pair = pair
        groups = self.groups = pair.groups
        self.order = np.concatenate(groups)
        self.starts = np.cumsum([0] + [len(g) for g in groups[:-1]])

    def boxes(self, verts: np.ndarray) -> np.ndarray:
        """Per body part, ``(lo, hi)`` of ``verts (V, 3)``: ``(R, 2, 3)``, equal to ``PairDistance._boxes``."""
        v = verts[self.order]
        lo, hi = np.minimum.reduceat(v, self.starts, axis=0), np.maximum.reduceat(v, self.starts, axis=0)
        return np.stack([lo, hi], axis=1)

    def candidates(self, p: np.ndarray, other_boxes: np.ndarray, band: float, only: np.ndarray | None = None,
                   own_boxes: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
        """``PairDistance.candidates`` from the other body's part boxes: the vertices of ``p`` (or
        of ``only``) that may lie within ``band`` of it. The same set (its order may differ)."""
        lo, hi = other_boxes[:, 0] - band, other_boxes[:, 1] + band
        if only is not None:
            q = p[only]
            left = np.flatnonzero(np.all((q >= lo.min(0)) & (q <= hi.max(0)), axis=1))  # in the box around them all
            hit = np.zeros(len(q), dtype=bool)
            for r in np.argsort(-np.prod(hi - lo, axis=1)):  # the largest boxes first: they take most points
                if not len(left):
                    break
                x = q[left]
                m = ((x[:, 0] >= lo[r, 0]) & (x[:, 0] <= hi[r, 0]) & (x[:, 1] >= lo[r, 1]) & (x[:, 1] <= hi[r, 1])
                     & (x[:, 2] >= lo[r, 2]) & (x[:, 2] <= hi[r, 2]))  # fmt: skip
                hit[left[m]] = True
                left = left[~m]
            return only[hit]
        own = self.boxes(p) if own_boxes is None else own_boxes
        g_lo, g_hi = own[:, 0] - band, own[:, 1] + band
        keep = np.any(np.all((other_boxes[None, :, 0] <= g_hi[:, None]) & (other_boxes[None, :, 1] >= g_lo[:, None]),
                             axis=2), axis=1)  # fmt: skip
        kept = [g for g, k in zip(self.groups, keep) if k]
        return np.concatenate(kept) if kept else np.zeros(0, dtype=np.int64)

    def __call__(self, verts_a: np.ndarray, verts_b: np.ndarray, band: float, query_a: np.ndarray | None = None,
                 query_b: np.ndarray | None = None, need_a: np.ndarray | None = None,
                 need_b: np.ndarray | None = None, boxes: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """``(d_a (V,), d_b (V,))`` as ``PairDistance(verts_a, verts_b, band, query_a, query_b)``
        returns them on the vertices of ``need_a`` / ``need_b`` (default: every queried vertex; a
        ``need`` must lie within its query set); NaN on the others. ``boxes``: the two bodies'
        :meth:`boxes`, when the caller has them."""
        boxes = (self.boxes(verts_a), self.boxes(verts_b)) if boxes is None else boxes
        out = []
        sides = ((verts_a, verts_b, query_a, need_a), (verts_b, verts_a, query_b, need_b))
        for i, (p, other, only, need) in enumerate(sides):
            d = np.full(len(p), np.nan)
            if need is None:
                near = self.candidates(p, boxes[1 - i], band, only, boxes[i])
            else:
                near = self.candidates(p, boxes[1 - i], band, np.asarray(need, dtype=np.int64), boxes[i])
            if len(near):
                mesh = self.pair.meshes[1 - i]
                mesh.update(other)
                d[near] = mesh.query(p[near], band)
            out.append(d)
        return out[0], out[1]


@functools.lru_cache(maxsize=2)
def get_fast_pair(device: str = "cpu") -> FastPair:
    """The :class:`FastPair` over :func:`~dualhuman_builder.geometry.distance.get_pair_distance` (built once).

    On the CPU it wraps ``get_pair_distance()`` called exactly so, without arguments: its cache
    keys on how it is called, and a second ``PairDistance`` would build its BVHs on another frame,
    where a point as close to two faces (on their shared edge) may take the other face's rounding."""
    from dualhuman_builder.geometry.distance import get_pair_distance

    return FastPair(get_pair_distance() if device == "cpu" else get_pair_distance(device))

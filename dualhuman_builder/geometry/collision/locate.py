"""Where two bodies penetrate: the broad phase and the exact location of the contacts.

Bodies are ``(B, V, 3)`` torch tensors in metres, one frame per row. The broad phase marks a frame
active when the bodies' axis-aligned boxes, grown by ``pad``, overlap; inactive frames get no query.
In an active frame the query points of each direction are the obstacle-surface vertices of one body
within ``pad`` of the other body's box, and :class:`ContactLocator` finds, exactly, those inside the
other body (and, with a margin, those outside within it), each with its closest point on the other
surface as a face and barycentric weights.

Problems are numbered ``p = 2k + side`` over the active frames ``k``: side 0 queries b's vertices
against a, side 1 a's against b.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dualhuman_builder.geometry.collision.flood import SignFlood
from dualhuman_builder.geometry.collision.memory import SignMemory
from dualhuman_builder.geometry.collision.queries import MeshPool
from dualhuman_builder.geometry.collision.search import search_contacts
from dualhuman_builder.geometry.collision.surface import ObstacleSurface


@dataclass
class Contacts:
    """Located vertices of one call, concatenated over (frame, direction), sorted by problem then vertex.

    ``frame (M,)`` index into the batch, ``side (M,)`` 0 = a vertex of b against a, 1 = a vertex of a
    against b, ``vert (M,)`` query vertex, ``depth (M,)`` metres (> 0 inside, negative: outside within
    the margin), ``face (M,)`` row of the obstacle faces, ``bary (M, 3)`` barycentric weights of the
    closest point on that face.
    """

    frame: np.ndarray
    side: np.ndarray
    vert: np.ndarray
    depth: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    #: the index tensors :func:`~.depth.assemble` builds from the above, kept for the next evaluation
    #: of the same contacts (a held pass evaluates them many times)
    assembly: tuple | None = None

    @classmethod
    def empty(cls) -> Contacts:
        z = np.zeros(0, np.int64)
        return cls(frame=z, side=z, vert=z, depth=np.zeros(0), face=z, bary=np.zeros((0, 3)))

    def select(self, keep: np.ndarray, frame: np.ndarray | None = None) -> Contacts:
        """The contacts at ``keep`` (bool mask or indices), with ``frame`` renumbered if given."""
        return Contacts(frame=self.frame[keep] if frame is None else frame, side=self.side[keep], vert=self.vert[keep],
                        depth=self.depth[keep], face=self.face[keep], bary=self.bary[keep])  # fmt: skip


def broad_phase(va: torch.Tensor, vb: torch.Tensor, pad: float) -> tuple[torch.Tensor, np.ndarray, tuple]:
    """Frames whose bodies ``va``, ``vb`` ``(B, V, 3)`` may touch: ``active (B,)`` bool tensor (the
    boxes, grown by ``pad`` metres, overlap), its indices ``(n,)`` int64, and the ungrown boxes
    ``(lo_a, hi_a, lo_b, hi_b)``, each ``(B, 3)`` float32 numpy."""
    ta, tb = va.transpose(1, 2).contiguous(), vb.transpose(1, 2).contiguous()  # fast reductions
    boxes = ta.amin(dim=2), ta.amax(dim=2), tb.amin(dim=2), tb.amax(dim=2)
    lo_a, hi_a, lo_b, hi_b = boxes[0] - pad, boxes[1] + pad, boxes[2] - pad, boxes[3] + pad
    active = ((lo_a <= hi_b) & (lo_b <= hi_a)).all(dim=1)
    boxes = tuple(np.asarray(b.detach().cpu().numpy(), np.float32) for b in boxes)
    return active, np.flatnonzero(active.cpu().numpy()), boxes


class ContactLocator:
    """Exact location of the contacts (methods ``"warp"`` and ``"igl"``) over the term's collaborators.

    ``band``: radius of the first, banded query (metres); ``pad``: how far outside the other body's
    box a vertex is still a candidate (metres); ``flood_min``: open far vertices from which the sign
    flood fill replaces one full query each (:mod:`.search`).
    """

    def __init__(self, surface: ObstacleSurface, pool: MeshPool, flood: SignFlood, memory: SignMemory,
                 method: str, band: float, pad: float, flood_min: int):  # fmt: skip
        self.surface, self.pool, self.flood, self.memory = surface, pool, flood, memory
        self.method, self.band, self.pad, self.flood_min = method, band, pad, flood_min

    def locate(self, va: torch.Tensor, vb: torch.Tensor, frames: np.ndarray, boxes: tuple, keys: list | None = None,
               margin: float = 0.0) -> tuple[Contacts, dict]:  # fmt: skip
        """Penetrating vertices of both bodies ``va``, ``vb`` ``(B, V, 3)`` in the active ``frames``
        (:func:`broad_phase`, with its ``boxes``); with ``margin > 0`` (metres, at most ``band``) also
        those outside within ``margin`` of the other surface. ``keys``: the batch's frame names, for
        the sign memory (:mod:`.memory`), or None. Returns the contacts and the counts of the search
        (candidates, near, far, representatives, conflicted, full, reused; candidates only for igl)."""
        A, Bv, Q, O, lo, hi, dbox, cand = self._problems(va, vb, frames, boxes)
        V = A.shape[1]
        stats = {"candidates": int(cand.sum())}
        if self.method == "igl":
            prob, vert, depth, face, bary = igl_contacts(Q, O, cand, self.surface.obstacle_faces, self.band, margin)
        elif keys is None or self.memory.max_memo == 0:
            found, _, _, stats = search_contacts(self.pool, self.flood, Q, O, cand, dbox, lo, hi, self.band,
                                                 self.flood_min, None, margin)  # fmt: skip
            prob, vert, depth, face, bary = found
        else:
            (prob, vert, depth, face, bary), stats = self._remembered([keys[f] for f in frames], A, Bv, Q, O, cand, dbox,
                                                                       lo, hi, margin)  # fmt: skip
        if self.method != "igl":  # one order however the signs were found (the loss sums in this order)
            order = np.argsort(prob * V + vert, kind="stable")
            prob, vert, depth, face, bary = prob[order], vert[order], depth[order], face[order], bary[order]
        return Contacts(frame=frames[prob // 2], side=prob % 2, vert=vert, depth=depth, face=face, bary=bary), stats

    def _problems(self, va, vb, frames, boxes) -> tuple:
        """The active frames' bodies ``A``, ``Bv`` ``(K, V, 3)``, problems ``Q`` (query) and ``O``
        (obstacle) ``(2K, V, 3)``, float32; the obstacles' boxes ``lo``, ``hi`` ``(2K, 3)``; each query
        vertex's distance to its obstacle's box ``dbox (2K, V)`` (a lower bound of its distance to the
        obstacle) and the candidates ``cand (2K, V)``: surface vertices within ``pad`` of that box."""
        A = va[torch.as_tensor(frames, device=va.device)].detach().cpu().numpy().astype(np.float32)
        Bv = vb[torch.as_tensor(frames, device=vb.device)].detach().cpu().numpy().astype(np.float32)
        K, V = A.shape[:2]
        Q = np.empty((2 * K, V, 3), np.float32)
        Q[0::2], Q[1::2] = Bv, A
        O = np.empty_like(Q)
        O[0::2], O[1::2] = A, Bv
        # the broad phase's boxes hold all of each obstacle's vertices, which is all a lower bound needs
        # (float32 rounding is monotonic, so they are also the boxes of O)
        la, ha, lb_, hb = (b[frames] for b in boxes)
        lo, hi = np.empty((2 * K, 3), np.float32), np.empty((2 * K, 3), np.float32)
        lo[0::2], lo[1::2], hi[0::2], hi[1::2] = la, lb_, ha, hb
        lo_t, hi_t = torch.from_numpy(lo), torch.from_numpy(hi)
        Qt = torch.from_numpy(Q)  # torch: vectorised over these large arrays, zero-copy
        dbox = torch.linalg.vector_norm(Qt - torch.clamp(Qt, lo_t[:, None], hi_t[:, None]), dim=2).numpy()
        cand = (dbox <= self.pad) & self.surface.vertex_mask(V)
        return A, Bv, Q, O, lo, hi, dbox, cand

    def _remembered(self, fkeys: list, A, Bv, Q, O, cand, dbox, lo, hi, margin: float) -> tuple:
        """:func:`~.search.search_contacts` with the sign memory: level by level
        (:meth:`~.memory.SignMemory.levels`), each frame starting from the signs remembered for its
        source frame, and remembering its own. Returns the contacts' arrays and the summed counts."""
        K = len(A)
        stats, out = {}, []
        for rows, src in self.memory.levels(fkeys, A.shape[1]):
            p = np.ravel([2 * rows, 2 * rows + 1], order="F")  # their problems, in order
            pick = ((A, rows), (Bv, rows), (Q, p), (O, p), (cand, p), (dbox, p), (lo, p), (hi, p))
            sub = [x if len(rows) == K else np.ascontiguousarray(x[i]) for x, i in pick]
            prior = self.memory.prior([fkeys[k] for k in src], sub[0], sub[1])
            found, sgn, lb, counts = search_contacts(self.pool, self.flood, *sub[2:], self.band, self.flood_min, prior,
                                                     margin)  # fmt: skip
            self.memory.remember([fkeys[k] for k in rows], sub[0], sub[1], sgn, lb)
            out.append((p[found[0]],) + found[1:])
            for key, n in counts.items():
                stats[key] = stats.get(key, 0) + n
        return tuple(np.concatenate(x) for x in zip(*out)), stats


def igl_contacts(Q: np.ndarray, O: np.ndarray, cand: np.ndarray, faces: np.ndarray, band: float,
                 margin: float = 0.0) -> tuple:  # fmt: skip
    """Method ``"igl"``: ``igl.signed_distance`` (pseudonormal sign) of the candidates ``cand (P, V)``
    of problems ``Q`` against ``O`` (``(P, V, 3)``, mesh ``faces``), exact, with libigl's AABB tree
    rebuilt per problem. Returns ``(problem, vertex, depth, face, bary)`` of the vertices inside or
    outside within ``margin`` (metres), in problem order."""
    import igl

    P = Q.shape[0]
    out = [[], [], [], [], []]
    for p in range(P):
        vi = np.flatnonzero(cand[p])
        if not len(vi):
            continue
        Ov = O[p].astype(np.float64)
        S, fi, C, _ = igl.signed_distance(Q[p, vi].astype(np.float64), Ov, faces,
                                           igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL, -np.inf, band)  # fmt: skip
        ins = np.isfinite(S) & (S < margin)
        if not ins.any():
            continue
        fi, C = fi[ins], C[ins]
        out[0].append(np.full(int(ins.sum()), p))
        out[1].append(vi[ins])
        out[2].append(-S[ins])
        out[3].append(fi)
        out[4].append(barycentric(C, Ov[faces[fi]]))
    if not out[0]:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(0, int), np.zeros((0, 3))
    return tuple(np.concatenate(x) for x in out)


def barycentric(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentric weights ``(N, 3)`` of points ``p (N, 3)`` lying on triangles ``tri (N, 3, 3)``
    (degenerate triangles: the denominator is clamped to 1e-30)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d00 = (v0 * v0).sum(1)
    d01 = (v0 * v1).sum(1)
    d11 = (v1 * v1).sum(1)
    d20 = (v2 * v0).sum(1)
    d21 = (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 1e-30, den, 1e-30)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.stack([1.0 - v - w, v, w], axis=1)

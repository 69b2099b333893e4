"""Per-vertex contacts between two body meshes, frame by frame, with ``igl.signed_distance``.

For every frame and both directions (vertices of A against B's surface, of B against A's), the
pseudonormal signed distance (metres, negative inside) within a band ``band_m``; a vertex is in
contact when its distance is below ``threshold_m`` (penetrations included). Frames are in the
world frame of :mod:`dualhuman_builder.conventions`; vertices ``(T, V, 3)`` metres.

How a frame is computed (exact: within the band, equal to one ``igl.signed_distance`` call of
every vertex against the whole closed mesh, and labels equal to that call's without a band, which
``tests/test_contacts.py`` checks to 1e-9 m):

1. **Broad phase.** Each body region is cut once (at the rest pose) into patches of <= 16
   vertices, grouped into coarse patches of <= 64. Per frame, a *query* box per patch holds its
   vertices; a *target* box per patch holds its faces (a face belongs to the patch of the majority
   of its vertices), so every point of the surface lies in some target box. A frame whose
   whole-body boxes are farther apart than the band is skipped with no query at all. Otherwise
   coarse query/target pairs within the band are found, then the fine pairs inside them; only
   the vertices of query patches in some pair are queried. Any vertex left out is farther than
   the band from the other surface.
2. **Sub-mesh.** Those vertices are queried against only the faces of target patches in some
   pair. This holds the closest face of every vertex within the band and every face around its
   closest vertex or edge (they all contain a point within the band), so libigl finds the same
   closest point with the same pseudonormal sign. ``igl`` rebuilds its AABB tree and normals on
   every call (about 2 us per face), which on the whole 26,692-face body dominates the cost.
3. **Deep penetration.** ``igl`` returns NaN for points farther than the band on either side, so
   a vertex more than ``band_m`` inside the other body would come back NaN. Such vertices are
   found by a flood fill over the query body's edges: from a vertex inside within the band, across
   an edge shorter than the band, to an out-of-band vertex, then across out-of-band vertices
   joined by edges shorter than twice the band (the signed distance is 1-Lipschitz, so these
   edges cannot leave the inside). They are labelled in contact with distance ``-inf``.
   (anny has a few edges longer than 5 cm, on the thighs and shins; a deep vertex reachable
   only across them stays NaN, i.e. not in contact.)

Frames run one after the other in the calling thread. ``igl.signed_distance`` holds the GIL (a
Python thread makes no progress during a call), so a thread pool cannot help. A 2-process fork
pool measured 1.0x to 1.8x the serial loop on the shared 2-core machine, depending on what else
ran (``benchmarks/bench_contacts.py``, row d), and a spawned one lost its ~1 s start-up on short
sequences; neither is used: forking a process that holds torch's and warp's threads is unsafe,
and spawning fails in callers' scripts without a ``__main__`` guard.

Region events follow CHI3D's contact signatures: a region pair (region ``r`` of actor 0, region
``s`` of actor 1) is in contact on a frame when a contact vertex of actor 0 in ``r`` has its
closest point on a face of actor 1 in region ``s``, or symmetrically from actor 1's side.
An event is a maximal run of such frames (gaps of up to ``merge_gap`` frames are merged):
``start`` inclusive, ``end`` exclusive. A face's region is the majority region of its vertices.
Vertices deeper than the band have no closest face and count towards no pair.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

DEFAULT_THRESHOLD_M = 0.02
DEFAULT_BAND_M = 0.05
DEFAULT_MERGE_GAP = 1
CONTACT_RESULT_VERSION = 1


# ============================================================================ mesh topology
def _bisect(points: np.ndarray, idx: np.ndarray, fine: int, coarse: int, out: list, parent: list,
            cid: int | None = None) -> None:  # fmt: skip
    """Split ``idx`` at the median of its points' longest box axis down to groups of <= ``fine``
    (appended to ``out`` in depth-first order); the first ancestor with <= ``coarse`` points names
    the coarse group (``parent``) of every leaf under it, so a coarse group's leaves are contiguous."""
    if cid is None and len(idx) <= coarse:
        cid = (max(parent) + 1) if parent else 0
    if len(idx) <= fine:
        out.append(idx)
        parent.append(cid)
        return
    p = points[idx]
    axis = int(np.argmax(p.max(0) - p.min(0)))
    order = idx[np.argsort(p[:, axis], kind="stable")]
    half = len(order) // 2
    _bisect(points, order[:half], fine, coarse, out, parent, cid)
    _bisect(points, order[half:], fine, coarse, out, parent, cid)


def _starts(lengths) -> np.ndarray:
    lengths = np.asarray(lengths, dtype=np.int64)
    return np.cumsum(lengths) - lengths


@dataclass(frozen=True, eq=False)
class ContactTopology:
    """Index arrays for one mesh topology, shared by both bodies, built once.

    ``faces (F, 3)`` int64: the closed target mesh (for anny, its body component); ``num_vertices``
    V; ``vertex_region (V,)`` region index per vertex; ``region_names (R,)``; ``reference_vertices
    (V, 3)`` metres, any pose (the rest pose for anny), used only to cut each region into compact
    **patches**: median splits along the longest axis down to ``patch_vertices`` vertices, grouped
    into coarse patches of at most ``coarse_vertices`` (a two-level hierarchy of boxes).
    Derived: ``face_region (F,)`` and ``face_patch (F,)``, the majority region / patch of each face's
    vertices (the first vertex's on a three-way tie); ``vertex_patch (V,)``.
    """

    faces: np.ndarray
    num_vertices: int
    vertex_region: np.ndarray
    region_names: tuple[str, ...]
    reference_vertices: np.ndarray = field(repr=False)
    patch_vertices: int = 16
    coarse_vertices: int = 64
    face_region: np.ndarray = field(init=False, repr=False)
    vertex_patch: np.ndarray = field(init=False, repr=False)
    face_patch: np.ndarray = field(init=False, repr=False)
    _ix: dict = field(init=False, repr=False)  # index arrays, see __post_init__

    def __post_init__(self):
        faces = np.asarray(self.faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
            raise ValueError(f"faces must have shape (F, 3) with F > 0, got {faces.shape}")
        if not np.issubdtype(faces.dtype, np.integer):
            raise ValueError(f"faces must be integer vertex indices, got dtype {faces.dtype}")
        faces = faces.astype(np.int64)
        V = int(self.num_vertices)
        if faces.min() < 0 or faces.max() >= V:
            raise ValueError(f"faces index vertices 0..{V - 1}; found {faces.min()}..{faces.max()}")
        region = np.asarray(self.vertex_region)
        if region.shape != (V,):
            raise ValueError(f"vertex_region must have shape ({V},), got {region.shape}")
        if not np.issubdtype(region.dtype, np.integer) or region.min() < 0:
            raise ValueError("vertex_region must hold non-negative integer region indices")
        names = tuple(str(n) for n in self.region_names)
        if int(region.max()) >= len(names):
            raise ValueError(f"vertex_region uses region {int(region.max())} but only {len(names)} names are given")
        ref = np.asarray(self.reference_vertices, dtype=np.float64)
        if ref.shape != (V, 3) or not np.isfinite(ref).all():
            raise ValueError(f"reference_vertices must be finite with shape ({V}, 3), got {ref.shape}")
        if not 1 <= int(self.patch_vertices) <= int(self.coarse_vertices):
            raise ValueError(f"need 1 <= patch_vertices ({self.patch_vertices}) <= coarse_vertices "
                             f"({self.coarse_vertices})")  # fmt: skip
        region = region.astype(np.int64)
        patches: list[np.ndarray] = []
        coarse_of: list[int] = []
        for r in np.unique(region):
            _bisect(ref, np.flatnonzero(region == r), int(self.patch_vertices), int(self.coarse_vertices), patches,
                    coarse_of)  # fmt: skip
        coarse_of = np.array(coarse_of)
        vertex_patch = np.empty(V, dtype=np.int64)
        for k, idx in enumerate(patches):
            vertex_patch[idx] = k

        def majority(label):
            a, b, c = label[faces[:, 0]], label[faces[:, 1]], label[faces[:, 2]]
            return np.where((b == c) & (a != b), b, a)

        face_patch = majority(vertex_patch)
        # target patches: those owning faces (a patch of only eye or mouth vertices owns none)
        t_patches, face_target = np.unique(face_patch, return_inverse=True)
        by_target = np.argsort(face_target, kind="stable")
        t_groups = [np.unique(g) for g in np.split(faces[by_target], np.cumsum(np.bincount(face_target))[:-1])]
        t_coarse_len = np.unique(coarse_of[t_patches], return_counts=True)[1]  # t_patches sorted: contiguous
        q_coarse_len = np.unique(coarse_of, return_counts=True)[1]
        e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        ix = {
            "q_index": np.concatenate(patches), "q_starts": _starts([len(g) for g in patches]),
            "q_len": np.array([len(g) for g in patches]),
            "qc_starts": _starts(q_coarse_len), "qc_len": q_coarse_len,
            "t_index": np.concatenate(t_groups), "t_starts": _starts([len(g) for g in t_groups]),
            "tc_starts": _starts(t_coarse_len), "tc_len": t_coarse_len,
            "face_target": face_target,
            "edges": np.unique(np.sort(e, axis=1), axis=0),
        }  # fmt: skip
        for k, v in (("faces", faces), ("num_vertices", V), ("vertex_region", region), ("region_names", names),
                     ("reference_vertices", ref), ("face_region", majority(region)), ("vertex_patch", vertex_patch),
                     ("face_patch", face_patch), ("_ix", ix)):  # fmt: skip
            object.__setattr__(self, k, v)

    @property
    def num_patches(self) -> int:
        return len(self._ix["q_starts"])

    @classmethod
    def for_model(cls, model=None, regions=None, patch_vertices: int = 16, coarse_vertices: int = 64) -> "ContactTopology":
        """The topology of the anny ``model`` (default: the process-wide one): its body component
        (:func:`~dualhuman_builder.body.topology.collision_faces`), ``regions`` (default
        :func:`~dualhuman_builder.body.regions.load_regions`) and patches cut at the rest pose."""
        from dualhuman_builder.body.model import get_body_model
        from dualhuman_builder.body.regions import load_regions
        from dualhuman_builder.body.topology import collision_faces

        model = model or get_body_model()
        faces = model.faces.cpu().numpy()
        regions = regions or load_regions(model)
        rest = model.rest().vertices[0].detach().cpu().numpy()
        return cls(faces[collision_faces(faces, model.num_vertices)], model.num_vertices, regions.vertex_region,
                   regions.names, rest, patch_vertices, coarse_vertices)  # fmt: skip

    def boxes(self, X: np.ndarray) -> dict[str, np.ndarray]:
        """Boxes of one body's vertices ``X (V, 3)``: as query (``q``: fine patches of its
        vertices, ``qc``: coarse) and as target (``t``, ``tc``: the same over each patch's faces,
        so that they hold the whole surface). Each ``(N, 2, 3)`` lo/hi."""
        ix = self._ix
        out = {}
        for key, index, starts in (("q", ix["q_index"], ix["q_starts"]), ("t", ix["t_index"], ix["t_starts"])):
            G = X[index]
            lo, hi = np.minimum.reduceat(G, starts, axis=0), np.maximum.reduceat(G, starts, axis=0)
            c = ix[key + "c_starts"]
            out[key] = (lo, hi)
            out[key + "c"] = (np.minimum.reduceat(lo, c, axis=0), np.maximum.reduceat(hi, c, axis=0))
        return out


# ============================================================================ result
@dataclass(eq=False)
class ContactResult:
    """Contacts of two bodies over T frames (index 0 = actor A, 1 = actor B).

    ``labels (2, T, V)`` bool: vertex of actor i in contact with the other body (signed distance
    below ``threshold_m``, penetration included); ``distances (2, T, V)`` float16 signed distance
    in metres (negative inside), NaN beyond the band or not queried, ``-inf`` inside deeper than
    the band; ``frame_contact (T,)``: any contact on the frame; ``valid (T,)``: frame computed
    (False: skipped because of non-finite vertices); ``events``: region-level contact events (see
    the module docstring; keys ``region_a``, ``region_b``, ``start``, ``end`` (exclusive),
    ``contact_frames``, ``peak_vertices``, ``min_distance_m``, and ``start_s``/``end_s`` when
    ``fps`` is known); ``stats``: counts and timings; ``region_names``; ``actors`` names.
    """

    labels: np.ndarray
    distances: np.ndarray
    frame_contact: np.ndarray
    valid: np.ndarray
    events: list[dict[str, Any]]
    stats: dict[str, Any]
    region_names: tuple[str, ...] = ()
    actors: tuple[str, str] = ("a", "b")

    def __post_init__(self):
        self.labels = np.asarray(self.labels, dtype=bool)
        if self.labels.ndim != 3 or self.labels.shape[0] != 2:
            raise ValueError(f"labels must have shape (2, T, V), got {self.labels.shape}")
        self.distances = np.asarray(self.distances, dtype=np.float16)
        if self.distances.shape != self.labels.shape:
            raise ValueError(f"distances {self.distances.shape} and labels {self.labels.shape} differ in shape")
        T = self.labels.shape[1]
        self.frame_contact = np.asarray(self.frame_contact, dtype=bool)
        self.valid = np.asarray(self.valid, dtype=bool)
        for name in ("frame_contact", "valid"):
            if getattr(self, name).shape != (T,):
                raise ValueError(f"{name} must have shape ({T},), got {getattr(self, name).shape}")
        self.region_names = tuple(self.region_names)
        self.actors = tuple(self.actors)

    @property
    def num_frames(self) -> int:
        return self.labels.shape[1]

    def contact_counts(self) -> np.ndarray:
        """``(2, T)`` int: number of contact vertices of each actor per frame."""
        return self.labels.sum(axis=2)

    def f1(self, other) -> dict[str, float]:
        """Precision, recall and F1 of these labels against ``other`` (the reference): a
        ``(2, T, V)`` bool array or a pair of ``(T, V)`` arrays. F1 is 1.0 when neither has a
        contact."""
        ref = np.stack([np.asarray(o, dtype=bool) for o in other]) if not isinstance(other, np.ndarray) \
            else np.asarray(other, dtype=bool)  # fmt: skip
        if ref.shape != self.labels.shape:
            raise ValueError(f"reference labels have shape {ref.shape}, these have {self.labels.shape}")
        tp = int(np.sum(self.labels & ref))
        fp = int(np.sum(self.labels & ~ref))
        fn = int(np.sum(~self.labels & ref))
        precision = tp / (tp + fp) if tp + fp else 1.0
        recall = tp / (tp + fn) if tp + fn else 1.0
        f1 = 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 1.0
        return {"f1": f1, "precision": precision, "recall": recall, "tp": tp, "fp": fp, "fn": fn}

    def save(self, path: str | Path) -> Path:
        """One ``.npz`` (atomic): labels bit-packed along V, float16 distances, JSON metadata."""
        from dualhuman_builder.fileio import save_npz

        arrays = {"labels_packed": np.packbits(self.labels, axis=2), "distances": self.distances,
                  "frame_contact": self.frame_contact, "valid": self.valid}  # fmt: skip
        meta = {"num_vertices": int(self.labels.shape[2]), "events": self.events, "stats": self.stats,
                "region_names": list(self.region_names), "actors": list(self.actors)}  # fmt: skip
        return save_npz(path, "ContactResult", CONTACT_RESULT_VERSION, arrays, meta)

    @classmethod
    def load(cls, path: str | Path) -> "ContactResult":
        from dualhuman_builder.errors import FormatError
        from dualhuman_builder.fileio import load_npz

        names = ("labels_packed", "distances", "frame_contact", "valid")
        arrays, meta = load_npz(path, "ContactResult", CONTACT_RESULT_VERSION, required=names)
        try:
            labels = np.unpackbits(arrays["labels_packed"], axis=2, count=int(meta["num_vertices"])).astype(bool)
            return cls(labels, arrays["distances"], arrays["frame_contact"], arrays["valid"], meta["events"],
                       meta["stats"], tuple(meta["region_names"]), tuple(meta["actors"]))  # fmt: skip
        except (KeyError, ValueError) as e:
            raise FormatError(f"inconsistent ContactResult: {e}", path=path) from e


# ============================================================================ one frame
def _overlap(alo, ahi, blo, bhi, pad: float) -> np.ndarray:
    """``(Na, Nb)`` bool: box a grown by ``pad`` overlaps box b (boxes ``(N, 3)`` lo and hi).
    Per axis: ``np.all`` over a length-3 axis is several times slower than two ``&``."""
    out = (alo[:, None, 0] <= bhi[None, :, 0] + pad) & (ahi[:, None, 0] >= blo[None, :, 0] - pad)
    for k in (1, 2):
        out &= alo[:, None, k] <= bhi[None, :, k] + pad
        out &= ahi[:, None, k] >= blo[None, :, k] - pad
    return out


def _inside(x, lo, hi) -> np.ndarray:
    """``(N,)`` bool: point or box ``x`` (``(N, 3)``; a box as ``(xlo, xhi)``) overlaps box ``lo, hi`` ``(N, 3)``."""
    xlo, xhi = x if isinstance(x, tuple) else (x, x)
    out = (xhi[:, 0] >= lo[:, 0]) & (xlo[:, 0] <= hi[:, 0])
    for k in (1, 2):
        out &= xhi[:, k] >= lo[:, k]
        out &= xlo[:, k] <= hi[:, k]
    return out


def _near(ba: dict, bb: dict, band: float) -> bool:
    """Whether the whole-body boxes of two bodies (from :meth:`ContactTopology.boxes`) come
    within ``band`` of each other."""
    def near(q, t):
        return bool(np.all(q[0].min(0) <= t[1].max(0) + band) and np.all(q[1].max(0) >= t[0].min(0) - band))

    return near(ba["qc"], bb["tc"]) or near(bb["qc"], ba["tc"])


def _ranges(starts: np.ndarray, lens: np.ndarray, groups: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Concatenated ``starts[g] + arange(lens[g])`` over ``groups``, and the position in
    ``groups`` each element comes from."""
    n = lens[groups]
    owner = np.repeat(np.arange(len(groups)), n)
    return starts[groups][owner] + np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n), owner


def _query(topo: ContactTopology, P: np.ndarray, Q: np.ndarray, pbox: dict, qbox: dict, band: float, counts: dict):
    """Signed distances ``(V,)`` of the vertices ``P`` to the surface of ``Q`` (NaN: farther than
    ``band`` or not queried) and the closest face ``(V,)`` (index into ``topo.faces``, -1 where NaN).
    ``pbox``, ``qbox``: :meth:`ContactTopology.boxes` of ``P`` and ``Q``."""
    import igl

    ix = topo._ix
    V = topo.num_vertices
    d = np.full(V, np.nan)
    face = np.full(V, -1, dtype=np.int64)
    (qlo, qhi), (tlo, thi) = pbox["qc"], qbox["tc"]
    # coarse patches near the other body's whole box, then coarse pairs, then their fine pairs
    iq = np.flatnonzero(_overlap(qlo, qhi, tlo.min(0, keepdims=True), thi.max(0, keepdims=True), band)[:, 0])
    it = np.flatnonzero(_overlap(tlo, thi, qlo.min(0, keepdims=True), qhi.max(0, keepdims=True), band)[:, 0])
    pi, pj = np.nonzero(_overlap(qlo[iq], qhi[iq], tlo[it], thi[it], band))
    if not len(pi):
        return d, face
    fq, own = _ranges(ix["qc_starts"], ix["qc_len"], iq[pi])
    ft, own2 = _ranges(ix["tc_starts"], ix["tc_len"], it[pj][own])
    fq = fq[own2]
    (qlo, qhi), (tlo, thi) = pbox["q"], qbox["t"]
    ok = _inside((qlo[fq] - band, qhi[fq] + band), tlo[ft], thi[ft])
    q_on = np.zeros(len(qlo), dtype=bool)
    q_on[fq[ok]] = True
    t_on = np.zeros(len(tlo), dtype=bool)
    t_on[ft[ok]] = True
    keep = np.flatnonzero(q_on[topo.vertex_patch])
    if not len(keep):
        return d, face
    fidx = np.flatnonzero(t_on[ix["face_target"]])
    sub = topo.faces[fidx]
    used = np.zeros(V, dtype=bool)
    used[sub.ravel()] = True
    vidx = np.flatnonzero(used)
    remap = np.empty(V, dtype=np.int64)
    remap[vidx] = np.arange(len(vidx))
    S, I, _, _ = igl.signed_distance(P[keep], Q[vidx], remap[sub], sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL,
                                     lower_bound=-band, upper_bound=band)  # fmt: skip
    ok = np.isfinite(S)
    d[keep] = S
    face[keep[ok]] = fidx[I[ok]]
    counts["queried_vertices"] += len(keep)
    counts["queried_faces"] += len(fidx)
    return d, face


def _flood_deep(topo: ContactTopology, P: np.ndarray, d: np.ndarray, band: float) -> int:
    """Set ``d`` to -inf on vertices more than ``band`` inside (see the module docstring);
    returns how many."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = topo._ix["edges"]
    neg, far = d < 0, np.isnan(d)
    if not neg.any():
        return 0
    touch = (neg[e[:, 0]] & far[e[:, 1]]) | (far[e[:, 0]] & neg[e[:, 1]])
    if not touch.any():
        return 0
    length = np.linalg.norm(P[e[:, 0]] - P[e[:, 1]], axis=1)
    seed_e = e[touch & (length < band)]
    if not len(seed_e):
        return 0
    seeds = np.where(far[seed_e[:, 0]], seed_e[:, 0], seed_e[:, 1])
    ff = e[far[e[:, 0]] & far[e[:, 1]] & (length < 2 * band)]
    V = topo.num_vertices
    graph = coo_matrix((np.ones(len(ff)), (ff[:, 0], ff[:, 1])), shape=(V, V))
    comp = connected_components(graph, directed=False)[1]
    deep = far & np.isin(comp, np.unique(comp[seeds]))
    d[deep] = -np.inf
    return int(deep.sum())


def _frame_pairs(topo, d_a, f_a, d_b, f_b, threshold: float) -> dict[tuple[int, int], tuple[int, float]]:
    """Region pairs (region of actor 0, region of actor 1) in contact on one frame: pair ->
    (contact vertices on both sides, min distance)."""
    ra, rb, dist = [], [], []
    for i, (d, f) in enumerate(((d_a, f_a), (d_b, f_b))):
        v = np.flatnonzero(np.isfinite(d) & (d < threshold))
        if not len(v):
            continue
        own, other = topo.vertex_region[v], topo.face_region[f[v]]
        ra.append(own if i == 0 else other)
        rb.append(other if i == 0 else own)
        dist.append(d[v])
    if not ra:
        return {}
    ra, rb, dist = np.concatenate(ra), np.concatenate(rb), np.concatenate(dist)
    key = ra * len(topo.region_names) + rb
    order = np.argsort(key, kind="stable")
    key, dist = key[order], dist[order]
    uniq, start, count = np.unique(key, return_index=True, return_counts=True)
    mins = np.minimum.reduceat(dist, start)
    R = len(topo.region_names)
    return {(int(k // R), int(k % R)): (int(c), float(m)) for k, c, m in zip(uniq, count, mins)}


def _events(per_frame: list[dict], names, merge_gap: int, fps: float | None) -> list[dict[str, Any]]:
    runs: dict[tuple[int, int], list[tuple[int, int, float]]] = {}
    for t, pairs in enumerate(per_frame):
        for pair, (count, mind) in pairs.items():
            runs.setdefault(pair, []).append((t, count, mind))
    events = []
    for (ra, rb), frames in runs.items():
        group = [frames[0]]
        for item in frames[1:] + [None]:
            if item is not None and item[0] - group[-1][0] - 1 <= merge_gap:
                group.append(item)
                continue
            ev = {"region_a": names[ra], "region_b": names[rb], "start": group[0][0], "end": group[-1][0] + 1,
                  "contact_frames": len(group), "peak_vertices": max(g[1] for g in group),
                  "min_distance_m": round(min(g[2] for g in group), 6)}  # fmt: skip
            if fps:
                ev["start_s"], ev["end_s"] = round(ev["start"] / fps, 6), round(ev["end"] / fps, 6)
            events.append(ev)
            group = [item]
    events.sort(key=lambda e: (e["start"], e["region_a"], e["region_b"]))
    return events


def contact_frame(topology: ContactTopology, verts_a: np.ndarray, verts_b: np.ndarray, band_m: float = DEFAULT_BAND_M,
                  counts: dict | None = None) -> tuple[np.ndarray, np.ndarray] | None:  # fmt: skip
    """Both directions of one frame: ``(distances (2, V) float64, faces (2, V) int64)``, row 0 the
    vertices of A against B's surface, row 1 B against A's. Distances in metres, negative inside,
    NaN farther than ``band_m`` (or never queried), ``-inf`` inside deeper than ``band_m``;
    faces: the closest face (index into ``topology.faces``), -1 where the distance is not finite.
    None when the bodies' boxes are farther apart than ``band_m`` (no query made). ``counts``
    (optional) accumulates ``queried_vertices``, ``queried_faces`` and ``deep_vertices``."""
    A = np.ascontiguousarray(verts_a, dtype=np.float64)
    B = np.ascontiguousarray(verts_b, dtype=np.float64)
    V = topology.num_vertices
    for name, X in (("verts_a", A), ("verts_b", B)):
        if X.shape != (V, 3):
            raise ValueError(f"{name} must have shape ({V}, 3), got {X.shape}")
        if not np.isfinite(X).all():
            raise ValueError(f"{name} holds NaN or infinite coordinates")
    counts = counts if counts is not None else {}
    for k in ("queried_vertices", "queried_faces", "deep_vertices"):
        counts.setdefault(k, 0)
    lo_a, hi_a, lo_b, hi_b = A.min(0), A.max(0), B.min(0), B.max(0)
    if np.any(lo_a > hi_b + band_m) or np.any(lo_b > hi_a + band_m):
        return None  # whole bodies (all vertices) farther apart than the band
    ba, bb = topology.boxes(A), topology.boxes(B)
    if not _near(ba, bb, band_m):
        return None
    d_a, f_a = _query(topology, A, B, ba, bb, band_m, counts)
    d_b, f_b = _query(topology, B, A, bb, ba, band_m, counts)
    counts["deep_vertices"] += _flood_deep(topology, A, d_a, band_m) + _flood_deep(topology, B, d_b, band_m)
    return np.stack([d_a, d_b]), np.stack([f_a, f_b])


def _frame_result(topo: ContactTopology, A, B, threshold: float, band: float):
    """One frame as the sequence loop stores it: ``((labels (2, V), distances (2, V) float16,
    region pairs) or None when far apart, counts)``."""
    counts: dict = {}
    frame = contact_frame(topo, A, B, band, counts)
    if frame is None:
        return None, counts
    (d_a, d_b), (f_a, f_b) = frame
    labels = np.stack([d_a < threshold, d_b < threshold])  # NaN compares False, -inf True
    return (labels, np.stack([d_a, d_b]).astype(np.float16), _frame_pairs(topo, d_a, f_a, d_b, f_b, threshold)), counts


# ============================================================================ sequences
def check_params(threshold_m: float, band_m: float, merge_gap: int = DEFAULT_MERGE_GAP) -> tuple[float, float, int]:
    """Validated ``(threshold_m, band_m, merge_gap)``: a positive threshold (metres), a finite band
    at least as wide, a non-negative whole number of frames; ValueError otherwise."""
    try:
        threshold, band = float(threshold_m), float(band_m)
    except (TypeError, ValueError):
        raise ValueError(f"threshold_m and band_m must be numbers (metres), got {threshold_m!r} and {band_m!r}") from None
    if not (math.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold_m must be a positive distance in metres, got {threshold_m}")
    if not (math.isfinite(band) and band >= threshold):
        raise ValueError(f"band_m must be finite and at least threshold_m ({threshold}), got {band_m}")
    if isinstance(merge_gap, bool) or not isinstance(merge_gap, (int, np.integer)) or merge_gap < 0:
        raise ValueError(f"merge_gap must be a non-negative whole number of frames, got {merge_gap!r}")
    return threshold, band, int(merge_gap)


def _check_vertices(name: str, v, V: int) -> np.ndarray:
    v = np.asarray(v)
    if v.ndim != 3 or v.shape[2] != 3:
        raise ValueError(f"{name} must have shape (T, V, 3), got {v.shape}")
    if v.shape[0] == 0:
        raise ValueError(f"{name} has no frames (shape {v.shape})")
    if v.shape[1] != V:
        raise ValueError(f"{name} has {v.shape[1]} vertices per frame; the mesh topology has {V}")
    if not np.issubdtype(v.dtype, np.floating):
        raise ValueError(f"{name} must hold floating-point coordinates, got dtype {v.dtype}")
    return v


def contacts_from_vertices(verts_a: np.ndarray, verts_b: np.ndarray, topology: ContactTopology, *,
                           threshold_m: float = DEFAULT_THRESHOLD_M, band_m: float = DEFAULT_BAND_M,
                           merge_gap: int = DEFAULT_MERGE_GAP, fps: float | None = None,
                           actors: Sequence[str] = ("a", "b"), nan_policy: str = "skip",
                           progress: Callable[[str], None] | None = None) -> ContactResult:  # fmt: skip
    """Contacts between two bodies given their vertices ``verts_a``, ``verts_b`` ``(T, V, 3)``
    (world metres, any float dtype) on the mesh ``topology`` (see :meth:`ContactTopology.for_model`).

    ``threshold_m``: contact distance (> 0); ``band_m`` (>= threshold): distances are computed
    within it; ``merge_gap``: events separated by at most this many frames are merged;
    ``nan_policy``: ``"skip"`` (frames with any non-finite vertex are left out, counted in
    ``stats["skipped_nan_frames"]``, with ``valid`` False) or ``"raise"`` (ValueError naming the
    first such frame, before any work). ``progress(str)`` is called about every 10 % of frames.
    """
    topo = topology
    V = topo.num_vertices
    verts_a = _check_vertices("verts_a", verts_a, V)
    verts_b = _check_vertices("verts_b", verts_b, V)
    if verts_a.shape != verts_b.shape:
        raise ValueError(f"verts_a {verts_a.shape} and verts_b {verts_b.shape} must have the same shape")
    threshold, band, merge_gap = check_params(threshold_m, band_m, merge_gap)
    if nan_policy not in ("skip", "raise"):
        raise ValueError(f"nan_policy must be 'skip' or 'raise', got {nan_policy!r}")
    if len(actors) != 2:
        raise ValueError(f"actors must name two actors, got {list(actors)}")

    T = verts_a.shape[0]
    finite = np.isfinite(verts_a).all(axis=(1, 2)) & np.isfinite(verts_b).all(axis=(1, 2))
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        which = "verts_a" if not np.isfinite(verts_a[bad]).all() else "verts_b"
        if nan_policy == "raise":
            raise ValueError(f"{which} holds NaN or infinite coordinates at frame {bad} "
                             f"({int((~finite).sum())} of {T} frames affected)")  # fmt: skip
        if not finite.any():
            raise ValueError(f"every one of the {T} frames holds NaN or infinite vertex coordinates")

    t0 = time.perf_counter()
    labels = np.zeros((2, T, V), dtype=bool)
    distances = np.full((2, T, V), np.nan, dtype=np.float16)
    counts = {"queried_vertices": 0, "queried_faces": 0, "deep_vertices": 0}
    per_frame: list[dict] = [{} for _ in range(T)]
    far_frames = done = 0
    frames = np.flatnonzero(finite)
    step = max(1, math.ceil(len(frames) / 10))
    for t in frames:
        frame, c = _frame_result(topo, verts_a[t], verts_b[t], threshold, band)
        for k, v in c.items():
            counts[k] += v
        if frame is None:
            far_frames += 1
        else:
            labels[:, t], distances[:, t], per_frame[t] = frame
        done += 1
        if progress is not None and (done % step == 0 or done == len(frames)):
            progress(f"contacts: {done}/{len(frames)} frames ({100 * done // len(frames)} %)")
    seconds = time.perf_counter() - t0
    frame_contact = labels.any(axis=(0, 2))
    computed = int(finite.sum())
    stats = {
        "frames": T,
        "contact_frames": int(frame_contact.sum()),
        "skipped_far_frames": far_frames,
        "skipped_nan_frames": int(T - computed),
        "first_nan_frames": np.flatnonzero(~finite)[:10].tolist(),
        "queried_vertices": counts["queried_vertices"],
        "queried_faces": counts["queried_faces"],
        "deep_vertices": counts["deep_vertices"],
        "seconds": round(seconds, 4),
        "frame_pairs_per_s": round(computed / seconds, 2) if seconds > 0 else None,
        "threshold_m": threshold,
        "band_m": band,
        "merge_gap": int(merge_gap),
        "fps": fps,
    }
    events = _events(per_frame, topo.region_names, int(merge_gap), fps)
    return ContactResult(labels, distances, frame_contact, finite, events, stats, topo.region_names, tuple(actors))


def compute_contacts(seq, threshold_m: float = DEFAULT_THRESHOLD_M, band_m: float = DEFAULT_BAND_M,
                     progress: Callable[[str], None] | None = None, merge_gap: int = DEFAULT_MERGE_GAP,
                     nan_policy: str = "skip", topology: ContactTopology | None = None) -> ContactResult:  # fmt: skip
    """Contacts between the two fitted bodies of ``seq`` (an
    :class:`~dualhuman_builder.tracks.InteractionSequence`, e.g. the fit stage's ``bodies.npz``);
    vertices from :meth:`BodyTrack.vertices` (computed here if not cached: ~5 ms per frame pair).
    See :func:`contacts_from_vertices`; ``topology`` defaults to the installed anny's."""
    from dualhuman_builder.tracks import InteractionSequence

    if seq is None:
        raise ValueError("no fitted bodies: pass the InteractionSequence the fit stage wrote (bodies.npz)")
    if not isinstance(seq, InteractionSequence):
        raise ValueError(f"expected an InteractionSequence of two fitted bodies (the fit stage's bodies.npz), "
                         f"got {type(seq).__name__}")  # fmt: skip
    if seq.num_frames == 0:
        raise ValueError(f"sequence {seq.take or '(unnamed)'} has no frames: the fit stage produced no bodies")
    check_params(threshold_m, band_m, merge_gap)  # before the body model runs
    topo = topology or default_topology()
    return contacts_from_vertices(seq.actors[0].vertices(), seq.actors[1].vertices(), topo, threshold_m=threshold_m,
                                  band_m=band_m, merge_gap=merge_gap, fps=seq.fps,
                                  actors=tuple(a.actor or f"actor{i}" for i, a in enumerate(seq.actors)),
                                  nan_policy=nan_policy, progress=progress)  # fmt: skip


@functools.lru_cache(maxsize=1)
def default_topology() -> ContactTopology:
    """:meth:`ContactTopology.for_model` of the process-wide anny model, built once (~0.5 s)."""
    return ContactTopology.for_model()


def contacts_for_scene(scene, threshold_m: float | None = None, band_m: float | None = None,
                       topology: ContactTopology | None = None) -> tuple[ContactResult, dict[str, float]]:
    """Contacts of a ground-truth :class:`~dualhuman_builder.sim.scenes.Scene` (or a path to a
    saved one) and their precision, recall and F1 against the scene's own per-vertex contacts
    (:meth:`Scene.contact_labels` at the same threshold). Defaults: the scene's
    ``CONTACT_THRESHOLD`` and ``DISTANCE_BAND``."""
    from dualhuman_builder.sim.scenes import CONTACT_THRESHOLD, DISTANCE_BAND, Scene

    if isinstance(scene, (str, Path)):
        scene = Scene.load(scene)
    threshold = CONTACT_THRESHOLD if threshold_m is None else threshold_m
    band = DISTANCE_BAND if band_m is None else band_m
    if threshold > DISTANCE_BAND:
        raise ValueError(f"threshold_m {threshold} exceeds the scene's stored distance band {DISTANCE_BAND} m; "
                         "its reference labels cannot be compared")  # fmt: skip
    res = compute_contacts(scene.sequence, threshold, band, topology=topology)
    return res, res.f1(scene.contact_labels(threshold))

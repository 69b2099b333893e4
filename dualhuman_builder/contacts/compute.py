"""Per-vertex contacts between two body meshes, frame by frame, with ``igl.signed_distance``.

For every frame and both directions (vertices of A against B's surface, of B against A's), the
pseudonormal signed distance (metres, negative inside) within a band ``band_m``; a vertex is in
contact when its distance is below ``threshold_m`` (penetrations included). Frames are in the
world frame of :mod:`dualhuman_builder.conventions`; vertices ``(T, V, 3)`` metres.

How a frame is computed (labels equal to one ``igl.signed_distance`` call of every vertex
against the whole closed mesh, and distances within the band equal to its answers, which
``tests/test_contacts.py`` checks: to 1e-9 m below the threshold, to 1e-7 m above it):

1. **Broad phase.** A frame whose whole-body boxes are farther apart than the band is skipped
   with no query at all; otherwise only vertices inside the other body's box grown by the band go
   on, and in the kernel only those within the band of one of the other body's region boxes.
2. **Narrow phase** (:mod:`dualhuman_builder.geometry.narrow`). A warp BVH of each body, built once
   at the rest pose and refit per frame, finds in float32 each remaining vertex's closest face and
   distance, keeping those within the band (plus a 10 um slack); the two directions run in two
   threads (warp's kernels release the GIL). Then per vertex:

   * **possible contacts** (float32 distance below ``threshold`` plus the slack) go to libigl:
     the narrow phase picks every face that may lie within the vertex's distance (plus the slack),
     and ``igl.signed_distance`` answers these vertices against that sub-mesh only. It holds the
     closest face and every face around the closest vertex or edge (they all contain the closest
     point), so libigl finds the same closest point with the same pseudonormal sign as on the
     whole mesh;
   * **the others** get the same pseudonormal signed distance in float64 on the face the BVH
     found, in the same warp kernel (the rule of :mod:`dualhuman_builder.geometry.pseudonormal`:
     closest point, and the sign from the face, edge or vertex pseudonormal as libigl builds
     them; ``tests/test_pseudonormal.py`` checks the kernel against that module to 1e-12 m); any
     that comes out inside (a deep penetration) goes to libigl too. Where two faces tie to
     float32 precision the BVH may name either: the distance then differs from libigl's by less
     than 1e-7 m (the test's bound; ``benchmarks/bench_contacts.py`` prints the largest
     difference), far below the float16 it is stored in.

   ``igl`` rebuilds its AABB tree and normals on every call (about 1.5 us per face) and spends
   about 5 us per point; the BVH's face walk for a vertex 4 cm away costs about as much, which is
   why only possible contacts take that path: on a hug's contact frames ~480 vertices per
   direction of the ~2,600 in the band.
3. **Deep penetration.** ``igl`` returns NaN for points farther than the band on either side, so
   a vertex more than ``band_m`` inside the other body would come back NaN. Such vertices are
   found by a flood fill over the query body's edges: from a vertex inside within the band, across
   an edge shorter than the band, to an out-of-band vertex, then across out-of-band vertices
   joined by edges shorter than twice the band (the signed distance is 1-Lipschitz, so these
   edges cannot leave the inside). They are labelled in contact with distance ``-inf``.
   (anny has a few edges longer than 5 cm, on the thighs and shins; a deep vertex reachable
   only across them stays NaN, i.e. not in contact.)

Frames run in the calling thread, pipelined: helper threads run the next two frames' narrow
phases (mostly outside the GIL) while this one runs libigl on the last (:func:`_compute_frames`);
or, for long sequences on machines with more than two CPUs, in worker processes
(:mod:`~dualhuman_builder.contacts.workers`): ``igl.signed_distance`` holds the GIL for each whole
call, so threads cannot share the rest of the work.

Region events follow CHI3D's contact signatures: a region pair (region ``r`` of actor 0, region
``s`` of actor 1) is in contact on a frame when a contact vertex of actor 0 in ``r`` has its
closest point on a face of actor 1 in region ``s``, or symmetrically from actor 1's side.
An event is a maximal run of such frames (gaps of up to ``merge_gap`` frames are merged):
``start`` inclusive, ``end`` exclusive. A face's region is the majority region of its vertices.
Vertices deeper than the band have no closest face and count towards no pair.
"""

from __future__ import annotations

import collections
import functools
import math
import threading
import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from dualhuman_builder.geometry.narrow import NearSelector
from dualhuman_builder.geometry.pseudonormal import MeshAdjacency

DEFAULT_THRESHOLD_M = 0.02
DEFAULT_BAND_M = 0.05
DEFAULT_MERGE_GAP = 1
CONTACT_RESULT_VERSION = 1
SELECTORS = 3  # narrow-phase selectors per thread: frames in flight (see _compute_frames)
COUNT_KEYS = ("queried_vertices", "queried_faces", "pseudonormal_vertices", "deep_vertices")


# ============================================================================ mesh topology
@dataclass(frozen=True, eq=False)
class ContactTopology:
    """Index arrays for one mesh topology, shared by both bodies, built once.

    ``faces (F, 3)`` int64: the closed target mesh (for anny, its body component); ``num_vertices``
    V; ``vertex_region (V,)`` region index per vertex; ``region_names (R,)``; ``reference_vertices
    (V, 3)`` metres, any pose (the rest pose for anny): the warp BVHs of the narrow phase are built
    there and refit per frame. Derived: ``face_region (F,)``, the majority region of each face's
    vertices (the first vertex's on a three-way tie), the unique edges (for the flood fill) and
    the faces' :class:`~dualhuman_builder.geometry.pseudonormal.MeshAdjacency`.
    """

    faces: np.ndarray
    num_vertices: int
    vertex_region: np.ndarray
    region_names: tuple[str, ...]
    reference_vertices: np.ndarray = field(repr=False)
    face_region: np.ndarray = field(init=False, repr=False)
    edges: np.ndarray = field(init=False, repr=False)  # (E, 2) int64, unique, sorted per row
    adjacency: MeshAdjacency = field(init=False, repr=False)

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
        region = region.astype(np.int64)
        a, b, c = region[faces[:, 0]], region[faces[:, 1]], region[faces[:, 2]]
        e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        for k, v in (("faces", faces), ("num_vertices", V), ("vertex_region", region), ("region_names", names),
                     ("reference_vertices", ref), ("face_region", np.where((b == c) & (a != b), b, a)),
                     ("edges", np.unique(np.sort(e, axis=1), axis=0)), ("adjacency", MeshAdjacency.of(faces, V))):  # fmt: skip
            object.__setattr__(self, k, v)

    @classmethod
    def for_model(cls, model=None, regions=None) -> "ContactTopology":
        """The topology of the anny ``model`` (default: the process-wide one): its body component
        (:func:`~dualhuman_builder.body.topology.collision_faces`), ``regions`` (default
        :func:`~dualhuman_builder.body.regions.load_regions`) and the rest pose."""
        from dualhuman_builder.body.model import get_body_model
        from dualhuman_builder.body.regions import load_regions
        from dualhuman_builder.body.topology import collision_faces

        model = model or get_body_model()
        faces = model.faces.cpu().numpy()
        regions = regions or load_regions(model)
        rest = model.rest().vertices[0].detach().cpu().numpy()
        return cls(faces[collision_faces(faces, model.num_vertices)], model.num_vertices, regions.vertex_region,
                   regions.names, rest)  # fmt: skip


_LOCAL = threading.local()


def _selectors(topo: ContactTopology) -> tuple[NearSelector, ...]:
    """This thread's :data:`SELECTORS` :class:`NearSelector` for ``topo`` (built on first use: ~10 ms
    each), so that the sequence loop can prepare the next frames with some while it finishes the
    last with another."""
    cache = getattr(_LOCAL, "selectors", None)
    if cache is None:
        cache = _LOCAL.selectors = weakref.WeakKeyDictionary()
    sel = cache.get(topo)
    if sel is None:
        sel = cache[topo] = tuple(NearSelector(topo.faces, topo.reference_vertices, face_groups=topo.face_region,
                                               adjacency=topo.adjacency) for _ in range(SELECTORS))  # fmt: skip
    return sel


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
def _direction(topo: ContactTopology, P: np.ndarray, Q: np.ndarray, near, band: float,
               counts: dict) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Signed distances ``(V,)`` of the vertices ``P`` to the surface ``Q`` (NaN farther than
    ``band``) and each one's closest face ``(V,)`` (index into ``topo.faces``, -1 where the
    distance is NaN), from :meth:`NearSelector.query`'s ``near``: its float64 pseudonormal
    distances where it has them and they lie outside, libigl against the sub-mesh of
    ``near.faces`` for the rest (possible contacts)."""
    import igl

    V = topo.num_vertices
    d = np.full(V, np.nan)
    face = np.full(V, -1, dtype=np.int64)
    if not len(near.idx):
        return d, face
    pseudo = np.ones(len(near.idx), dtype=bool)
    pseudo[near.exact] = False
    counts["pseudonormal_vertices"] += int(pseudo.sum())
    within = pseudo & (near.signed <= band)  # libigl's banded answer is NaN beyond the band
    d[near.idx[within]] = near.signed[within]
    face[near.idx[within]] = near.face[within]
    if not len(near.exact):
        return d, face
    keep, fidx = near.idx[near.exact], near.faces
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


def _box(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` of points ``X (N, 3)`` (numpy reduces ``(N, 3)`` along axis 0 ~20x slower than
    its ``(3, N)`` copy along axis 1)."""
    T = np.ascontiguousarray(X.T)
    return T.min(axis=1), T.max(axis=1)


def _as_frame(topo: ContactTopology, verts_a, verts_b) -> tuple[np.ndarray, np.ndarray]:
    A = np.ascontiguousarray(verts_a, dtype=np.float64)
    B = np.ascontiguousarray(verts_b, dtype=np.float64)
    V = topo.num_vertices
    for name, X in (("verts_a", A), ("verts_b", B)):
        if X.shape != (V, 3):
            raise ValueError(f"{name} must have shape ({V}, 3), got {X.shape}")
        if not np.isfinite(X).all():
            raise ValueError(f"{name} holds NaN or infinite coordinates")
    return A, B


def _flood_deep(topo: ContactTopology, P: np.ndarray, d: np.ndarray, band: float) -> int:
    """Set ``d`` to -inf on vertices more than ``band`` inside (see the module docstring);
    returns how many."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    e = topo.edges
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
                  counts: dict | None = None, threshold_m: float = DEFAULT_THRESHOLD_M) -> tuple[np.ndarray, np.ndarray] | None:  # fmt: skip
    """Both directions of one frame: ``(distances (2, V) float64, faces (2, V) int64)``, row 0 the
    vertices of A against B's surface, row 1 B against A's. Distances in metres, negative inside,
    NaN farther than ``band_m``, ``-inf`` inside deeper than ``band_m``; faces: the closest face
    (index into ``topology.faces``), -1 where the distance is not finite. None when the bodies'
    boxes are farther apart than ``band_m`` (no query made). Vertices that may lie below
    ``threshold_m`` or inside are answered by libigl (see the module docstring). ``counts``
    (optional) accumulates ``queried_vertices``, ``queried_faces`` (those libigl was given),
    ``pseudonormal_vertices`` and ``deep_vertices``."""
    A, B = _as_frame(topology, verts_a, verts_b)
    counts = counts if counts is not None else {}
    for k in COUNT_KEYS:
        counts.setdefault(k, 0)
    near = _prepare(A, B, band_m, threshold_m, _selectors(topology)[0])
    return None if near is None else _complete(topology, A, B, near, band_m, counts)


def _prepare(A: np.ndarray, B: np.ndarray, band: float, threshold: float, selector: NearSelector):
    """The part of a frame that runs in helper threads, mostly outside the GIL: None when the
    bodies' boxes are farther apart than ``band``, else :meth:`NearSelector.query_pair`'s
    ``(near_a, near_b)``."""
    (lo_a, hi_a), (lo_b, hi_b) = _box(A), _box(B)
    if np.any(lo_a > hi_b + band) or np.any(lo_b > hi_a + band):
        return None  # whole bodies (all vertices) farther apart than the band
    return selector.query_pair(A, B, band, threshold)


def _complete(topo: ContactTopology, A: np.ndarray, B: np.ndarray, near, band: float, counts: dict):
    """The rest of a frame from :func:`_prepare`'s ``near`` (libigl, which holds the GIL, and
    the flood fill): :func:`contact_frame`'s result."""
    near_a, near_b = near
    d_a, f_a = _direction(topo, A, B, near_a, band, counts)
    d_b, f_b = _direction(topo, B, A, near_b, band, counts)
    counts["deep_vertices"] += _flood_deep(topo, A, d_a, band) + _flood_deep(topo, B, d_b, band)
    return np.stack([d_a, d_b]), np.stack([f_a, f_b])


def _frame_result(topo: ContactTopology, frame, threshold: float):
    """One frame as the sequence loop stores it: ``(labels (2, V), distances (2, V) float16,
    region pairs)`` from :func:`contact_frame`'s ``frame``."""
    (d_a, d_b), (f_a, f_b) = frame
    labels = np.stack([d_a < threshold, d_b < threshold])  # NaN compares False, -inf True
    return labels, np.stack([d_a, d_b]).astype(np.float16), _frame_pairs(topo, d_a, f_a, d_b, f_b, threshold)


def _compute_frames(topo: ContactTopology, verts_a, verts_b, frames, threshold: float, band: float, counts: dict,
                    on_done: Callable[[], None] | None = None):  # fmt: skip
    """Yields ``(t, result)`` for each index ``t`` of ``frames`` in order: ``result`` is
    :func:`_frame_result`'s tuple, or None when the bodies are farther apart than ``band``.
    ``counts`` accumulates the query counts; ``on_done()`` after each frame.

    A pipeline: two helper threads run the narrow phases of frames ``t + 1`` and ``t + 2``
    (:func:`_prepare`, warp kernels, outside the GIL) while this thread finishes frame ``t``
    (:func:`_complete`: libigl, which holds the GIL, and numpy), each frame on one of
    :data:`SELECTORS` selectors in turn. On the hug window of ``benchmarks/bench_contacts.py``
    (2 CPUs), timed with a script outside the repo: ~65 frame pairs/s with one frame ahead, ~70
    with two, ~69 with three (a shorter thread switch interval than Python's 5 ms did not help).
    """
    from concurrent.futures import ThreadPoolExecutor

    sels = _selectors(topo)
    frames = [int(t) for t in frames]
    ahead = len(sels) - 1  # frames prepared while this one is finished

    def prepare(i: int):
        A, B = _as_frame(topo, verts_a[frames[i]], verts_b[frames[i]])
        return A, B, _prepare(A, B, band, threshold, sels[i % len(sels)])

    if not frames:
        return
    with ThreadPoolExecutor(max_workers=ahead, thread_name_prefix="contacts-prepare") as pool:
        jobs = collections.deque(pool.submit(prepare, i) for i in range(min(ahead, len(frames))))
        for i, t in enumerate(frames):
            A, B, near = jobs.popleft().result()
            if i + ahead < len(frames):
                jobs.append(pool.submit(prepare, i + ahead))  # a selector no frame in flight uses
            frame = None if near is None else _complete(topo, A, B, near, band, counts)
            result = None if frame is None else _frame_result(topo, frame, threshold)
            if on_done is not None:
                on_done()
            yield t, result


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
                           progress: Callable[[str], None] | None = None, workers: int | None = None) -> ContactResult:  # fmt: skip
    """Contacts between two bodies given their vertices ``verts_a``, ``verts_b`` ``(T, V, 3)``
    (world metres, any float dtype) on the mesh ``topology`` (see :meth:`ContactTopology.for_model`).

    ``threshold_m``: contact distance (> 0); ``band_m`` (>= threshold): distances are computed
    within it; ``merge_gap``: events separated by at most this many frames are merged;
    ``nan_policy``: ``"skip"`` (frames with any non-finite vertex are left out, counted in
    ``stats["skipped_nan_frames"]``, with ``valid`` False) or ``"raise"`` (ValueError naming the
    first such frame, before any work). ``progress(str)`` is called about every 10 % of frames.
    ``workers``: processes to spread the frames over (:mod:`~dualhuman_builder.contacts.workers`;
    1: all in this process; default: one per two CPUs, up to 8, when each gets at least 48 frames).
    The result does not depend on it.
    """
    topo = topology
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1):
        raise ValueError(f"workers must be a whole number >= 1 (or None for automatic), got {workers!r}")
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
    counts = dict.fromkeys(COUNT_KEYS, 0)
    per_frame: list[dict] = [{} for _ in range(T)]
    far_frames = done = 0
    frames = np.flatnonzero(finite)
    step = max(1, math.ceil(len(frames) / 10))

    def tick():
        nonlocal done
        done += 1
        if progress is not None and (done % step == 0 or done == len(frames)):
            progress(f"contacts: {done}/{len(frames)} frames ({100 * done // len(frames)} %)")

    from dualhuman_builder.contacts.workers import auto_workers, run_in_workers

    n_workers = auto_workers(len(frames)) if workers is None else min(int(workers), max(1, len(frames)))
    if n_workers > 1:
        if progress is not None:
            progress(f"contacts: {len(frames)} frames in {n_workers} worker processes")
        results = run_in_workers(topo, verts_a, verts_b, frames, threshold, band, n_workers, counts, on_done=tick)
    else:
        results = _compute_frames(topo, verts_a, verts_b, frames, threshold, band, counts, on_done=tick)
    for t, result in results:
        if result is None:
            far_frames += 1
        else:
            labels[:, t], distances[:, t], per_frame[t] = result
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
        "pseudonormal_vertices": counts["pseudonormal_vertices"],
        "deep_vertices": counts["deep_vertices"],
        "seconds": round(seconds, 4),
        "frame_pairs_per_s": round(computed / seconds, 2) if seconds > 0 else None,
        "threshold_m": threshold,
        "band_m": band,
        "merge_gap": int(merge_gap),
        "fps": fps,
        "workers": n_workers,
    }
    events = _events(per_frame, topo.region_names, int(merge_gap), fps)
    return ContactResult(labels, distances, frame_contact, finite, events, stats, topo.region_names, tuple(actors))


def compute_contacts(seq, threshold_m: float = DEFAULT_THRESHOLD_M, band_m: float = DEFAULT_BAND_M,
                     progress: Callable[[str], None] | None = None, merge_gap: int = DEFAULT_MERGE_GAP,
                     nan_policy: str = "skip", topology: ContactTopology | None = None,
                     workers: int | None = None) -> ContactResult:  # fmt: skip
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
                                  nan_policy=nan_policy, progress=progress, workers=workers)  # fmt: skip


@functools.lru_cache(maxsize=1)
def default_topology() -> ContactTopology:
    """:meth:`ContactTopology.for_model` of the process-wide anny model, built once (~0.5 s)."""
    return ContactTopology.for_model()

"""The per-frame contact kernel: signed distances of two body meshes' vertices, both directions.

For one frame: the pseudonormal signed distance (metres, negative inside, world frame of
:mod:`dualhuman_builder.conventions`) of each vertex of A to B's closed surface and of B to A's,
within a band ``band``, equal to one ``igl.signed_distance`` call of every vertex against the
whole mesh (labels exactly; distances to 1e-9 m below the threshold, 1e-7 m above it: checked by
``tests/contacts/test_contacts.py``). Design and measurements: ``docs/design/contacts.md``,
``docs/decisions/0021-contacts-libigl-on-possible-contacts.md``.

1. **Broad phase.** A frame whose whole-body boxes are farther apart than the band is skipped with
   no query; otherwise the narrow phase sees only vertices near the other body's region boxes.
2. **Narrow phase** (:class:`~dualhuman_builder.geometry.narrow.NearSelector`): a warp BVH per
   body, built at the topology's reference pose and refit per frame, finds each vertex's closest
   face in float32. Possible contacts (below the threshold plus a 10 um slack) and vertices found
   inside go to libigl against the sub-mesh of faces that may be closest to them, which holds every
   face the pseudonormal sign reads, so libigl answers as on the whole mesh. The other vertices in
   the band keep the kernel's float64 pseudonormal distance on the face the BVH found
   (:mod:`dualhuman_builder.geometry.pseudonormal`'s rule).
3. **Deep penetration.** libigl answers NaN beyond the band on either side; vertices more than the
   band inside are found by a flood fill over the query body's edges (from an inside vertex within
   the band across an edge shorter than the band, then across out-of-band vertices joined by edges
   shorter than twice the band: the signed distance is 1-Lipschitz) and get ``-inf``. A deep vertex
   reachable only across a longer edge (a few on anny's thighs and shins) stays NaN.

:func:`compute_frames` runs a sequence of frames as a pipeline: helper threads run the next
frames' narrow phases (warp, outside the GIL) while the calling thread runs libigl (which holds
the GIL) on the current one. ``counts`` dicts accumulate the :data:`COUNT_KEYS`.
"""

from __future__ import annotations

import collections
import threading
import weakref
from typing import Callable

import numpy as np

from dualhuman_builder.contacts.events import frame_pairs
from dualhuman_builder.contacts.topology import ContactTopology
from dualhuman_builder.geometry.narrow import NearSelector

#: Contact distance (m): a vertex nearer than this to the other body's surface, or inside it, is in contact.
DEFAULT_THRESHOLD_M = 0.02
#: Band (m, at least the threshold) within which signed distances are computed; NaN beyond.
DEFAULT_BAND_M = 0.05
#: Narrow-phase selectors per thread, i.e. frames in flight in :func:`compute_frames`: the one
#: libigl is finishing and two prepared ahead by helper threads.
SELECTORS = 3
#: Query counters of a ``counts`` dict: vertices and faces given to libigl, vertices answered by
#: the pseudonormal kernel, vertices found deeper than the band.
COUNT_KEYS = ("queried_vertices", "queried_faces", "pseudonormal_vertices", "deep_vertices")

_LOCAL = threading.local()


def _selectors(topo: ContactTopology) -> tuple[NearSelector, ...]:
    """This thread's :data:`SELECTORS` :class:`NearSelector` for ``topo``, built on first use and
    kept while ``topo`` lives: the sequence loop prepares the next frames on some while it
    finishes the current one on another."""
    cache = getattr(_LOCAL, "selectors", None)
    if cache is None:
        cache = _LOCAL.selectors = weakref.WeakKeyDictionary()
    sel = cache.get(topo)
    if sel is None:
        sel = cache[topo] = tuple(NearSelector(topo.faces, topo.reference_vertices, face_groups=topo.face_region,
                                               adjacency=topo.adjacency) for _ in range(SELECTORS))  # fmt: skip
    return sel


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
    """``(lo, hi)`` ``(3,)`` of points ``X (N, 3)``, reduced along the contiguous axis of a
    ``(3, N)`` copy (much faster in numpy than along axis 0 of ``(N, 3)``)."""
    T = np.ascontiguousarray(X.T)
    return T.min(axis=1), T.max(axis=1)


def _as_frame(topo: ContactTopology, verts_a, verts_b) -> tuple[np.ndarray, np.ndarray]:
    """Both bodies' vertices ``(V, 3)`` as contiguous float64; ValueError on another shape or on
    non-finite coordinates."""
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
    """One frame as the sequence loop stores it: ``(labels (2, V) bool, distances (2, V) float16,
    region pairs)`` from :func:`contact_frame`'s ``frame``."""
    (d_a, d_b), (f_a, f_b) = frame
    labels = np.stack([d_a < threshold, d_b < threshold])  # NaN compares False, -inf True
    return labels, np.stack([d_a, d_b]).astype(np.float16), frame_pairs(topo, d_a, f_a, d_b, f_b, threshold)


def compute_frames(topo: ContactTopology, verts_a, verts_b, frames, threshold: float, band: float, counts: dict,
                   on_done: Callable[[], None] | None = None):  # fmt: skip
    """Yields ``(t, result)`` for each index ``t`` of ``frames`` (into ``verts_a``/``verts_b``
    ``(T, V, 3)`` m), in order: ``result`` is ``(labels (2, V) bool, distances (2, V) float16 m,
    region pairs)`` (:func:`~dualhuman_builder.contacts.events.frame_pairs`), or None when the
    bodies are farther apart than ``band``. ``counts`` accumulates the :data:`COUNT_KEYS`;
    ``on_done()`` is called after each frame.

    A pipeline: two helper threads run the narrow phases of frames ``t + 1`` and ``t + 2``
    (:func:`_prepare`: warp kernels, outside the GIL) while this thread finishes frame ``t``
    (:func:`_complete`: libigl, which holds the GIL, and numpy), each frame on one of the
    :data:`SELECTORS` selectors in turn.
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


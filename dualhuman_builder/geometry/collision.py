"""Differentiable collision term between two bodies, after Jiang et al. (CVPR 2020), made exact.

Jiang et al. ("Coherent reconstruction of multiple humans") sample, for each person, a 32^3 grid
of the distance inside the body (0 outside) at the other person's vertices and sum a robustified
depth. Here the same quantity -- for every vertex of one body, how deep it lies inside the other
-- is computed exactly on the mesh, both ways, and its gradient pushes both bodies. Vertices are
``(B, V, 3)`` torch tensors in the Y-up world frame, metres; ``B`` frames are independent.

``depth(p)``
    distance from surface vertex ``p`` of one body to the closest point ``c`` on the other
    body's surface when ``p`` is inside it, else 0 (metres). In torch it is recomputed as
    ``depth = (c - p) . n`` with ``c = sum_k w_k x_k`` (barycentric weights ``w`` of the closest
    triangle ``x_0 x_1 x_2``, from the query) and ``n = (c - p) / |c - p|`` held fixed: the exact
    gradient of the distance, ``-n`` on ``p`` (along the surface normal at ``c``) and ``+w_k n``
    on the triangle's three vertices, so the vertex is pushed out and the surface pushed back.

Loss per frame ``(B,)``
    ``sum_{p penetrating, both bodies} rho(depth_p) / (2 V)`` -- the mean over both bodies' ``2V``
    vertices, so it does not grow with mesh resolution -- plus the coincidence guard below.
    ``rho`` defaults to the pseudo-Huber ``sqrt(1 + (d/s)^2) - 1`` with ``s = robust_sigma_m``
    (1 cm): quadratic, ``d^2 / 2s^2``, for the shallow contacts that make most of a fit; linear,
    ``d / s``, for deep ones, whose push stays at ``1/s`` per vertex instead of vanishing.
    Geman-McClure (``rho="geman_mcclure"``, Jiang's) saturates: its slope falls as
    ``2 s^2 / d^3``, so a vertex 5 cm deep is pushed 40x less than one 6 mm deep and a gross
    overlap is never undone; ``"squared"`` (``(d/s)^2``) lets a few deep vertices outweigh every
    other term of the fit. Both are available.

Coincidence guard (Jiang's pitfall: the loss is 0 when both start at the same spot)
    Identical bodies have every vertex on the other's surface: all depths are 0. And no symmetric
    penetration measure can separate them -- at identical bodies its gradient with respect to a
    equals the one with respect to b. So when the bodies' centroids are closer than ``guard_m``
    (10 cm) the frame also pays ``guard_weight * (1 - |dc| / guard_m)`` (``dc`` = centroid of b
    minus centroid of a), whose gradient pushes them apart along ``dc`` (world +X when they
    coincide). The centroids are those of ``guard_vertices`` (default: every vertex). Whole-body
    centroids are a poor measure of "the same spot": arms wrapped round the partner pull them
    together, and in the simulated hug of seed 2 they come within 1.2 cm in 43 of 78 frames,
    where the guard then fought the data and the fit's collision passes swung the arms through
    the partner to move them apart. The fitter passes the torso's vertices
    (:func:`~dualhuman_builder.fit.skeleton.torso_vertices`), whose centroids coincide when the
    bodies do and stayed 24.6 cm or more apart in the 18 simulated scenes surveyed once (six types x
    seeds 1-3, 2026-11-23; the test checks hug seed 2 only).

Broad phase
    Frames whose axis-aligned boxes, grown by ``pad_m`` (default ``band_m``), do not overlap
    are inactive: loss exactly 0, zero gradient, no query. In an active frame only the surface
    vertices inside the other body's grown box are queried.

Inside/outside, and which sign to trust
    anny's mesh is watertight (``igl.is_edge_manifold`` true, no boundary loop, every edge shared
    by two faces, consistent outward winding) but has four closed components: the body (13,348
    vertices) and three small shells (two eyeballs, mouth interior) that sit partly outside the
    body surface (the eyeballs by up to 3.8 mm). Against the full mesh the pseudonormal sign is
    wrong near those shells (29 of 5,014 inside points of the hug frame flipped). The obstacle is
    therefore the body component only (:func:`~dualhuman_builder.body.topology.collision_faces`)
    and the query points are its vertices (eyes and mouth never count). On it the pseudonormal
    sign agrees with the generalised winding number on every point of the hug frame and of 15
    frames of the simulated hug scene pushed 3 cm into each other (0 of 605); it is exact for a
    closed surface that does not intersect itself. Where a posed body does (51 of 317 inside
    points disagree on bodies with 0.3 rad of random noise on every joint) only the winding
    number is right: ``sign="winding"`` uses it, 2-3x slower. Default: pseudonormal
    (``wp.mesh_query_point_sign_normal``).

Method ``"warp"`` (default): exact depths, banded query and sign flood fill
    One ``wp.Mesh`` per body and frame (a pool, refit per call). (1) Candidates are queried with
    ``max_dist = band_m``: near vertices get exact signed distances (~1 us each instead of 5-9).
    (2) If more than ``flood_min`` (1,500) are farther, their sign is propagated along the query
    body's edges: an edge ``(u, w)`` shorter than ``lb_u + lb_w`` (lower bounds of the distances
    to the other surface: the exact one near it, ``band_m`` or the distance to its box farther
    out) cannot cross that surface (the distance is 1-Lipschitz), so ``u`` and ``w`` are on the
    same side. Connected components of such edges take the sign of a known member; a component
    with none gets one full query. A component with members known on both sides (a pseudonormal
    sign gone wrong where the obstacle crosses itself) gets a full query per open member: before,
    it took whichever sign came last (on the fit benchmark's hug one frame read 18.8 mm deep where
    the winding number says 20.8; on a noise-posed pair 437 vertices were on the wrong side, 138
    now). Fewer far vertices get a full query each. (3) Far vertices found inside get a full
    query for their depth. Queries, and the flood fill's components (a union-find forest per
    problem, :meth:`CollisionTerm._flood`), run in warp CPU kernels split over ``threads`` threads.

Reuse across calls (``keys``)
    An optimiser evaluates the term many times on bodies that barely move. When the caller names
    its frames (``keys``, e.g. timeline indices), each (frame, direction) keeps the last call's
    sign and a lower bound ``lb`` of ``|distance|`` per query vertex, with the vertices it was
    computed on. On the next call with the same key the signed distance has changed by at most
    ``|dq| + max|do|`` (the query vertex's move plus the obstacle's largest vertex move: the
    distance is 1-Lipschitz, and a surface whose vertices move by at most ``D`` lies within ``D``
    of where it was), so where ``lb - |dq| - max|do| > 0`` the sign is unchanged: such vertices
    outside need no query, such vertices inside need only their depth. Where the pseudonormal sign
    is exact (a closed surface that does not cross itself) the answer is the same as without keys
    (tested through small and large moves). Where a posed body crosses itself (an arm pressed into
    its own torso) the pseudonormal sign is not well defined there, and a vertex keeps the sign
    it had before the crossing instead of a fresh, possibly wrong one: on the benchmark's hug a
    fresh call reported a vertex 9.7 cm inside that the winding number puts 9.7 cm outside, the
    keyed call had it outside. On a 90-frame hug fit the term's time fell from 87 s to 33 s
    (queries 20.7 s -> 2.7 s; the rest is per-vertex bookkeeping in numpy and mesh refits).
    Stale entries are only less useful, never wrong; ``max_memo`` bounds them (oldest dropped),
    ``clear_memo()`` frees them. With ``parts`` (``(V,)`` ints; the fitter's: each hand's fingers, and
    the rest, :attr:`~dualhuman_builder.fit.skeleton.BodyRig.opening_groups`) the bound is taken per
    part of the obstacle: each part's faces lie within its own largest move of where they were, and
    within the box of its face corners old and new, so a vertex keeps its sign where, for every part,
    ``lb - |dq|`` less the part's move, or the distance to its box less ``|dq|``, is positive
    (:meth:`CollisionTerm._prior`). The fitter's hands' pass moves the fingers alone: with them as
    parts (until 2026-11-27 a special case, "move groups") the check after it reused 1.20 of 1.23
    million candidates' signs instead of 0.65 million on the fit benchmark's hug, the flood fill's
    vertices 500,000 -> 3,200 (same answers; 2026-11-26). The body's 23 segments as parts as well
    kept 99.2 % of all remembered signs instead of 88.4 % in a 0.25-minute hug's checks, but few more
    of the candidates', and cost more than they saved (2026-11-27, scripts outside the repo). The
    bound is computed by three warp kernels (:func:`_moves`, :func:`_part_moves`, :func:`_kept_signs`).

Held contacts (:meth:`CollisionTerm.linearise`, :meth:`CollisionTerm.linear_loss`)
    Locate the contacts once (plus the vertices outside within a margin) and evaluate the term many
    times on their positions only, each depth ``(c - p) . m`` against the plane held at its closest
    point: see :class:`Linearised`. The fitter's passes use it; the exact call above is its fallback.

Method ``"igl"``: ``igl.signed_distance`` (pseudonormal) on the candidates with
    ``lower_bound=-inf, upper_bound=band_m``: exact, but libigl rebuilds its AABB tree per call.

Method ``"grid"``: Jiang's formulation. Per body and active frame a ``grid_res^3`` grid of the
    inside distance over the body's box grown by 20 % (filled by warp queries), sampled at the
    other body's vertices with ``torch.nn.functional.grid_sample`` (trilinear). The grid is a
    constant: each direction pushes only the querying body's vertices; cells are 3-6 cm.

Measured (``benchmarks/bench_collision.py``; 2-core x86 CPU, torch 1 thread; anny average body,
rest A-pose, body b turned 180 deg about +Y; "hug" b 0.15 m in front of a, feet interleaved,
91 mm deepest, ~5,000 vertices inside each way; "back 3cm"/"thin" back to back, 30 / 3 mm
deepest; "far" 2 m apart; ms per frame pair for ``penetration()``, both directions, median of
7; errors on all four scenes against ``igl.signed_distance`` with the winding-number sign; missed
= inside by > 0.1 mm but reported 0, false = outside but reported > 0.1 mm)::

    method                                      hug   back 3cm  thin   far   max err   missed  false
    warp, band 1 cm, flood if > 1500 (default)   90     10.1     8.7   1.0   < 1 um       0      0
    warp, band 1 cm, always flood fill           90     14.0    11.6   1.0   < 1 um       0      0
    warp, no band (one full query each)         118      9.0     7.8   0.8   < 1 um       0      0
    warp, band 0.5 cm (flood if > 1500)         108     10.2     8.9   1.0   < 1 um       0      0
    warp, band 2 cm (flood if > 1500)            91     11.3     9.2   1.0   < 1 um       0      0
    warp, winding-number sign, band 1 cm        221     32.1    26.9   0.9   < 1 um       0      0
    igl.signed_distance, band 1 cm              320    119.9   120.9   0.9   < 1 um       0      0
    grid 32^3 + grid_sample (Jiang)             367    376.0   374.7   0.8   25.8 mm     16   2628

With gradients (loss + backward), default: hug 98 ms, back 3cm 13 ms, thin 12 ms; batches of 16
frames: 7.0 ms per "back 3cm" frame, 0.6 ms per "far" frame. The grid costs the most (2 x 32,768
fill queries per frame) and is the least accurate (a 3 mm penetration reads as 4 mm, 60
vertices instead of 8); libigl pays its tree build; the banded warp query with the flood fill is
exact and fastest on deep overlaps, and within 10 % of plain full queries on shallow ones.

Queries always run on the CPU (warp CPU kernels, the flood fill too): CUDA tensors are
copied to the CPU for the query (``V x 3`` floats per body and frame) and the differentiable
assembly runs on the tensors' own device. A :class:`CollisionTerm` serialises its calls (lock).
"""

from __future__ import annotations

import dataclasses
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch
import warp as wp

from dualhuman_builder.body.topology import collision_faces

METHODS = ("warp", "igl", "grid")
RHOS = ("pseudo_huber", "geman_mcclure", "squared")

# queries per kernel launch below which splitting across threads does not pay
_MIN_CHUNK = 2048

_init_lock = threading.Lock()
_initialised = False
_loaded: set = set()


def _init_warp() -> None:
    global _initialised
    with _init_lock:
        if not _initialised:
            wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
            wp.config.quiet = True
            wp.init()
            _initialised = True


@wp.kernel
def _closest(
    meshes: wp.array(dtype=wp.uint64),
    which: wp.array(dtype=wp.int32),
    points: wp.array(dtype=wp.vec3),
    max_dist: wp.array(dtype=wp.float32),
    start: wp.int32,
    winding: wp.int32,
    sdist: wp.array(dtype=wp.float32),
    face: wp.array(dtype=wp.int32),
    bary: wp.array(dtype=wp.vec3),
):
    """Closest point of ``points[start + tid]`` on its mesh within ``max_dist``, with the
    pseudonormal sign, or the winding-number sign when ``winding`` is 1."""
    i = wp.tid() + start
    m = meshes[which[i]]
    p = points[i]
    if winding != 0:
        q = wp.mesh_query_point_sign_winding_number(m, p, max_dist[i], 2.0, 0.5)
    else:
        q = wp.mesh_query_point_sign_normal(m, p, max_dist[i])
    face[i] = -1
    if q.result:
        c = wp.mesh_eval_position(m, q.face, q.u, q.v)
        sdist[i] = q.sign * wp.length(p - c)
        face[i] = q.face
        bary[i] = wp.vec3(q.u, q.v, 1.0 - q.u - q.v)


def _cpu_view(x: np.ndarray, dtype=None) -> wp.array:
    """``x`` (C-contiguous) as a warp CPU array over the same memory, so a kernel may write into it
    (warp keeps ``x`` alive); ``dtype`` a warp type (``wp.vec3`` over a trailing axis of 3), by
    default ``x``'s own (float32, int32 or int8)."""
    dtype = dtype or {np.float32: wp.float32, np.int32: wp.int32, np.int8: wp.int8}[x.dtype.type]
    return wp.array(x, dtype=dtype, device="cpu", copy=False)


@wp.func
def _root(parent: wp.array2d(dtype=wp.int32), t: int, v: int) -> int:
    """The root of vertex ``v``'s tree in row ``t`` of the union-find forest ``parent``, halving
    the path on the way (each vertex visited then points to its grandparent)."""
    x = int(v)
    while parent[t, x] != x:
        g = parent[t, parent[t, x]]
        parent[t, x] = g
        x = g
    return x


@wp.kernel
def _flood_union(
    points: wp.array2d(dtype=wp.vec3),
    bound: wp.array2d(dtype=wp.float32),
    sgn: wp.array2d(dtype=wp.int8),
    rows: wp.array(dtype=wp.int32),
    e0: wp.array(dtype=wp.int32),
    e1: wp.array(dtype=wp.int32),
    start: wp.int32,
    parent: wp.array2d(dtype=wp.int32),
):
    """Problem ``rows[t]`` (``t = tid + start``): the connected components, as a union-find forest in
    ``parent[t]`` (vertex indices), of the query mesh's edges the sign flood fill may follow: those
    with an end of unknown sign (``sgn`` 0) whose ends' distance bounds add up to more than the edge
    (a margin for float32 rounding), so that it cannot cross the obstacle. A thread owns whole
    problems, so threads never write the same row."""
    t = wp.tid() + start
    r = rows[t]
    for v in range(points.shape[1]):
        parent[t, v] = v
    for k in range(e0.shape[0]):
        a = e0[k]
        b = e1[k]
        if sgn[r, a] == wp.int8(0) or sgn[r, b] == wp.int8(0):
            if bound[r, a] + bound[r, b] > wp.length(points[r, a] - points[r, b]) * (1.0 + 1.0e-4) + 1.0e-6:
                x = _root(parent, t, a)
                y = _root(parent, t, b)
                if x < y:
                    parent[t, y] = x
                elif y < x:
                    parent[t, x] = y


@wp.kernel
def _flood_signs(
    sgn: wp.array2d(dtype=wp.int8),
    rows: wp.array(dtype=wp.int32),
    start: wp.int32,
    parent: wp.array2d(dtype=wp.int32),
    flags: wp.array2d(dtype=wp.int32),
    code: wp.array2d(dtype=wp.int32),
):
    """Problem ``rows[t]``, after :func:`_flood_union`: each vertex of unknown sign whose component's
    known members agree takes their sign (written into ``sgn``); ``code[t]`` says what the others
    need: 2, members known on both sides (a conflict: the vertex needs a query of its own); 3, no
    known member and this is the component's first vertex (its representative, to be queried);
    ``-(4 + r)``, no known member and ``r`` is the representative. 0 for every other vertex.
    ``flags``: scratch, per root which signs its members have (1 outside, 2 inside), then the
    representative of a root without any. Launched again on a row it gives the same answer."""
    t = wp.tid() + start
    r = rows[t]
    n = sgn.shape[1]
    for v in range(n):
        flags[t, v] = 0
    for v in range(n):
        root = _root(parent, t, v)
        parent[t, v] = root
        s = sgn[r, v]
        if s > wp.int8(0):
            flags[t, root] = flags[t, root] | 1
        elif s < wp.int8(0):
            flags[t, root] = flags[t, root] | 2
    for v in range(n):
        c = int(0)
        if sgn[r, v] == wp.int8(0):
            root = parent[t, v]
            f = flags[t, root]
            if f == 1:
                sgn[r, v] = wp.int8(1)
            elif f == 2:
                sgn[r, v] = wp.int8(-1)
            elif f == 3:
                c = 2
            elif f == 0:
                flags[t, root] = 4 + v  # the first vertex of a component without a known member
                c = 3
            else:
                c = -f
        code[t, v] = c


@wp.kernel
def _moves(
    a: wp.array2d(dtype=wp.vec3),
    a0: wp.array2d(dtype=wp.vec3),
    b: wp.array2d(dtype=wp.vec3),
    b0: wp.array2d(dtype=wp.vec3),
    da: wp.array2d(dtype=wp.float32),
    db: wp.array2d(dtype=wp.float32),
):
    """Frame ``i``, vertex ``v`` (:meth:`CollisionTerm._prior`): how far each body's vertex moved (``da``, ``db``)."""
    i, v = wp.tid()
    da[i, v] = wp.length(a[i, v] - a0[i, v])
    db[i, v] = wp.length(b[i, v] - b0[i, v])


@wp.kernel
def _part_moves(
    a: wp.array2d(dtype=wp.vec3),
    a0: wp.array2d(dtype=wp.vec3),
    b: wp.array2d(dtype=wp.vec3),
    b0: wp.array2d(dtype=wp.vec3),
    da: wp.array2d(dtype=wp.float32),
    db: wp.array2d(dtype=wp.float32),
    vert: wp.array(dtype=wp.int32),
    part: wp.array(dtype=wp.int32),
    start: wp.int32,
    most: wp.array3d(dtype=wp.float32),
    lo: wp.array3d(dtype=wp.vec3),
    hi: wp.array3d(dtype=wp.vec3),
):
    """Frame ``i`` (``tid + start``), pair ``k``: vertex ``vert[k]``, a corner of a face of the obstacle's
    part ``part[k]`` (:meth:`CollisionTerm._prior`). Per frame, body (0: a, 1: b) and part, the largest
    move of its corners (``most[i, body, g]``) and the box of their old and new positions (``lo``,
    ``hi``). A thread owns whole frames (the maxima and minima are read-modify-writes)."""
    t, k = wp.tid()
    i = t + start
    v = vert[k]
    g = part[k]
    wp.atomic_max(most, i, 0, g, da[i, v])
    wp.atomic_max(most, i, 1, g, db[i, v])
    wp.atomic_min(lo, i, 0, g, wp.min(a[i, v], a0[i, v]))
    wp.atomic_max(hi, i, 0, g, wp.max(a[i, v], a0[i, v]))
    wp.atomic_min(lo, i, 1, g, wp.min(b[i, v], b0[i, v]))
    wp.atomic_max(hi, i, 1, g, wp.max(b[i, v], b0[i, v]))


@wp.kernel
def _kept_signs(
    a: wp.array2d(dtype=wp.vec3),
    b: wp.array2d(dtype=wp.vec3),
    da: wp.array2d(dtype=wp.float32),
    db: wp.array2d(dtype=wp.float32),
    most: wp.array3d(dtype=wp.float32),
    lo: wp.array3d(dtype=wp.vec3),
    hi: wp.array3d(dtype=wp.vec3),
    whole: wp.array2d(dtype=wp.float32),
    s0: wp.array2d(dtype=wp.int8),
    l0: wp.array2d(dtype=wp.float32),
    rows: wp.array(dtype=wp.int32),
    start: wp.int32,
    sgn: wp.array2d(dtype=wp.int8),
    lb: wp.array2d(dtype=wp.float32),
):
    """Remembered problem ``r = 2 i + side`` (``tid + start``), vertex ``v`` (:meth:`CollisionTerm._prior`):
    the query vertex (b's for side 0, against a; a's for side 1) keeps its sign ``s0`` and a bound ``lb``
    in row ``rows[r]`` where its remembered bound ``l0``, less its own move and the obstacle's largest
    (``whole[i, body]``), stays positive -- or else where, for every part ``g`` of the obstacle, ``l0``
    less its own move and the part's largest (``most[i, body, g]``), or its distance to the part's box
    (``lo``, ``hi``) less its own move, does."""
    t, v = wp.tid()
    r = t + start
    i = r // 2
    body = 0
    p = b[i, v]
    dq = db[i, v]
    if r - 2 * i == 1:
        body = 1
        p = a[i, v]
        dq = da[i, v]
    l = l0[r, v]
    eps = 1.0e-6 + 1.0e-6 * l  # float32 rounding of the stored bound
    left = l - (dq + whole[i, body])
    if left <= eps:  # the plain bound fails: per part, its own move or its box
        left = float(1.0e30)
        for g in range(most.shape[2]):
            x = l - (dq + most[i, body, g])
            if x <= eps:
                c = wp.min(wp.max(p, lo[i, body, g]), hi[i, body, g])
                x = wp.max(x, wp.length(p - c) - dq)
            left = wp.min(left, x)
    if left > eps:
        sgn[rows[r], v] = s0[r, v]
        lb[rows[r], v] = left


@dataclass
class CollisionResult:
    """Output of :meth:`CollisionTerm.__call__`, one entry per frame.

    ``loss (B,)`` differentiable w.r.t. both vertex sets; the rest carry no gradient:
    ``max_depth_m (B,)`` deepest vertex of either body inside the other (metres, 0 if none),
    ``penetrating (B,)`` int64 count of such vertices (depth > ``eps_m``), ``share (B,)`` =
    ``penetrating / (2 V)``, ``active (B,)`` bool, frames that passed the broad phase.
    """

    loss: torch.Tensor
    max_depth_m: torch.Tensor
    penetrating: torch.Tensor
    share: torch.Tensor
    active: torch.Tensor


@dataclass
class _Contacts:
    """Penetrating vertices of one call, concatenated over (frame, direction).

    ``frame (M,)`` index into the batch, ``side (M,)`` 0 = a vertex of b inside a, 1 = a vertex
    of a inside b, ``vert (M,)`` query vertex, ``depth (M,)`` metres (> 0), ``face (M,)`` row of
    the obstacle faces, ``bary (M, 3)`` barycentric weights of the closest point.
    """

    frame: np.ndarray
    side: np.ndarray
    vert: np.ndarray
    depth: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    #: the index tensors :meth:`CollisionTerm._assemble` builds from the above, kept for the next
    #: evaluation of the same contacts (a held pass evaluates them a dozen times)
    assembly: tuple | None = None


@dataclass
class Linearised:
    """The collision term located once, for many evaluations (:meth:`CollisionTerm.linearise`).

    An optimiser's line search evaluates the term a dozen times on bodies that move by
    millimetres. Locating the contacts is most of the cost (the full meshes skinned, the closest
    points queried); so it is done once, and each evaluation (:meth:`CollisionTerm.linear_loss`)
    re-reads only the contacts' positions: for each vertex ``p`` inside the other body or
    outside within the margin, ``depth = (c - p) . m`` with ``c = sum_k w_k x_k`` on the same
    triangle (barycentric weights held) and ``m`` the obstacle's outward normal there, held --
    the first-order (point-to-plane) expansion of the signed depth around where it was located,
    exact in value and gradient at that point. Vertices that cross in from farther than the
    margin are missed until the next :meth:`~CollisionTerm.linearise`, which the caller runs
    after each optimiser step.

    ``contacts``: the located vertices (``depth`` metres, negative outside); ``normals (M, 3)``
    float64 ``m``; ``guard (n,)`` int64 frames where the coincidence guard is on; ``B``, ``V``
    the batch; ``max_depth_m``, ``share``, ``penetrating``, ``active`` ``(B,)`` numpy: the
    diagnostics of :meth:`CollisionTerm.penetration` at the located bodies.
    """

    contacts: _Contacts
    normals: np.ndarray
    guard: torch.Tensor
    B: int
    V: int
    max_depth_m: np.ndarray
    share: np.ndarray
    penetrating: np.ndarray
    active: np.ndarray

    def subset(self, frames) -> "Linearised":
        """The same contacts restricted to the batch rows ``frames`` (distinct ints), renumbered
        ``0..len(frames)-1`` in that order."""
        frames = np.asarray(frames, np.int64).ravel()
        if len(np.unique(frames)) != len(frames) or (len(frames) and (frames.min() < 0 or frames.max() >= self.B)):
            raise ValueError(f"frames must be distinct rows of the batch of {self.B}")
        row = np.full(self.B, -1, np.int64)
        row[frames] = np.arange(len(frames))
        c = self.contacts
        keep = row[c.frame] >= 0
        sub = _Contacts(frame=row[c.frame[keep]], side=c.side[keep], vert=c.vert[keep], depth=c.depth[keep],
                        face=c.face[keep], bary=c.bary[keep])  # fmt: skip
        g = torch.as_tensor(row, device=self.guard.device)[self.guard]
        return Linearised(contacts=sub, normals=self.normals[keep], guard=g[g >= 0], B=len(frames), V=self.V,
                          max_depth_m=self.max_depth_m[frames], share=self.share[frames],
                          penetrating=self.penetrating[frames], active=self.active[frames])  # fmt: skip


class CollisionTerm:
    """Penetration loss and diagnostics between two bodies sharing one triangle topology.

    ``faces (F, 3)`` int array or tensor (anny's ``model.faces``); its largest component must be
    closed. ``method`` ``"warp"`` (default, exact), ``"igl"`` (exact, slower) or ``"grid"``
    (Jiang's voxel grid). ``robust_sigma_m`` the scale ``s`` of ``rho`` (metres); ``band_m`` the
    near-surface band of the first query (metres); ``pad_m`` growth of the broad-phase boxes
    (default ``band_m``); ``rho`` ``"pseudo_huber"``, ``"geman_mcclure"`` or ``"squared"``;
    ``sign`` ``"normal"`` (pseudonormal) or ``"winding"`` (generalised winding number, 2-3x
    slower); ``guard_m``/``guard_weight``/``guard_vertices`` the coincidence guard (the last:
    indices of the vertices whose centroids it compares, default all); ``eps_m`` depth above which a
    vertex counts as penetrating in the diagnostics; ``grid_res`` cells per axis of ``"grid"``;
    ``threads`` query threads (default: CPU count, at most 8); ``flood_min`` far candidates from
    which the sign flood fill replaces one full query each; ``max_memo`` frames kept for the reuse
    across calls that ``keys`` enables (~0.5 MB each for anny); ``bvh_points`` optional ``(V, 3)``
    points (e.g. a rest pose) every pooled mesh's BVH is built over before it is refit to a call's
    bodies: a refit keeps the tree a build made, and which of two equally close faces a query
    returns depends on that tree, so without them the answers depend (by rounding) on which frames
    first built each pooled mesh; with them only on each call's bodies; ``parts`` optional ``(V,)``
    ints, the parts of a body that move together (e.g. its segments), over which the reuse across
    calls bounds how far the obstacle moved part by part (default: one part; a face belongs to the
    highest-numbered part among its corners', so number last a part that moves alone). See the module
    docstring.
    """

    def __init__(
        self,
        faces,
        method: str = "warp",
        robust_sigma_m: float = 0.01,
        band_m: float = 0.01,
        *,
        rho: str = "pseudo_huber",
        sign: str = "normal",
        pad_m: float | None = None,
        guard_m: float = 0.1,
        guard_weight: float = 1.0,
        guard_vertices=None,
        eps_m: float = 1e-5,
        grid_res: int = 32,
        threads: int | None = None,
        flood_min: int = 1500,
        max_memo: int = 128,
        bvh_points=None,
        parts=None,
        seed_stride: int = 4,
    ):
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        if rho not in RHOS:
            raise ValueError(f"rho must be one of {RHOS}, got {rho!r}")
        if sign not in ("normal", "winding"):
            raise ValueError(f"sign must be 'normal' or 'winding', got {sign!r}")
        pad_m = band_m if pad_m is None else pad_m
        metres = (("robust_sigma_m", robust_sigma_m), ("band_m", band_m), ("pad_m", pad_m), ("guard_m", guard_m))
        for name, val in metres:
            if not (np.isfinite(val) and val > 0):
                raise ValueError(f"{name} must be a positive number of metres, got {val!r}")
        if not (np.isfinite(guard_weight) and guard_weight >= 0):
            raise ValueError(f"guard_weight must be >= 0, got {guard_weight!r}")
        if not (np.isfinite(eps_m) and eps_m >= 0):
            raise ValueError(f"eps_m must be >= 0, got {eps_m!r}")
        if int(flood_min) < 0:
            raise ValueError(f"flood_min must be >= 0, got {flood_min!r}")
        if int(max_memo) < 0:
            raise ValueError(f"max_memo must be >= 0, got {max_memo!r}")
        if int(grid_res) < 2:
            raise ValueError(f"grid_res must be >= 2, got {grid_res!r}")
        f = faces.detach().cpu().numpy() if isinstance(faces, torch.Tensor) else np.asarray(faces)
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise ValueError(f"faces must have shape (F, 3) with F > 0, got {f.shape}")
        if not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"faces must be integer vertex indices, got dtype {f.dtype}")
        if f.min() < 0:
            raise ValueError("faces contain negative vertex indices")
        self.faces = f.astype(np.int64)
        self.num_vertices_min = int(self.faces.max()) + 1
        self.method = method
        self.sigma = float(robust_sigma_m)
        self.band = float(band_m)
        self.pad = float(pad_m)
        self.rho_name = rho
        self.sign = sign
        self.guard_m = float(guard_m)
        self.guard_weight = float(guard_weight)
        gv = None if guard_vertices is None else np.unique(np.asarray(guard_vertices, dtype=np.int64).ravel())
        if gv is not None and (len(gv) == 0 or gv.min() < 0):
            raise ValueError("guard_vertices must be a non-empty list of vertex indices")
        #: (G,) int64 vertex indices whose centroids the coincidence guard compares; None: all
        self.guard_vertices = gv
        self._guard_idx = None if gv is None else torch.as_tensor(gv)  # moved to the vertices' device on use
        self.eps = float(eps_m)
        self.grid_res = int(grid_res)
        self.flood_min = int(flood_min)
        self.threads = max(1, int(threads) if threads else min(os.cpu_count() or 1, 8))
        # obstacle surface: the largest closed component (anny: the body without eyes and mouth)
        self.obstacle_faces = self.faces[collision_faces(self.faces, self.num_vertices_min)]
        e = np.sort(np.concatenate([self.obstacle_faces[:, [0, 1]], self.obstacle_faces[:, [1, 2]],
                                    self.obstacle_faces[:, [2, 0]]]), axis=1)  # fmt: skip
        _, counts = np.unique(e, axis=0, return_counts=True)
        if not np.all(counts == 2):
            raise ValueError(
                f"the obstacle surface (largest component of faces) is not closed: {int(np.sum(counts == 1))} "
                f"boundary and {int(np.sum(counts > 2))} non-manifold edges; inside/outside is undefined"
            )
        self.obstacle_vertices = np.unique(self.obstacle_faces)
        # query points: the vertices of that surface; its undirected edges carry the sign flood fill
        self.edges = np.unique(e, axis=0)
        self._edges_wp: tuple | None = None  # the edges' two columns as warp arrays (_flood)
        self._boxes: tuple | None = None  # the current call's bodies' boxes (_active_frames)
        self._surface_mask: np.ndarray | None = None
        bp = None if bvh_points is None else np.ascontiguousarray(np.asarray(bvh_points, dtype=np.float32))
        if bp is not None and (bp.ndim != 2 or bp.shape[1] != 3 or len(bp) < self.num_vertices_min or not np.isfinite(bp).all()):
            raise ValueError(f"bvh_points must be finite (V, 3) points with V >= {self.num_vertices_min}, got shape {bp.shape}")
        self._bvh_points = bp
        # the obstacle's parts (see _prior): each face belongs to the highest-numbered part among its corners'
        # (a part numbered above its neighbours, the fingers, takes the faces it shares with them: when it moves
        # alone they stay still); per part the corners of its faces, as (vertex, part) pairs
        if parts is None:
            labels = np.zeros(self.num_vertices_min, np.int64)
        else:
            labels = np.asarray(parts)
            if labels.ndim != 1 or len(labels) < self.num_vertices_min or not np.issubdtype(labels.dtype, np.integer):
                raise ValueError(f"parts must be (V,) integers with V >= {self.num_vertices_min}, got {labels.shape} {labels.dtype}")
        face_part = np.unique(labels[self.obstacle_faces].max(axis=1), return_inverse=True)[1].ravel()
        pairs = np.unique(np.stack([np.repeat(face_part, 3), self.obstacle_faces.ravel()], axis=1), axis=0)
        self._part_pairs = (np.ascontiguousarray(pairs[:, 1], np.int32), np.ascontiguousarray(pairs[:, 0], np.int32))
        self._parts_wp: tuple | None = None  # the same as warp arrays (made on first use)
        #: the obstacle's part count (:meth:`_prior`)
        self.num_parts = int(face_part.max()) + 1
        self._pool: list[wp.Mesh] = []
        self._pool_points: list[wp.array] = []
        self._executor: ThreadPoolExecutor | None = None
        self._lock = threading.Lock()
        self.max_memo = int(max_memo)
        if int(seed_stride) < 1 or int(seed_stride) & (int(seed_stride) - 1):
            raise ValueError(f"seed_stride must be a power of 2 (1: off), got {seed_stride!r}")
        #: frames of one call never seen before are found in levels, each from a neighbour's signs (:meth:`_levels`)
        self.seed_stride = int(seed_stride)
        #: frame key -> (a's vertices (V, 3), b's (V, 3), sign (2, V) int8, lb (2, V)), float32; row = side
        self._memo: dict = {}
        #: counts of the last exact query: candidates, near, far, representatives, full (empty: none)
        self.last_stats: dict = {}

    # ------------------------------------------------------------------------------------ public
    def __call__(self, verts_a, verts_b, keys=None, points=None) -> CollisionResult:
        """Loss and diagnostics for ``verts_a``, ``verts_b`` ``(B, V, 3)`` tensors (metres).
        ``keys``: optional ``B`` hashable names of the frames (e.g. timeline indices), which lets
        later calls on the same frames reuse this one's signs (see the module docstring).

        ``points``: optional ``points(body, frames, vertices) -> (M, 3)`` tensor, the positions of
        body ``body`` (0: a, 1: b) at the pairs ``frames (M,)``, ``vertices (M,)`` (int64 tensors),
        differentiable in whatever the caller optimises. Given it, ``verts_a``/``verts_b`` only
        locate the contacts (they may be detached) and the loss's gradient flows through
        ``points`` at the few vertices it reads (the penetrating ones and the corners of their
        closest triangles; all of a frame's only where the coincidence guard is on): the same loss
        and gradient without differentiating every vertex of every frame."""
        va, vb = self._check(verts_a, verts_b, need_tensor=True)
        keys = self._check_keys(keys, va.shape[0])
        B, V = va.shape[:2]
        dev, dtype = va.device, va.dtype
        if points is None:
            def points(body, f, v):
                return (va, vb)[body][f, v]

            # zero that keeps the graph (and a zero gradient) for frames without contact
            loss = (va.sum(dim=(1, 2)) + vb.sum(dim=(1, 2))) * 0.0
        else:
            if self.method == "grid":
                raise ValueError("points= needs an exact method ('warp' or 'igl'); the grid samples every vertex")
            loss = torch.zeros(B, device=dev, dtype=dtype)
        with self._lock:
            active, frames = self._active_frames(va.detach(), vb.detach())
            max_depth = torch.zeros(B, device=dev, dtype=dtype)
            count = torch.zeros(B, device=dev, dtype=torch.int64)
            if len(frames):
                if self.method == "grid":
                    pen_loss, depth_a, depth_b = self._grid_terms(va, vb, frames)
                    loss = loss + pen_loss
                    d = torch.cat([depth_a, depth_b], dim=1)
                else:
                    c = self._contacts(va.detach(), vb.detach(), frames, keys)
                    loss = loss + self._assemble(c, B, V, dev, dtype, points)
                    d = self._depth_maps(c, B, V, dev, dtype)
                    d = torch.cat(d, dim=1)
                max_depth = torch.where(d > self.eps, d, torch.zeros_like(d)).amax(dim=1)
                count = (d > self.eps).sum(dim=1)
                loss = loss + self._guard(va.detach(), vb.detach(), active, points)
        share = count.to(dtype) / (2 * V)
        return CollisionResult(loss=loss, max_depth_m=max_depth, penetrating=count, share=share, active=active)

    def penetration(self, verts_a, verts_b, keys=None) -> dict:
        """Depths without gradient, as numpy arrays, for evaluation and reports.

        ``verts_a``, ``verts_b``: ``(B, V, 3)`` (or ``(V, 3)``) tensors or arrays, metres;
        ``keys`` as for :meth:`__call__`.
        Returns ``max_depth_m (B,)``, ``share (B,)``, ``penetrating (B,)``, ``active (B,)``,
        ``depth_a (B, V)`` (how deep each vertex of a lies inside b; 0 outside) and
        ``depth_b (B, V)`` (b inside a), float64 metres.
        """
        va, vb = self._check(verts_a, verts_b, need_tensor=False)
        B, V = va.shape[:2]
        keys = self._check_keys(keys, B)
        with self._lock, torch.no_grad():
            active, frames = self._active_frames(va, vb)
            depth_a = torch.zeros(B, V, dtype=va.dtype, device=va.device)
            depth_b = torch.zeros_like(depth_a)
            if len(frames):
                if self.method == "grid":
                    _, depth_a, depth_b = self._grid_terms(va, vb, frames)
                else:
                    c = self._contacts(va, vb, frames, keys)
                    depth_a, depth_b = self._depth_maps(c, B, V, va.device, va.dtype)
        return self._penetration_dict(depth_a, depth_b, active)

    def _penetration_dict(self, depth_a: torch.Tensor, depth_b: torch.Tensor, active: torch.Tensor) -> dict:
        """:meth:`penetration`'s dict from the depth maps ``(B, V)`` (entries <= ``eps_m`` count as 0)."""
        da = depth_a.double().cpu().numpy()
        db = depth_b.double().cpu().numpy()
        both = np.concatenate([da, db], axis=1)
        pen = both > self.eps
        return {
            "max_depth_m": np.where(pen, both, 0.0).max(axis=1),
            "share": pen.sum(axis=1) / (2.0 * da.shape[1]),
            "penetrating": pen.sum(axis=1).astype(np.int64),
            "active": active.cpu().numpy(),
            "depth_a": np.where(da > self.eps, da, 0.0),
            "depth_b": np.where(db > self.eps, db, 0.0),
        }

    def linearise(self, verts_a, verts_b, keys=None, margin_m: float = 0.005) -> Linearised:
        """Locate the contacts of ``verts_a``, ``verts_b`` ``(B, V, 3)`` (tensors, metres; no
        gradient is taken) once, for :meth:`linear_loss`: every vertex of either body inside the
        other or outside within ``margin_m`` (0 < margin_m <= min(band_m, pad_m)) of it. ``keys``
        as for :meth:`__call__`. Exact methods only (``"warp"``, ``"igl"``). See :class:`Linearised`."""
        if self.method == "grid":
            raise ValueError("linearise needs an exact method ('warp' or 'igl'); the grid has no closest points")
        if not (np.isfinite(margin_m) and 0 < margin_m <= min(self.band, self.pad)):
            raise ValueError(f"margin_m must be in (0, min(band_m, pad_m)] = (0, {min(self.band, self.pad)}] m, got {margin_m!r}")
        va, vb = self._check(verts_a, verts_b, need_tensor=True)
        va, vb = va.detach(), vb.detach()
        B, V = va.shape[:2]
        keys = self._check_keys(keys, B)
        with self._lock, torch.no_grad():
            active, frames = self._active_frames(va, vb)
            if len(frames):
                c = self._contacts(va, vb, frames, keys, margin=float(margin_m))
            else:
                z = np.zeros(0, np.int64)
                c = _Contacts(frame=z, side=z, vert=z, depth=np.zeros(0), face=z, bary=np.zeros((0, 3)))
            guard = self._guard_frames(va, vb, active)
            diag = self._penetration_dict(*self._depth_maps(c, B, V, va.device, va.dtype), active)
        # the outward normal at each contact, as _assemble finds it for a vertex inside
        f, side = torch.as_tensor(c.frame), torch.as_tensor(c.side)
        A, Bv = va.cpu(), vb.cpu()  # read at the contacts only, then in float64
        tri = torch.as_tensor(self.obstacle_faces[c.face])
        q = torch.where((side == 0)[:, None], Bv[f, torch.as_tensor(c.vert)], A[f, torch.as_tensor(c.vert)]).double()
        x = torch.where((side == 0)[:, None, None], A[f[:, None], tri], Bv[f[:, None], tri]).double()
        diff = (torch.as_tensor(c.bary, dtype=torch.float64)[:, :, None] * x).sum(dim=1) - q
        normals = self._outward_normals(diff, x, inside=torch.as_tensor(np.asarray(c.depth) > 0)).numpy()
        return Linearised(contacts=c, normals=normals, guard=guard, B=B, V=V, max_depth_m=diag["max_depth_m"],
                          share=diag["share"], penetrating=diag["penetrating"], active=diag["active"])  # fmt: skip

    def linear_loss(self, lin: Linearised, points, device=None, dtype=torch.float32) -> torch.Tensor:
        """The loss ``(B,)`` of :meth:`__call__` with the contacts of ``lin`` held (see
        :class:`Linearised`): ``sum rho(relu((c - p) . m)) / (2 V)`` plus the coincidence guard on
        ``lin.guard``; ``points(body, frames, vertices) -> (M, 3)`` as for :meth:`__call__`, on
        ``device`` (default: the CPU)."""
        dev = torch.device("cpu") if device is None else torch.device(device)
        loss = self._assemble(lin.contacts, lin.B, lin.V, dev, dtype, points, normals=lin.normals)
        return loss + self._guard_loss(lin.guard, lin.B, lin.V, dev, dtype, points)

    def moving_only(self, lin: Linearised, moving: np.ndarray) -> Linearised:
        """The contacts of ``lin`` whose held depth changes when only the vertices ``moving`` (``(V,)``
        bool, the same in both bodies) move: their query vertex or a corner of their triangle is
        among them. The others' held depths are constant over such a move, so :meth:`linear_loss`
        on the answer differs from it on ``lin`` by a constant per frame: the same gradient, the same
        optimiser steps, fewer points to read. The coincidence guard is kept unless none of its
        vertices is ``moving``. (The fitter's hands' pass moves only the fingers: of a hug window's
        ~24,000 located contacts a few thousand touch them.)"""
        moving = np.asarray(moving, bool)
        if moving.shape != (lin.V,):
            raise ValueError(f"moving must be a ({lin.V},) bool mask, got shape {moving.shape}")
        c = lin.contacts
        keep = moving[c.vert] | moving[self.obstacle_faces[c.face]].any(axis=1)
        sub = _Contacts(frame=c.frame[keep], side=c.side[keep], vert=c.vert[keep], depth=c.depth[keep],
                        face=c.face[keep], bary=c.bary[keep])  # fmt: skip
        guard_moves = bool(moving.any()) if self._guard_idx is None else bool(moving[self._guard_idx.numpy()].any())
        guard = lin.guard if guard_moves else lin.guard[:0]
        return dataclasses.replace(lin, contacts=sub, normals=lin.normals[keep], guard=guard)

    def clear_memo(self) -> None:
        """Forget the signs kept for ``keys`` (see the module docstring)."""
        with self._lock:
            self._memo.clear()

    def rho(self, depth: torch.Tensor) -> torch.Tensor:
        """The robust penalty of depths (metres, >= 0), dimensionless."""
        x = depth / self.sigma
        if self.rho_name == "pseudo_huber":
            return torch.sqrt(1.0 + x * x) - 1.0
        if self.rho_name == "geman_mcclure":
            return x * x / (x * x + 1.0)
        return x * x

    # ------------------------------------------------------------------------------------ input
    def _check(self, verts_a, verts_b, need_tensor: bool) -> tuple[torch.Tensor, torch.Tensor]:
        out = []
        for name, v in (("verts_a", verts_a), ("verts_b", verts_b)):
            if not isinstance(v, torch.Tensor):
                if need_tensor:
                    raise ValueError(f"{name} must be a torch tensor (B, V, 3), got {type(v).__name__}")
                v = torch.as_tensor(np.asarray(v, dtype=np.float64))
            if not v.is_floating_point():
                raise ValueError(f"{name} must be floating point, got {v.dtype}")
            if v.dim() == 2 and not need_tensor:
                v = v[None]
            if v.dim() != 3 or v.shape[-1] != 3:
                raise ValueError(f"{name} must have shape (B, V, 3), got {tuple(v.shape)}")
            if v.shape[0] == 0:
                raise ValueError(f"{name} is empty: batch of 0 frames")
            if v.shape[1] < self.num_vertices_min:
                raise ValueError(f"{name} has {v.shape[1]} vertices but faces index up to {self.num_vertices_min - 1}")
            bad = ~torch.isfinite(v.detach().sum(dim=(1, 2), dtype=torch.float64))  # NaN and inf survive a sum
            if bool(bad.any()):
                frames = torch.nonzero(bad).flatten().tolist()[:10]
                raise ValueError(f"{name} contains NaN or infinite coordinates in frame(s) {frames}")
            out.append(v)
        if out[0].shape != out[1].shape:
            raise ValueError(f"verts_a {tuple(out[0].shape)} and verts_b {tuple(out[1].shape)} must have the same shape")
        if out[0].device != out[1].device or out[0].dtype != out[1].dtype:
            raise ValueError(f"verts_a ({out[0].device}, {out[0].dtype}) and verts_b ({out[1].device}, {out[1].dtype}) "
                             "must share device and dtype")  # fmt: skip
        return out[0], out[1]

    @staticmethod
    def _check_keys(keys, B: int) -> list | None:
        if keys is None:
            return None
        keys = keys.tolist() if isinstance(keys, (np.ndarray, torch.Tensor)) else list(keys)
        if len(keys) != B:
            raise ValueError(f"keys must name each of the {B} frames, got {len(keys)}")
        if len(set(keys)) != B:
            raise ValueError("keys must be distinct: two frames of one call cannot share a name")
        return keys

    # ------------------------------------------------------------------------------------ broad phase
    def _active_frames(self, va: torch.Tensor, vb: torch.Tensor) -> tuple[torch.Tensor, np.ndarray]:
        """A new call (``last_stats`` cleared): the broad phase's ``(B,)`` mask and its frames; the
        bodies' boxes are kept for :meth:`_contacts` (``_boxes``: ``(lo_a, hi_a, lo_b, hi_b)``, each
        ``(B, 3)`` float32 numpy, ungrown)."""
        self.last_stats = {}
        active, boxes = self._broad_phase(va, vb)
        self._boxes = tuple(np.asarray(b.detach().cpu().numpy(), np.float32) for b in boxes)
        return active, np.flatnonzero(active.cpu().numpy())

    def _broad_phase(self, va: torch.Tensor, vb: torch.Tensor) -> tuple[torch.Tensor, tuple]:
        """``(B,)`` bool: the boxes of a and b, grown by ``pad_m``, overlap; and the boxes ``(lo_a, hi_a,
        lo_b, hi_b)`` ``(B, 3)`` themselves, ungrown."""
        ta, tb = va.transpose(1, 2).contiguous(), vb.transpose(1, 2).contiguous()  # fast reductions
        boxes = ta.amin(dim=2), ta.amax(dim=2), tb.amin(dim=2), tb.amax(dim=2)
        lo_a, hi_a, lo_b, hi_b = boxes[0] - self.pad, boxes[1] + self.pad, boxes[2] - self.pad, boxes[3] + self.pad
        active = ((lo_a <= hi_b) & (lo_b <= hi_a)).all(dim=1)
        return active, boxes

    # ------------------------------------------------------------------------------------ warp plumbing
    def _meshes(self, points: np.ndarray, only: np.ndarray | None = None) -> np.ndarray:
        """Pooled meshes for the rows of ``points (M, V, 3)`` float32, refit to the rows ``only``
        (default: all); their ids ``(M,)``."""
        _init_warp()
        M, V = points.shape[:2]
        winding = self.sign == "winding"
        if self._pool and self._pool_points[0].shape[0] != V:
            self._pool, self._pool_points = [], []
        n0 = len(self._pool)
        if M > n0:  # new meshes, built at these rows' points, in threads (ctypes releases the GIL; a BVH
            # build was ~14 ms here: 96 took 1.34 s in one thread, 0.67 s in two, script outside the repo)
            idx = wp.array(self.obstacle_faces.astype(np.int32).ravel(), dtype=wp.int32, device="cpu")  # shared
            new: list = [None] * (M - n0)

            at = self._bvh_points if self._bvh_points is not None and len(self._bvh_points) == V else None

            def build(rows):
                for i in rows:
                    pts = wp.array(points[i] if at is None else at, dtype=wp.vec3, device="cpu")
                    new[i - n0] = (wp.Mesh(points=pts, indices=idx, support_winding_number=winding), pts)

            self._threaded(build, np.arange(n0, M), 4)
            self._pool += [m for m, _ in new]
            self._pool_points += [p for _, p in new]
        todo = np.arange(M) if only is None else np.asarray(only)

        def refit(rows):
            for i in rows:
                self._pool_points[i].assign(points[i])
                self._pool[i].refit()  # a ctypes call: releases the GIL, so threads refit in parallel

        self._threaded(refit, todo, 4)  # a refit is ~0.5 ms: four a thread outweigh handing them over
        return np.array([self._pool[i].id for i in range(M)], dtype=np.uint64)

    def _threaded(self, fn, items: np.ndarray, min_chunk: int) -> None:
        """``fn(chunk)`` over contiguous chunks of ``items``, at least ``min_chunk`` each, on up to
        ``threads`` threads (this one included): for ctypes calls into warp, which release the GIL."""
        n_chunks = max(1, min(self.threads, len(items) // max(min_chunk, 1)))
        chunks = [c for c in np.array_split(items, n_chunks) if len(c)]
        if len(chunks) <= 1:
            if len(items):
                fn(items)
            return
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=self.threads - 1)
        futures = [self._executor.submit(fn, c) for c in chunks[1:]]
        fn(chunks[0])  # in this thread, while the others run
        for fut in futures:
            fut.result()

    def _launch_threaded(self, kernel, n: int, min_chunk: int, launch) -> None:
        """``launch(start, count)`` -- one warp CPU launch of ``kernel`` over items ``start .. start +
        count - 1`` -- over ``n`` items in threads (:meth:`_threaded`). warp loads a kernel's module on
        its first launch, which two threads must not do at once: the first launch ever is one item,
        alone (its result is written again by the threaded launches)."""
        if n == 0:
            return
        if kernel.key not in _loaded:
            launch(0, 1)
            _loaded.add(kernel.key)
        self._threaded(lambda items: launch(int(items[0]), len(items)), np.arange(n), min_chunk)
        wp.synchronize_device("cpu")

    def _query(self, mesh_ids: np.ndarray, which: np.ndarray, points: np.ndarray, max_dist) -> tuple:
        """Closest points of ``points (N, 3)`` on meshes ``mesh_ids[which]`` within ``max_dist``.

        Returns ``sdist (N,)`` (negative inside), ``face (N,)`` (-1 where nothing lies within
        ``max_dist``) and ``bary (N, 3)``.
        """
        N = len(points)
        if N == 0:
            return np.zeros(0, np.float32), np.zeros(0, np.int32), np.zeros((0, 3), np.float32)
        md = np.broadcast_to(np.asarray(max_dist, np.float32), (N,))
        winding = 1 if self.sign == "winding" else 0
        arrs = [
            wp.array(mesh_ids, dtype=wp.uint64, device="cpu"),
            wp.array(which.astype(np.int32), dtype=wp.int32, device="cpu"),
            wp.array(np.ascontiguousarray(points, np.float32), dtype=wp.vec3, device="cpu"),
            wp.array(np.ascontiguousarray(md), dtype=wp.float32, device="cpu"),
        ]
        sd = wp.zeros(N, dtype=wp.float32, device="cpu")
        face = wp.zeros(N, dtype=wp.int32, device="cpu")
        bary = wp.zeros(N, dtype=wp.vec3, device="cpu")
        self._launch_threaded(_closest, N, _MIN_CHUNK, lambda s, k: wp.launch(
            _closest, dim=k, inputs=[*arrs, s, winding, sd, face, bary], device="cpu"))  # fmt: skip
        return sd.numpy().copy(), face.numpy().copy(), bary.numpy().copy()

    def _flood(self, points: np.ndarray, bound: np.ndarray, sgn: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """The sign flood fill of problems ``rows`` (``points (P, V, 3)``, distance lower bounds
        ``bound (P, V)``, signs ``sgn (P, V)`` int8 with 0 unknown, written in place): each vertex of
        unknown sign takes the sign its component along the edges that cannot cross the obstacle
        agrees on; returns per row of ``rows`` and vertex what the others need (:func:`_flood_signs`'s
        codes), ``(len(rows), V)`` int32.

        Two warp kernels, a union-find forest per problem (:func:`_flood_union`) and its roots'
        signs (:func:`_flood_signs`), each thread owning whole problems. Before (until 2026-11-26),
        a kernel marked the safe edges and scipy's ``connected_components`` ran over the graph of
        all ``(problem, vertex)`` pairs; a hug window's first check, captured and replayed (a script
        outside the repo), took 0.66 s that way and 0.43 s this way, with identical answers."""
        P, V = sgn.shape
        if sgn.dtype != np.int8 or not sgn.flags.c_contiguous:
            raise ValueError("sgn must be a C-contiguous int8 array (it is written in place)")
        if self._edges_wp is None:
            self._edges_wp = tuple(wp.array(np.ascontiguousarray(self.edges[:, i], np.int32), dtype=wp.int32, device="cpu")
                                   for i in (0, 1))  # fmt: skip
        n = len(rows)  # (sgn is viewed, not copied: the kernels write the agreed signs into it)
        arrs = [_cpu_view(np.ascontiguousarray(points, np.float32), wp.vec3), _cpu_view(np.ascontiguousarray(bound, np.float32)),
                _cpu_view(sgn), _cpu_view(np.ascontiguousarray(rows, np.int32))]  # fmt: skip
        parent = wp.empty((n, V), dtype=wp.int32, device="cpu")
        flags = wp.empty((n, V), dtype=wp.int32, device="cpu")
        code = wp.empty((n, V), dtype=wp.int32, device="cpu")
        self._launch_threaded(_flood_union, n, 1, lambda s, k: wp.launch(
            _flood_union, dim=k, inputs=[*arrs, *self._edges_wp, s, parent], device="cpu"))  # fmt: skip
        self._launch_threaded(_flood_signs, n, 1, lambda s, k: wp.launch(
            _flood_signs, dim=k, inputs=[arrs[2], arrs[3], s, parent, flags, code], device="cpu"))  # fmt: skip
        return code.numpy()

    # ------------------------------------------------------------------------------------ exact contacts
    def _contacts(self, va: torch.Tensor, vb: torch.Tensor, frames: np.ndarray, keys: list | None = None,
                  margin: float = 0.0) -> _Contacts:  # fmt: skip
        """Penetrating vertices of both bodies in the active ``frames`` (exact methods); with
        ``margin > 0`` (metres, at most ``band_m``) also those outside within ``margin`` of the
        other surface (their ``depth`` is negative: minus the distance)."""
        A = va[torch.as_tensor(frames, device=va.device)].detach().cpu().numpy().astype(np.float32)
        Bv = vb[torch.as_tensor(frames, device=vb.device)].detach().cpu().numpy().astype(np.float32)
        K, V = A.shape[:2]
        # problem p = 2k + side: side 0 queries b's vertices against a, side 1 a's against b
        Q = np.empty((2 * K, V, 3), np.float32)
        Q[0::2], Q[1::2] = Bv, A
        O = np.empty_like(Q)
        O[0::2], O[1::2] = A, Bv
        # (P, 3) boxes of the obstacles (of all their vertices: a box holding the surface is all a lower
        # bound needs; the broad phase's, in float32: rounding is monotonic, so these are the boxes of
        # O), and (P, V) each query vertex's distance to it, a lower bound of the distance to the
        # obstacle (torch: vectorised over these ~1e6-vertex arrays, zero-copy)
        la, ha, lb_, hb = (b[frames] for b in self._boxes)
        lo, hi = np.empty((2 * K, 3), np.float32), np.empty((2 * K, 3), np.float32)
        lo[0::2], lo[1::2], hi[0::2], hi[1::2] = la, lb_, ha, hb
        lo_t, hi_t = torch.from_numpy(lo), torch.from_numpy(hi)
        Qt = torch.from_numpy(Q)
        dbox = torch.linalg.vector_norm(Qt - torch.clamp(Qt, lo_t[:, None], hi_t[:, None]), dim=2).numpy()
        if self._surface_mask is None or len(self._surface_mask) != V:
            self._surface_mask = np.zeros(V, bool)
            self._surface_mask[self.obstacle_vertices] = True
        cand = (dbox <= self.pad) & self._surface_mask
        self.last_stats = {"candidates": int(cand.sum())}
        if self.method == "igl":
            prob, vert, depth, face, bary = self._igl_contacts(Q, O, cand, margin)
        elif keys is None or self.max_memo == 0:
            prob, vert, depth, face, bary, _, _ = self._warp_contacts(Q, O, cand, dbox, lo, hi, None, margin)
        else:
            fkeys = [keys[f] for f in frames]
            stats, out = {}, []
            for rows, src in self._levels(fkeys, V):  # each level's frames start from the signs of an earlier one's
                p = np.ravel([2 * rows, 2 * rows + 1], order="F")  # their problems, in order
                sub = [x if len(rows) == K else np.ascontiguousarray(x[i]) for x, i in ((A, rows), (Bv, rows), (Q, p), (O, p),
                                                                                        (cand, p), (dbox, p), (lo, p), (hi, p))]  # fmt: skip
                prior = self._prior([fkeys[k] for k in src], sub[0], sub[1])
                res = self._warp_contacts(*sub[2:], prior, margin)
                self._remember([fkeys[k] for k in rows], sub[0], sub[1], res[5], res[6])
                out.append((p[res[0]],) + res[1:5])
                for key, n in self.last_stats.items():
                    stats[key] = stats.get(key, 0) + n
            self.last_stats = stats
            prob, vert, depth, face, bary = (np.concatenate(x) for x in zip(*out))
        if self.method != "igl":  # one order however the signs were found (the loss sums in this order)
            order = np.argsort(prob * V + vert, kind="stable")
            prob, vert, depth, face, bary = prob[order], vert[order], depth[order], face[order], bary[order]
        return _Contacts(frame=frames[prob // 2], side=prob % 2, vert=vert, depth=depth, face=face, bary=bary)

    def _levels(self, fkeys: list, V: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """The rows of a call's frames ``fkeys`` in the order their signs are found, as ``(rows, src)``
        pairs of ``(n,)`` int arrays: ``src`` the rows whose remembered signs each starts from (see
        :meth:`_prior`; its own, or for a frame never seen, a neighbour's found just before).

        A frame never seen before costs a query for every vertex near the other body's box (~17 ms on
        a hug's frame pair, against ~6 for one whose signs are kept), though the frame beside it in
        the call is nearly the same bodies. So with ``seed_stride`` ``s`` (a power of 2) the unseen
        frames at rows ``0, s, 2s ...`` are found first, with the seen ones; then those at ``s/2,
        3s/2 ...`` from the row ``s/2`` before each, and so on down to the odd rows from the row
        before. The bound of :meth:`_prior` holds between any two bodies, so the answer is the same
        (the neighbour's move only decides how many signs it keeps)."""
        K = len(fkeys)
        rows = np.arange(K)
        seen = np.array([key in self._memo and self._memo[key][0].shape == (V, 3) for key in fkeys], bool)
        s = self.seed_stride
        if seen.all() or s <= 1 or K - seen.sum() < 2:
            return [(rows, rows)]
        # level of an unseen row: 0 at multiples of s, then one more for each halving of the step
        step = np.where(rows % s == 0, s, rows & -rows)
        levels = [(rows[seen | (step == s)], rows[seen | (step == s)])]
        h = s // 2
        while h >= 1:
            r = rows[~seen & (step == h)]
            if len(r):
                levels.append((r, r - h))
            h //= 2
        return levels

    # ------------------------------------------------------------------------------------ reuse across calls
    def _prior(self, fkeys: list, A: np.ndarray, Bv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signs ``(P, V)`` int8 (0: unknown) and their lower bounds ``(P, V)`` float32, problem
        ``p = 2k + side`` as in :meth:`_contacts`, that still hold after the move from the
        remembered bodies of frame ``fkeys[k]`` to ``A[k]``, ``Bv[k]`` ``(V, 3)``.

        Every obstacle face belongs to one part (``parts``; one part, the whole surface, without
        them), and lies, at the old and new positions and all between, within the part's largest
        move ``m_g`` of where it was and within the box of the part's face corners old and new. So
        a query vertex ``q`` that moved by ``|dq|``, at least ``lb`` from the obstacle before, stays
        farther than ``min_g max(lb - |dq| - m_g, dist(q, box_g) - |dq|)`` from it all along the
        move: where that is positive its sign holds (:func:`_kept_signs`; the plain bound ``lb -
        |dq| - max_g m_g`` first, the parts only where it fails)."""
        K, V = A.shape[:2]
        sgn = np.zeros((2 * K, V), np.int8)
        lb = np.zeros((2 * K, V), np.float32)
        have = [k for k, key in enumerate(fkeys) if key in self._memo and self._memo[key][0].shape == (V, 3)]
        if not have:
            return sgn, lb
        n = len(have)
        entries = [self._memo[fkeys[k]] for k in have]
        rows = np.ravel([[2 * k, 2 * k + 1] for k in have]).astype(np.int32)
        a0, b0 = (np.stack([e[i] for e in entries]) for i in (0, 1))
        s0 = np.concatenate([e[2] for e in entries])  # (2n, V), rows as in `rows`
        l0 = np.concatenate([e[3] for e in entries])
        A_now = A if n == len(A) else np.ascontiguousarray(A[have])
        B_now = Bv if n == len(Bv) else np.ascontiguousarray(Bv[have])
        if self._parts_wp is None:
            self._parts_wp = tuple(wp.array(x, dtype=wp.int32, device="cpu") for x in self._part_pairs)
        vert, part = self._parts_wp
        G = self.num_parts
        da, db = np.empty((n, V), np.float32), np.empty((n, V), np.float32)
        most = np.zeros((n, 2, G), np.float32)
        lo, hi = np.full((n, 2, G, 3), np.inf, np.float32), np.full((n, 2, G, 3), -np.inf, np.float32)
        # views without a copy: the kernels write into da, db, most, lo, hi, sgn and lb
        pos = [_cpu_view(x, wp.vec3) for x in (A_now, a0, B_now, b0)]
        wp.launch(_moves, dim=(n, V), device="cpu", inputs=pos, outputs=[_cpu_view(da), _cpu_view(db)])
        self._launch_threaded(_part_moves, n, 1, lambda s, k: wp.launch(
            _part_moves, dim=(k, vert.shape[0]), device="cpu", inputs=[*pos, _cpu_view(da), _cpu_view(db), vert, part, s],
            outputs=[_cpu_view(most), _cpu_view(lo, wp.vec3), _cpu_view(hi, wp.vec3)]))  # fmt: skip
        whole = np.ascontiguousarray(most.max(axis=2))
        arrs = [_cpu_view(A_now, wp.vec3), _cpu_view(B_now, wp.vec3), _cpu_view(da), _cpu_view(db), _cpu_view(most),
                _cpu_view(lo, wp.vec3), _cpu_view(hi, wp.vec3), _cpu_view(whole), _cpu_view(s0), _cpu_view(l0), _cpu_view(rows)]  # fmt: skip
        outs = [_cpu_view(sgn), _cpu_view(lb)]
        self._launch_threaded(_kept_signs, 2 * n, 8, lambda s, k: wp.launch(
            _kept_signs, dim=(k, V), inputs=[*arrs, s], outputs=outs, device="cpu"))  # fmt: skip
        return sgn, lb

    def _remember(self, fkeys: list, A: np.ndarray, Bv: np.ndarray, sgn: np.ndarray, lb: np.ndarray) -> None:
        for k, key in enumerate(fkeys):
            self._memo.pop(key, None)  # re-inserted last: the oldest go first
            self._memo[key] = (A[k].copy(), Bv[k].copy(), sgn[2 * k : 2 * k + 2].copy(), lb[2 * k : 2 * k + 2].copy())
        while len(self._memo) > self.max_memo:
            self._memo.pop(next(iter(self._memo)))

    def _warp_contacts(self, Q, O, cand, dbox, lo, hi, prior=None, margin: float = 0.0):
        """Penetrating vertices of the problems ``Q (P, V, 3)`` against ``O`` (and those outside
        within ``margin``), and per query vertex the sign ``(P, V)`` int8 and a lower bound
        ``(P, V)`` of the distance's magnitude. ``prior``: signs known to hold (:meth:`_prior`) or None."""
        P, V = Q.shape[:2]
        N = P * V
        Qf = Q.reshape(-1, 3)
        # sign: +1 outside, -1 inside, 0 unknown; lb: lower bound of the distance to the obstacle
        lb = dbox.ravel().astype(np.float32)
        query = cand.ravel()
        if prior is not None:
            psgn, plb = prior[0].ravel(), prior[1].ravel()
            pknown = psgn != 0
            sgn = np.where(pknown, psgn, np.int8(1))
            lb = np.where(pknown, np.maximum(lb, plb), lb)
            # known to be still outside (farther than the margin): nothing to compute
            query = query & ((psgn <= 0) | (plb < margin))
        else:
            pknown = np.zeros(N, bool)
            sgn = np.ones(N, np.int8)
        flat = np.flatnonzero(query)
        refit = np.zeros(P, bool)  # meshes moved to this call's vertices

        def meshes(idx):
            todo = np.flatnonzero((np.bincount(idx // V, minlength=P) > 0) & ~refit)
            refit[todo] = True
            return self._meshes(O, todo)

        # (1) banded query of the candidates
        ids = meshes(flat)
        sd, face, bary = self._query(ids, (flat // V).astype(np.int32), Qf[flat], self.band)
        near = face >= 0
        sgn[flat[near]] = np.where(sd[near] < 0, -1, 1)
        lb[flat[near]] = np.abs(sd[near])
        far = flat[~near]
        lb[far] = np.maximum(lb[far], self.band)
        open_ = far[~pknown[far]]  # far, sign not known from the last call
        sgn[open_] = 0
        res_idx, res_sd, res_face, res_bary = [flat[near]], [sd[near]], [face[near]], [bary[near]]
        n_rep = n_deep = n_conflict = 0
        big = (np.linalg.norm(hi - lo, axis=1) + 1.0).astype(np.float32)  # > any inside distance
        queried = np.zeros(N, bool)

        def full(idx):
            ids = meshes(idx)
            f_sd, f_face, f_bary = self._query(ids, (idx // V).astype(np.int32), Qf[idx], big[idx // V])
            res_idx.append(idx), res_sd.append(f_sd), res_face.append(f_face), res_bary.append(f_bary)
            sgn[idx] = np.where((f_face >= 0) & (f_sd < 0), -1, 1)
            lb[idx] = np.where(f_face >= 0, np.abs(f_sd), lb[idx])
            queried[idx] = True

        if 0 < len(open_) < self.flood_min:  # few: a full query each is cheaper than the flood fill
            full(open_)
        elif len(open_):
            # (2) sign flood fill along the query mesh's edges that cannot cross the obstacle
            rows = np.flatnonzero((sgn == 0).reshape(P, V).any(axis=1))  # problems with something to fill
            code = self._flood(Q, lb.reshape(P, V), sgn.reshape(P, V), rows)
            # a component with members known inside and others known outside cannot exist if every sign
            # were right: a pseudonormal sign went wrong where the obstacle crosses itself (an arm pressed
            # into the torso). Its open members get a query each, not the sign of whichever member came last.
            t, v = np.nonzero(code)
            c, at = code[t, v], rows[t] * V + v
            if (c == 2).any():
                full(at[c == 2])
                n_conflict = int((c == 2).sum())
            if (c == 3).any():  # a component with no known member: its first vertex's full query decides it
                full(at[c == 3])
                n_rep = int((c == 3).sum())
            follow = c <= -4  # the other members of such a component: their representative's sign
            sgn[at[follow]] = sgn[rows[t[follow]] * V + (-4 - c[follow])]
        # (3) full query for the depth of far vertices inside
        deep = far[(sgn[far] < 0) & ~queried[far]]
        if len(deep):
            full(deep)
        n_deep = int(queried[far].sum()) - n_rep - n_conflict
        self.last_stats = {"candidates": int(cand.sum()), "near": int(near.sum()), "far": int(len(far)),
                           "representatives": n_rep, "conflicted": n_conflict, "full": n_deep,
                           "reused": int((pknown & cand.ravel()).sum())}  # fmt: skip
        idx, sd_all = np.concatenate(res_idx), np.concatenate(res_sd)
        face_all, bary_all = np.concatenate(res_face), np.concatenate(res_bary)
        ins = (face_all >= 0) & (sd_all < margin)
        idx = idx[ins]
        return idx // V, idx % V, -sd_all[ins], face_all[ins], bary_all[ins], sgn.reshape(P, V), lb.reshape(P, V)

    def _igl_contacts(self, Q, O, cand, margin: float = 0.0):
        import igl

        P, V = Q.shape[:2]
        F = self.obstacle_faces
        out = [[], [], [], [], []]
        for p in range(P):
            vi = np.flatnonzero(cand[p])
            if not len(vi):
                continue
            Ov = O[p].astype(np.float64)
            S, fi, C, _ = igl.signed_distance(Q[p, vi].astype(np.float64), Ov, F,
                                               igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL, -np.inf, self.band)  # fmt: skip
            ins = np.isfinite(S) & (S < margin)
            if not ins.any():
                continue
            fi, C = fi[ins], C[ins]
            tri = Ov[F[fi]]
            out[0].append(np.full(int(ins.sum()), p))
            out[1].append(vi[ins])
            out[2].append(-S[ins])
            out[3].append(fi)
            out[4].append(_barycentric(C, tri))
        if not out[0]:
            return np.zeros(0, int), np.zeros(0, int), np.zeros(0), np.zeros(0, int), np.zeros((0, 3))
        return tuple(np.concatenate(x) for x in out)

    # ------------------------------------------------------------------------------------ torch side
    def _assemble(self, c: _Contacts, B: int, V: int, dev, dtype, points, normals=None) -> torch.Tensor:
        """Differentiable ``sum rho(depth) / (2V)`` per frame ``(B,)`` from the contacts; positions
        from ``points`` (see :meth:`__call__`), each (body, frame, vertex) read once. ``normals
        (M, 3)``: the obstacle's outward normal at each contact, held (a :class:`Linearised`
        term); None: from the positions, ``(c - p) / |c - p|`` (the exact distance's gradient)."""
        out = torch.zeros(B, device=dev, dtype=dtype)
        M = len(c.frame)
        if M == 0:
            return out
        key = (str(dev), dtype)
        if c.assembly is None or c.assembly[0] != key:
            # side 0: b's vertices (body 1) inside a (body 0); side 1: a's inside b
            tri = self.obstacle_faces[c.face]  # (M, 3)
            q_idx = np.empty(M, np.int64)  # row of each contact's query point in `pos`
            o_idx = np.empty((M, 3), np.int64)  # rows of its closest triangle's corners
            reads, offset = [], 0  # per body: the (frame, vertex) pairs read, once each
            for body in (0, 1):
                mq, mo = c.side == 1 - body, c.side == body
                pair = np.concatenate([c.frame[mq] * V + c.vert[mq], (c.frame[mo, None] * V + tri[mo]).ravel()])
                if not len(pair):
                    continue
                uniq, inv = np.unique(pair, return_inverse=True)
                nq = int(mq.sum())
                q_idx[mq] = offset + inv[:nq]
                o_idx[mo] = offset + inv[nq:].reshape(-1, 3)
                u = torch.as_tensor(uniq, device=dev)
                reads.append((body, u // V, u % V))
                offset += len(uniq)
            c.assembly = (key, reads, torch.as_tensor(q_idx, device=dev), torch.as_tensor(o_idx, device=dev),
                          torch.as_tensor(c.bary, device=dev, dtype=dtype), torch.as_tensor(c.frame, device=dev))  # fmt: skip
        _, reads, q_t, o_t, w, frame_t = c.assembly
        pos = torch.cat([points(body, f, v).to(dtype) for body, f, v in reads])
        p = pos.index_select(0, q_t)  # (M, 3); index_select: its backward (index_add) is cheaper than indexing's
        x = pos.index_select(0, o_t.reshape(-1)).reshape(-1, 3, 3)  # (M, 3, 3)
        closest = (w[:, :, None] * x).sum(dim=1)
        diff = closest - p
        if normals is None:  # every contact here is inside
            with torch.no_grad():
                n = self._outward_normals(diff, x)
        else:
            n = torch.as_tensor(normals, device=dev, dtype=dtype)
        depth = (diff * n).sum(dim=1).clamp_min(0.0)
        out = out.index_add(0, frame_t, self.rho(depth))
        return out / (2 * V)

    @staticmethod
    def _outward_normals(diff: torch.Tensor, x: torch.Tensor, inside: torch.Tensor | None = None) -> torch.Tensor:
        """The obstacle's outward normal ``(M, 3)`` at each contact's closest point: along
        ``diff = c - p`` (``(M, 3)``) for a vertex inside, against it outside (``inside (M,)`` bool;
        None: all inside), the triangle ``x (M, 3, 3)``'s own normal where ``p`` lies on it."""
        dist = diff.norm(dim=1, keepdim=True)
        fn = torch.linalg.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], dim=1)
        fn = fn / fn.norm(dim=1, keepdim=True).clamp_min(1e-20)
        d = diff if inside is None else torch.where(inside[:, None], diff, -diff)
        return torch.where(dist > 1e-9, d / dist.clamp_min(1e-20), fn)

    def _depth_maps(self, c: _Contacts, B: int, V: int, dev, dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """``(depth_a (B, V), depth_b (B, V))`` from the contacts, no gradient."""
        maps = []
        for side in (1, 0):  # depth_a: a's vertices inside b (side 1)
            d = np.zeros((B, V), np.float64)
            m = c.side == side
            d[c.frame[m], c.vert[m]] = c.depth[m]
            maps.append(torch.as_tensor(d, device=dev, dtype=dtype))
        return maps[0], maps[1]

    def _guard(self, va: torch.Tensor, vb: torch.Tensor, active: torch.Tensor, points) -> torch.Tensor:
        """``guard_weight * relu(1 - |dc| / guard_m)`` per frame, pushing the centroids apart;
        ``va``, ``vb`` (detached) pick the frames where it is on, ``points`` gives their centroids
        with the gradient."""
        B, V = va.shape[:2]
        return self._guard_loss(self._guard_frames(va, vb, active), B, V, va.device, va.dtype, points)

    def _guard_frames(self, va: torch.Tensor, vb: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
        """Frames ``(n,)`` (int64) of the batch where the coincidence guard is on: active, and the
        guard vertices' centroids closer than ``guard_m``."""
        V = va.shape[1]
        if self.guard_weight == 0:
            return torch.zeros(0, dtype=torch.int64, device=va.device)
        if self._guard_idx is None:
            sel = slice(None)
        elif self.guard_vertices[-1] >= V:  # sorted: the last is the largest
            raise ValueError(f"guard_vertices index {int(self.guard_vertices[-1])} is out of range for {V} vertices")
        else:
            sel = self._guard_idx.to(va.device)
        on = active & ((vb[:, sel].mean(dim=1) - va[:, sel].mean(dim=1)).norm(dim=1) < self.guard_m)
        return torch.nonzero(on).flatten()

    def _guard_loss(self, frames: torch.Tensor, B: int, V: int, dev, dtype, points) -> torch.Tensor:
        out = torch.zeros(B, device=dev, dtype=dtype)
        if not len(frames):  # relu(1 - |dc| / guard_m) and its gradient are 0 everywhere else
            return out
        frames = frames.to(dev)
        gv = torch.arange(V, device=dev) if self._guard_idx is None else self._guard_idx.to(dev)
        G = len(gv)
        f = frames.repeat_interleave(G)
        v = gv.repeat(len(frames))
        ca, cb = (points(body, f, v).reshape(len(frames), G, 3).mean(dim=1) for body in (0, 1))
        delta = cb - ca  # (n, 3)
        with torch.no_grad():
            dist = delta.norm(dim=1, keepdim=True)
            ex = torch.zeros_like(delta)
            ex[:, 0] = 1.0
            u = torch.where(dist > 1e-9, delta / dist.clamp_min(1e-20), ex)
        proj = (delta * u).sum(dim=1)
        g = self.guard_weight * torch.relu(1.0 - proj / self.guard_m)
        return out.index_put((frames,), g.to(out.dtype))

    # ------------------------------------------------------------------------------------ grid method
    def _grid_terms(self, va: torch.Tensor, vb: torch.Tensor, frames: np.ndarray):
        """Jiang's term: loss ``(B,)`` and interpolated depth maps ``(B, V)`` for a and b."""
        import torch.nn.functional as tnf

        B, V = va.shape[:2]
        dev, dtype = va.device, va.dtype
        R = self.grid_res
        ft = torch.as_tensor(frames, device=dev)
        A = va.detach()[ft].cpu().numpy().astype(np.float32)
        Bv = vb.detach()[ft].cpu().numpy().astype(np.float32)
        K = len(frames)
        O = np.empty((2 * K, V, 3), np.float32)
        O[0::2], O[1::2] = A, Bv  # grid 2k: inside a (sampled at b), 2k+1: inside b (sampled at a)
        ov = O[:, self.obstacle_vertices]
        lo, hi = ov.min(axis=1), ov.max(axis=1)
        pad = 0.2 * (hi - lo) / 2
        lo, hi = lo - pad, hi + pad
        t = np.linspace(0.0, 1.0, R, dtype=np.float32)
        zz, yy, xx = np.meshgrid(t, t, t, indexing="ij")  # phi[z, y, x], grid_sample's (D, H, W)
        unit = np.stack([xx, yy, zz], axis=-1).reshape(-1, 3)
        nodes = lo[:, None] + unit[None] * (hi - lo)[:, None]  # (P, R^3, 3)
        ids = self._meshes(O)
        P = 2 * K
        which = np.repeat(np.arange(P, dtype=np.int32), R**3)
        big = np.repeat(np.linalg.norm(hi - lo, axis=1), R**3)
        sd, face, _ = self._query(ids, which, nodes.reshape(-1, 3), big)
        phi = np.where((face >= 0) & (sd < 0), -sd, 0.0).astype(np.float32).reshape(P, 1, R, R, R)
        phi_t = torch.as_tensor(phi, device=dev, dtype=dtype)
        lo_t = torch.as_tensor(lo, device=dev, dtype=dtype)
        hi_t = torch.as_tensor(hi, device=dev, dtype=dtype)
        query = torch.stack([vb[ft], va[ft]], dim=1).reshape(P, V, 3)  # grid 2k sampled at b
        g = 2.0 * (query - lo_t[:, None]) / (hi_t - lo_t)[:, None] - 1.0
        depth = tnf.grid_sample(phi_t, g[:, None, None], mode="bilinear", padding_mode="zeros",
                                align_corners=True).reshape(P, V)  # fmt: skip
        surface = torch.zeros(V, device=dev, dtype=dtype)
        surface[torch.as_tensor(self.obstacle_vertices, device=dev)] = 1.0
        depth = depth.clamp_min(0.0) * surface  # query points: the surface vertices, as for the exact methods
        per = self.rho(depth).sum(dim=1).reshape(K, 2).sum(dim=1) / (2 * V)
        loss = torch.zeros(B, device=dev, dtype=dtype).index_add(0, ft, per)
        dd = depth.detach().reshape(K, 2, V)
        depth_b = torch.zeros(B, V, device=dev, dtype=dtype)
        depth_a = torch.zeros_like(depth_b)
        depth_b[ft] = dd[:, 0]
        depth_a[ft] = dd[:, 1]
        return loss, depth_a, depth_b


def _barycentric(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentric weights ``(N, 3)`` of points ``p (N, 3)`` lying on triangles ``tri (N, 3, 3)``."""
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

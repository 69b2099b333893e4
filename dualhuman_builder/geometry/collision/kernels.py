"""Warp CPU kernels of the collision term.

One Python module is one warp module, built and loaded as a unit, so all the term's kernels live
here. Positions are ``wp.vec3`` float32 metres; a *problem* is one (frame, direction) pair: the
vertices of one body (the query) against the surface of the other (the obstacle).

* :func:`closest_points` — closest point on a BVH mesh, with the inside/outside sign
  (:mod:`.queries`);
* :func:`flood_union`, :func:`flood_signs` — the sign flood fill's union-find forest and the
  signs it propagates (:mod:`.flood`);
* :func:`vertex_moves`, :func:`part_moves`, :func:`kept_signs` — the bound that lets a vertex keep
  a remembered sign (:mod:`.memory`).

Kernels that take ``start`` cover items ``start + tid``, so that :class:`.cpu_launch.CpuThreads`
can split one launch over threads.
"""

from __future__ import annotations

import warp as wp


@wp.kernel
def closest_points(
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
    """Closest point of ``points[start + tid]`` on mesh ``meshes[which[i]]`` within ``max_dist[i]``:
    signed distance ``sdist`` (negative inside; pseudonormal sign, or generalised winding number
    when ``winding`` is 1), ``face`` (-1: nothing within ``max_dist``) and barycentric ``bary``."""
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


@wp.func
def find_root(parent: wp.array2d(dtype=wp.int32), t: int, v: int) -> int:
    """The root of vertex ``v``'s tree in row ``t`` of the union-find forest ``parent``, halving
    the path on the way (each vertex visited then points to its grandparent)."""
    x = int(v)
    while parent[t, x] != x:
        g = parent[t, parent[t, x]]
        parent[t, x] = g
        x = g
    return x


@wp.kernel
def flood_union(
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
    ``parent[t]`` (vertex indices), of the query mesh's edges ``(e0, e1)`` the sign flood fill may
    follow: those with an end of unknown sign (``sgn`` 0) whose ends' distance bounds ``bound`` add
    up to more than the edge, so that it cannot cross the obstacle (the relative 1e-4 and absolute
    1e-6 m margin covers float32 rounding). A thread owns whole problems, so threads never write
    the same row."""
    t = wp.tid() + start
    r = rows[t]
    for v in range(points.shape[1]):
        parent[t, v] = v
    for k in range(e0.shape[0]):
        a = e0[k]
        b = e1[k]
        if sgn[r, a] == wp.int8(0) or sgn[r, b] == wp.int8(0):
            if bound[r, a] + bound[r, b] > wp.length(points[r, a] - points[r, b]) * (1.0 + 1.0e-4) + 1.0e-6:
                x = find_root(parent, t, a)
                y = find_root(parent, t, b)
                if x < y:
                    parent[t, y] = x
                elif y < x:
                    parent[t, x] = y


@wp.kernel
def flood_signs(
    sgn: wp.array2d(dtype=wp.int8),
    rows: wp.array(dtype=wp.int32),
    start: wp.int32,
    parent: wp.array2d(dtype=wp.int32),
    flags: wp.array2d(dtype=wp.int32),
    code: wp.array2d(dtype=wp.int32),
):
    """Problem ``rows[t]``, after :func:`flood_union`: each vertex of unknown sign whose component's
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
        root = find_root(parent, t, v)
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
def vertex_moves(
    a: wp.array2d(dtype=wp.vec3),
    a0: wp.array2d(dtype=wp.vec3),
    b: wp.array2d(dtype=wp.vec3),
    b0: wp.array2d(dtype=wp.vec3),
    da: wp.array2d(dtype=wp.float32),
    db: wp.array2d(dtype=wp.float32),
):
    """Frame ``i``, vertex ``v``: how far each body's vertex moved from ``a0``/``b0`` to ``a``/``b``
    (``da``, ``db``, metres)."""
    i, v = wp.tid()
    da[i, v] = wp.length(a[i, v] - a0[i, v])
    db[i, v] = wp.length(b[i, v] - b0[i, v])


@wp.kernel
def part_moves(
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
    part ``part[k]``. Per frame, body (0: a, 1: b) and part, the largest move of its corners
    (``most[i, body, g]``) and the box of their old and new positions (``lo``, ``hi``). A thread owns
    whole frames (the maxima and minima are read-modify-writes)."""
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
def kept_signs(
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
    """Remembered problem ``r = 2 i + side`` (``tid + start``), vertex ``v``: the query vertex (b's for
    side 0, against a; a's for side 1) keeps its sign ``s0`` and a bound ``lb`` in row ``rows[r]`` where
    its remembered bound ``l0``, less its own move and the obstacle's largest (``whole[i, body]``),
    stays positive -- or else where, for every part ``g`` of the obstacle, ``l0`` less its own move
    and the part's largest (``most[i, body, g]``), or its distance to the part's box (``lo``, ``hi``)
    less its own move, does. The margin ``eps`` covers the float32 rounding of the stored bound."""
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

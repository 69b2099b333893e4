"""Differentiable collision term between two bodies, after Jiang et al. (CVPR 2020), made exact.

Jiang et al. ("Coherent reconstruction of multiple humans") sample each person's inside distance on
a 32^3 grid and read it at the other person's vertices. Here the same quantity -- for every vertex of
one body, how deep it lies inside the other -- is computed exactly on the mesh, both ways, and its
gradient pushes both bodies. Vertices are ``(B, V, 3)`` torch tensors in the Y-up world frame,
metres; the ``B`` frames are independent. Why exact: ``docs/decisions/0010-exact-collision-term.md``;
how the fit uses it: ``docs/design/fit-collision.md``.

``depth(p)``
    distance from surface vertex ``p`` of one body to the closest point ``c`` on the other body's
    surface when ``p`` is inside it, else 0 (metres); differentiable as ``(c - p) . n`` with ``n``
    held (:mod:`.depth`), so the vertex is pushed out and the surface pushed back.

Loss per frame ``(B,)``
    ``sum_{p penetrating, both bodies} rho(depth_p) / (2 V)`` -- the mean over both bodies' ``2V``
    vertices, so it does not grow with mesh resolution -- plus the coincidence guard (:mod:`.guard`).
    ``rho`` defaults to the pseudo-Huber ``sqrt(1 + (d/s)^2) - 1``, ``s = robust_sigma_m`` (1 cm):
    quadratic for shallow contacts, linear for deep ones, whose push stays at ``1/s`` per vertex;
    ``"geman_mcclure"`` (Jiang's) and ``"squared"`` are available (:func:`.depth.robust_penalty`).

Broad phase
    Frames whose boxes, grown by ``pad_m``, do not overlap are inactive: loss exactly 0, zero
    gradient, no query. In an active frame only the surface vertices within ``pad_m`` of the other
    body's box are queried (:mod:`.locate`).

Inside and outside
    The obstacle is the largest closed component of the faces (anny: the body without eyes and
    mouth; :mod:`.surface`). The default pseudonormal sign (``sign="normal"``) is exact for a closed
    surface that does not intersect itself; where a posed body does (an arm pressed into its own
    torso), only the generalised winding number is right: ``sign="winding"``, slower.

Methods
    ``"warp"`` (default): exact depths by a banded BVH query, the sign flood fill and full queries
    (:mod:`.search`, :mod:`.flood`, :mod:`.queries`), in warp CPU kernels split over ``threads``
    threads. ``"igl"``: ``igl.signed_distance`` on the candidates, exact, its tree rebuilt per call.
    ``"grid"``: Jiang's voxel grid (:mod:`.grid`). Speed and accuracy of the three:
    ``benchmarks/bench_collision.py``.

Reuse across calls (``keys``)
    A caller that names its frames lets each keep its signs for the next call on the same frame,
    wherever a bound proves they cannot have changed (:mod:`.memory`): the same answer, fewer queries.

Held contacts
    :meth:`CollisionTerm.linearise` locates the contacts once and :meth:`CollisionTerm.linear_loss`
    evaluates them many times against held planes (:mod:`.linearised`).

Queries always run on the CPU: CUDA tensors are copied to the CPU for the query (``V x 3`` floats
per body and frame) and the differentiable assembly runs on the tensors' own device.

Modules: :mod:`.term` (:class:`CollisionTerm`), :mod:`.surface`, :mod:`.locate`, :mod:`.search`,
:mod:`.flood`, :mod:`.memory`, :mod:`.queries`, :mod:`.depth`, :mod:`.guard`, :mod:`.linearised`,
:mod:`.grid`, :mod:`.kernels` (the warp kernels), :mod:`.cpu_launch` (threaded launches).
"""

from dualhuman_builder.geometry.collision.depth import RHOS
from dualhuman_builder.geometry.collision.linearised import Linearised
from dualhuman_builder.geometry.collision.locate import Contacts
from dualhuman_builder.geometry.collision.term import METHODS, CollisionResult, CollisionTerm

__all__ = ["METHODS", "RHOS", "CollisionResult", "CollisionTerm", "Contacts", "Linearised"]

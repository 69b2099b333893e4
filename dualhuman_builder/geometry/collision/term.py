"""The collision term's public face: :class:`CollisionTerm` and its result, :class:`CollisionResult`.

:class:`CollisionTerm` checks its inputs, runs the broad phase, and hands the work to its
collaborators: :class:`~.locate.ContactLocator` (where the bodies penetrate), :mod:`.depth` (the
differentiable depths and the robust penalty), :class:`~.guard.CoincidenceGuard`, :mod:`.grid`
(method ``"grid"``) and :class:`~.linearised.Linearised` (held contacts). The contract is stated in
:mod:`dualhuman_builder.geometry.collision`.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass

import numpy as np
import torch

from dualhuman_builder.geometry.collision.cpu_launch import CpuThreads
from dualhuman_builder.geometry.collision.depth import RHOS, assemble, depth_maps, penetration_summary, robust_penalty
from dualhuman_builder.geometry.collision.flood import SignFlood
from dualhuman_builder.geometry.collision.grid import grid_terms
from dualhuman_builder.geometry.collision.guard import CoincidenceGuard
from dualhuman_builder.geometry.collision.linearised import Linearised, held_normals
from dualhuman_builder.geometry.collision.locate import ContactLocator, Contacts, broad_phase
from dualhuman_builder.geometry.collision.memory import SignMemory
from dualhuman_builder.geometry.collision.queries import MeshPool
from dualhuman_builder.geometry.collision.surface import ObstacleSurface, faces_array

METHODS = ("warp", "igl", "grid")
SIGNS = ("normal", "winding")
#: query threads when the caller does not say: the CPU count, at most this
MAX_DEFAULT_THREADS = 8


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


def _check_options(method, rho, sign, metres: dict, guard_weight, eps_m, flood_min, max_memo, grid_res) -> None:
    """``ValueError`` for an unknown method, penalty or sign, or a number out of its range."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if rho not in RHOS:
        raise ValueError(f"rho must be one of {RHOS}, got {rho!r}")
    if sign not in SIGNS:
        raise ValueError(f"sign must be 'normal' or 'winding', got {sign!r}")
    for name, val in metres.items():
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


def _bvh_points(bvh_points, num_vertices_min: int) -> np.ndarray | None:
    """``bvh_points`` as C-contiguous ``(V, 3)`` float32 (``V >= num_vertices_min``, finite), or None."""
    bp = None if bvh_points is None else np.ascontiguousarray(np.asarray(bvh_points, dtype=np.float32))
    if bp is not None and (bp.ndim != 2 or bp.shape[1] != 3 or len(bp) < num_vertices_min or not np.isfinite(bp).all()):
        raise ValueError(f"bvh_points must be finite (V, 3) points with V >= {num_vertices_min}, got shape {bp.shape}")
    return bp


class CollisionTerm:
    """Penetration loss and diagnostics between two bodies sharing one triangle topology.

    ``faces (F, 3)`` int array or tensor (anny's ``model.faces``); its largest component must be
    closed (:class:`~.surface.ObstacleSurface`). ``method`` ``"warp"`` (default, exact), ``"igl"``
    (exact, slower) or ``"grid"`` (Jiang's voxel grid). ``robust_sigma_m`` the scale ``s`` of
    ``rho`` (metres); ``band_m`` the radius of the first, banded query (metres); ``pad_m`` growth of
    the broad-phase boxes (metres, default ``band_m``); ``rho`` ``"pseudo_huber"``,
    ``"geman_mcclure"`` or ``"squared"``; ``sign`` ``"normal"`` (pseudonormal) or ``"winding"``
    (generalised winding number); ``guard_m``/``guard_weight``/``guard_vertices`` the coincidence
    guard (:class:`~.guard.CoincidenceGuard`); ``eps_m`` depth above which a vertex counts as
    penetrating in the diagnostics; ``grid_res`` cells per axis of ``"grid"``; ``threads`` query
    threads (default: the CPU count, at most 8); ``flood_min`` open far vertices from which the sign
    flood fill replaces one full query each; ``max_memo`` frames kept by the sign memory that
    ``keys`` enables (about 0.5 MB each for anny); ``bvh_points`` optional ``(V, 3)`` points every
    pooled mesh's BVH is built over (:class:`~.queries.MeshPool`: without them the answers depend,
    by rounding, on which frames first built each pooled mesh); ``parts`` optional ``(V,)`` ints, the
    parts of a body that move together, over which the sign memory bounds the obstacle's move
    (:mod:`.memory`; a face belongs to the highest-numbered part among its corners', so number last a
    part that moves alone); ``seed_stride`` a power of 2, how unseen frames start from their
    neighbours' signs (:meth:`~.memory.SignMemory.levels`; 1: off).

    Why these defaults: ``docs/decisions/0010-exact-collision-term.md`` (method, sign, ``rho`` and its
    scale), ``0014-hand-openings-and-torso-guard.md`` (the guard), ``0020-collision-term-cost.md``
    (band, sign memory); the fit passes its own band, pad, guard vertices and parts.

    Calls are serialised by a lock. ``last_stats``: the counts of the last call's exact search
    (candidates, near, far, representatives, conflicted, full, reused; empty: no query).
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
        pad_m = band_m if pad_m is None else pad_m
        metres = {"robust_sigma_m": robust_sigma_m, "band_m": band_m, "pad_m": pad_m, "guard_m": guard_m}
        _check_options(method, rho, sign, metres, guard_weight, eps_m, flood_min, max_memo, grid_res)
        faces = faces_array(faces)
        self.method = method
        self.sigma = float(robust_sigma_m)
        self.band = float(band_m)
        self.pad = float(pad_m)
        self.rho_name = rho
        self.sign = sign
        self.guard = CoincidenceGuard(guard_m, guard_weight, guard_vertices)
        self.guard_m, self.guard_weight = self.guard.guard_m, self.guard.weight
        self.eps = float(eps_m)
        self.grid_res = int(grid_res)
        self.flood_min = int(flood_min)
        self.threads = max(1, int(threads) if threads else min(os.cpu_count() or 1, MAX_DEFAULT_THREADS))
        self.surface = ObstacleSurface(faces)
        bvh = _bvh_points(bvh_points, self.surface.num_vertices_min)
        cpu = CpuThreads(self.threads)
        #: the signs remembered across calls that name their frames (:mod:`.memory`)
        self.memory = SignMemory(self.surface, parts, max_memo, seed_stride, cpu)
        self.pool = MeshPool(self.surface.obstacle_faces, cpu, sign == "winding", bvh)
        self.locator = ContactLocator(self.surface, self.pool, SignFlood(self.surface.edges, cpu), self.memory,
                                      method, self.band, self.pad, self.flood_min)  # fmt: skip
        self._lock = threading.Lock()
        self.last_stats: dict = {}

    # the obstacle surface (:class:`~.surface.ObstacleSurface`)
    faces = property(lambda self: self.surface.faces, doc="``(F, 3)`` int64, all faces")
    num_vertices_min = property(lambda self: self.surface.num_vertices_min, doc="vertices a body needs at least")
    obstacle_faces = property(lambda self: self.surface.obstacle_faces, doc="``(F', 3)`` the closed obstacle's faces")
    obstacle_vertices = property(lambda self: self.surface.obstacle_vertices, doc="``(S,)`` the query vertices")
    edges = property(lambda self: self.surface.edges, doc="``(E, 2)`` the obstacle's edges (the flood fill's)")
    num_parts = property(lambda self: self.memory.num_parts, doc="the obstacle's part count (:mod:`.memory`)")
    guard_vertices = property(lambda self: self.guard.vertices, doc="``(G,)`` the guard's vertices, or None: all")

    # ------------------------------------------------------------------------------------ public
    def __call__(self, verts_a, verts_b, keys=None, points=None) -> CollisionResult:
        """Loss and diagnostics for ``verts_a``, ``verts_b`` ``(B, V, 3)`` tensors (metres).
        ``keys``: optional ``B`` distinct hashable names of the frames (e.g. timeline indices), which
        let later calls on the same frames reuse this one's signs (:mod:`.memory`).

        ``points``: optional ``points(body, frames, vertices) -> (M, 3)`` tensor, the positions of
        body ``body`` (0: a, 1: b) at the pairs ``frames (M,)``, ``vertices (M,)`` (int64 tensors),
        differentiable in whatever the caller optimises. Given it, ``verts_a``/``verts_b`` only
        locate the contacts (they may be detached) and the loss's gradient flows through
        ``points`` at the few vertices it reads (the penetrating ones and the corners of their
        closest triangles; all of a frame's guard vertices where the coincidence guard is on): the
        same loss and gradient without differentiating every vertex of every frame. Exact methods only."""
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
            active, frames, boxes = self._broad_phase(va.detach(), vb.detach())
            max_depth = torch.zeros(B, device=dev, dtype=dtype)
            count = torch.zeros(B, device=dev, dtype=torch.int64)
            if len(frames):
                if self.method == "grid":
                    pen_loss, depth_a, depth_b = self._grid(va, vb, frames)
                    loss = loss + pen_loss
                    d = torch.cat([depth_a, depth_b], dim=1)
                else:
                    c = self._locate(va.detach(), vb.detach(), frames, boxes, keys)
                    loss = loss + assemble(c, B, V, dev, dtype, points, self.obstacle_faces, self.rho)
                    d = torch.cat(depth_maps(c, B, V, dev, dtype), dim=1)
                max_depth = torch.where(d > self.eps, d, torch.zeros_like(d)).amax(dim=1)
                count = (d > self.eps).sum(dim=1)
                guard = self.guard.frames(va.detach(), vb.detach(), active)
                loss = loss + self.guard.loss(guard, B, V, dev, dtype, points)
        share = count.to(dtype) / (2 * V)
        return CollisionResult(loss=loss, max_depth_m=max_depth, penetrating=count, share=share, active=active)

    def penetration(self, verts_a, verts_b, keys=None) -> dict:
        """Depths without gradient, as numpy arrays, for evaluation and reports.

        ``verts_a``, ``verts_b``: ``(B, V, 3)`` (or ``(V, 3)``) tensors or arrays, metres;
        ``keys`` as for :meth:`__call__`.
        Returns ``max_depth_m (B,)``, ``share (B,)``, ``penetrating (B,)``, ``active (B,)``,
        ``depth_a (B, V)`` (how deep each vertex of a lies inside b; 0 outside) and
        ``depth_b (B, V)`` (b inside a), float64 metres (:func:`~.depth.penetration_summary`).
        """
        va, vb = self._check(verts_a, verts_b, need_tensor=False)
        B, V = va.shape[:2]
        keys = self._check_keys(keys, B)
        with self._lock, torch.no_grad():
            active, frames, boxes = self._broad_phase(va, vb)
            depth_a = torch.zeros(B, V, dtype=va.dtype, device=va.device)
            depth_b = torch.zeros_like(depth_a)
            if len(frames):
                if self.method == "grid":
                    _, depth_a, depth_b = self._grid(va, vb, frames)
                else:
                    c = self._locate(va, vb, frames, boxes, keys)
                    depth_a, depth_b = depth_maps(c, B, V, va.device, va.dtype)
        return penetration_summary(depth_a, depth_b, active, self.eps)

    def linearise(self, verts_a, verts_b, keys=None, margin_m: float = 0.005) -> Linearised:
        """Locate the contacts of ``verts_a``, ``verts_b`` ``(B, V, 3)`` (tensors, metres; no
        gradient is taken) once, for :meth:`linear_loss`: every vertex of either body inside the
        other or outside within ``margin_m`` (0 < margin_m <= min(band_m, pad_m)) of it. ``keys``
        as for :meth:`__call__`. Exact methods only. See :mod:`.linearised`."""
        if self.method == "grid":
            raise ValueError("linearise needs an exact method ('warp' or 'igl'); the grid has no closest points")
        if not (np.isfinite(margin_m) and 0 < margin_m <= min(self.band, self.pad)):
            raise ValueError(f"margin_m must be in (0, min(band_m, pad_m)] = (0, {min(self.band, self.pad)}] m, got {margin_m!r}")
        va, vb = self._check(verts_a, verts_b, need_tensor=True)
        va, vb = va.detach(), vb.detach()
        B, V = va.shape[:2]
        keys = self._check_keys(keys, B)
        with self._lock, torch.no_grad():
            active, frames, boxes = self._broad_phase(va, vb)
            c = self._locate(va, vb, frames, boxes, keys, margin=float(margin_m)) if len(frames) else Contacts.empty()
            guard = self.guard.frames(va, vb, active)
            diag = penetration_summary(*depth_maps(c, B, V, va.device, va.dtype), active, self.eps)
        normals = held_normals(c, va, vb, self.obstacle_faces)
        return Linearised(contacts=c, normals=normals, guard=guard, B=B, V=V, max_depth_m=diag["max_depth_m"],
                          share=diag["share"], penetrating=diag["penetrating"], active=diag["active"])  # fmt: skip

    def linear_loss(self, lin: Linearised, points, device=None, dtype=torch.float32) -> torch.Tensor:
        """The loss ``(B,)`` of :meth:`__call__` with the contacts of ``lin`` held:
        ``sum rho(relu((c - p) . m)) / (2 V)`` plus the coincidence guard on ``lin.guard``;
        ``points(body, frames, vertices) -> (M, 3)`` as for :meth:`__call__`, on ``device``
        (default: the CPU)."""
        dev = torch.device("cpu") if device is None else torch.device(device)
        loss = assemble(lin.contacts, lin.B, lin.V, dev, dtype, points, self.obstacle_faces, self.rho,
                        normals=lin.normals)  # fmt: skip
        return loss + self.guard.loss(lin.guard, lin.B, lin.V, dev, dtype, points)

    def moving_only(self, lin: Linearised, moving: np.ndarray) -> Linearised:
        """The contacts of ``lin`` whose held depth changes when only the vertices ``moving``
        (``(V,)`` bool, the same in both bodies) move (:meth:`Linearised.moving_only`):
        :meth:`linear_loss` on the answer has the same gradient over such a move, with fewer points
        to read. The coincidence guard is kept unless none of its vertices is ``moving``."""
        return lin.moving_only(moving, self.obstacle_faces, self.guard)

    def clear_memo(self) -> None:
        """Forget the signs kept for ``keys`` (:mod:`.memory`)."""
        with self._lock:
            self.memory.clear()

    def rho(self, depth: torch.Tensor) -> torch.Tensor:
        """The robust penalty of depths (metres, >= 0), dimensionless (:func:`~.depth.robust_penalty`)."""
        return robust_penalty(depth, self.rho_name, self.sigma)

    # ------------------------------------------------------------------------------------ steps
    def _broad_phase(self, va: torch.Tensor, vb: torch.Tensor) -> tuple[torch.Tensor, np.ndarray, tuple]:
        """A new call: ``last_stats`` cleared, then :func:`~.locate.broad_phase` at ``pad``."""
        self.last_stats = {}
        return broad_phase(va, vb, self.pad)

    def _locate(self, va, vb, frames, boxes, keys, margin: float = 0.0) -> Contacts:
        """:meth:`~.locate.ContactLocator.locate`, its counts kept as ``last_stats``."""
        c, self.last_stats = self.locator.locate(va, vb, frames, boxes, keys, margin)
        return c

    def _grid(self, va, vb, frames):
        """Method ``"grid"``: loss and depth maps (:func:`~.grid.grid_terms`)."""
        return grid_terms(self.pool, self.obstacle_vertices, self.rho, self.grid_res, va, vb, frames)

    # ------------------------------------------------------------------------------------ input
    def _check(self, verts_a, verts_b, need_tensor: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """The two bodies as ``(B, V, 3)`` floating tensors of one shape, device and dtype; arrays are
        accepted (as float64) unless ``need_tensor``, and ``(V, 3)`` as one frame. ``ValueError``
        otherwise, and for too few vertices or NaN or infinite coordinates."""
        out = [self._check_one(name, v, need_tensor) for name, v in (("verts_a", verts_a), ("verts_b", verts_b))]
        if out[0].shape != out[1].shape:
            raise ValueError(f"verts_a {tuple(out[0].shape)} and verts_b {tuple(out[1].shape)} must have the same shape")
        if out[0].device != out[1].device or out[0].dtype != out[1].dtype:
            raise ValueError(f"verts_a ({out[0].device}, {out[0].dtype}) and verts_b ({out[1].device}, {out[1].dtype}) "
                             "must share device and dtype")  # fmt: skip
        return out[0], out[1]

    def _check_one(self, name: str, v, need_tensor: bool) -> torch.Tensor:
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
        return v

    @staticmethod
    def _check_keys(keys, B: int) -> list | None:
        """``keys`` as a list of ``B`` distinct names, or None; ``ValueError`` otherwise."""
        if keys is None:
            return None
        keys = keys.tolist() if isinstance(keys, (np.ndarray, torch.Tensor)) else list(keys)
        if len(keys) != B:
            raise ValueError(f"keys must name each of the {B} frames, got {len(keys)}")
        if len(set(keys)) != B:
            raise ValueError("keys must be distinct: two frames of one call cannot share a name")
        return keys

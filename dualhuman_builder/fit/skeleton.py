"""A fast, differentiable anny of one fixed shape, parameterised by segment orientations.

The fitter never calls anny in its inner loop: for one actor's shape it precomputes what anny's
forward pass would do and evaluates it in a handful of batched tensor operations, exactly (to float
precision: checked against :meth:`BodyModel.forward` in the tests).

Parameterisation (Y-up world, metres)
    ``A (B, S, 3, 3)``: the world-aligned global rotation (see :mod:`dualhuman_builder.body.model`)
    of the anny bone each of the ``S = 23`` MVN segments drives (``rigs/mvn_anny.toml``); every other
    anny bone (twist bones, spine05, fingers...) follows its nearest driven ancestor (zero local
    rotation), as the mapping's comments say — except that four *hand openings* (thumb and fingers
    of each hand, :mod:`dualhuman_builder.body.hands`) may straighten the fingers towards a flat
    hand. ``transl (B, 3)``: the root bone head (pelvis centre).

Positions
    bone heads ``h_j = transl + sum over the edges e on the path root->j of A_parent(e) (h0_e - h0_parent(e))``
    (``h0``: heads at anny's zero pose, root at the origin) — one matrix product with a constant
    path matrix, no loop over the tree; vertices by anny's linear blend skinning
    ``v = sum_k w_vk (A_k u_vk + h_k)`` with ``u_vk`` the vertex's zero-pose offset as carried by
    bone ``k`` (anny's rest bone poses are not its zero pose, so ``u`` is per vertex and bone).

Segment frames
    the segment orientation a suit reports is ``R_seg = A S`` with the constant
    ``S = A_Tpose^T B`` (:func:`~dualhuman_builder.sim.groundtruth.segment_kinematics` defines it);
    :meth:`BodyRig.retarget` inverts that: ``A = R_seg S^T``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import roma
import torch
import warp as wp
from torch.autograd.function import once_differentiable

from dualhuman_builder.body.mapping import MVN_SEGMENTS, SegmentMapping, load_segment_mapping


class _RotvecToRotmat(torch.autograd.Function):
    """``R = cos t I + a [v]x + b v v^T`` (Rodrigues, ``t = |v|``, ``a = sin t / t``, ``b = (1 - cos t) /
    t^2 = 2 sin^2(t/2) / t^2``, both from ``torch.sinc``: no cancellation, no branch at small angles)
    with a closed-form gradient: one node in the graph instead of roma's ~40 (the fit converts every
    correction and opening at every evaluation). First derivatives only (``once_differentiable``)."""

    @staticmethod
    def forward(ctx, v):
        t2 = (v * v).sum(-1)
        t = t2.sqrt()
        a = torch.sinc(t / math.pi)
        b = 0.5 * torch.sinc(t / (2 * math.pi)) ** 2
        c = torch.cos(t)
        x, y, z = v.unbind(-1)
        ax, ay, az = a * x, a * y, a * z
        skew = torch.stack([c, -az, ay, az, c, -ax, -ay, ax, c], dim=-1).reshape(*v.shape[:-1], 3, 3)
        ctx.save_for_backward(v, t2, a, b, c)
        return skew + (b[..., None] * v)[..., :, None] * v[..., None, :]

    @staticmethod
    @once_differentiable
    def backward(ctx, g):
        # R = c I + a K(v) + b v v^T with c, a, b functions of t = |v|: dc/dv = -a v, da/dv = al v,
        # db/dv = be v (al = a'(t) / t = (c - a) / t^2, be = b'(t) / t = (a - 2 b) / t^2), so
        # dL/dv = (-a tr G + al v.w + be v^T G v) v + a w + b (G + G^T) v, w = (G21 - G12, G02 - G20,
        # G10 - G01) (sum G * K(v) = v.w). al and be cancel at small t, but their terms scale with t^2:
        # the error stays at the rounding of a w
        v, t2, a, b, c = ctx.saved_tensors
        inv = 1.0 / t2.clamp(min=1e-12)
        al, be = (c - a) * inv, (a - 2 * b) * inv
        w = torch.stack([g[..., 2, 1] - g[..., 1, 2], g[..., 0, 2] - g[..., 2, 0], g[..., 1, 0] - g[..., 0, 1]], dim=-1)
        gv = ((g + g.transpose(-1, -2)) @ v[..., None])[..., 0]
        coef = -a * g.diagonal(dim1=-2, dim2=-1).sum(-1) + al * (v * w).sum(-1) + be * 0.5 * (v * gv).sum(-1)
        return coef[..., None] * v + a[..., None] * w + b[..., None] * gv


def rotvec_to_rotmat(v: torch.Tensor) -> torch.Tensor:
    """Rotation vectors ``v (..., 3)`` (radians) -> rotation matrices ``(..., 3, 3)``, as
    ``roma.rotvec_to_rotmat`` (within float rounding) but one autograd node (:class:`_RotvecToRotmat`)."""
    return _RotvecToRotmat.apply(v)


@dataclass
class Posed:
    """Output of :meth:`BodyRig.pose`: ``heads (B, J, 3)``, ``rot (B, J, 3, 3)`` world-aligned
    global rotations of all J anny bones, ``vertices (B, V', 3)`` (the rig's vertex subset) or None."""

    heads: torch.Tensor
    rot: torch.Tensor
    vertices: torch.Tensor | None


class BodyRig:
    """anny of one shape as tensors. ``vertex_ids``: the vertices to skin (None: all of them;
    an empty array: none); the fitter skins a subset for floor contact and the full mesh for
    collisions."""

    def __init__(self, model, shape, mapping: SegmentMapping | None = None, device=None, dtype=torch.float32):
        from dualhuman_builder.body.joints import tpose
        from dualhuman_builder.body.mapping import SEGMENT_TPOSE_FRAME

        self.model = model
        self.device = torch.device(device or model.device)
        self.dtype = dtype
        self.mapping = mapping or load_segment_mapping(bone_names=model.bone_names, num_vertices=model.num_vertices)
        self.shape = model.shape_tensor(shape).detach().reshape(-1).to(model.device)
        a, c = model.anny, model._c
        J = model.num_bones
        with torch.no_grad():
            eye = torch.eye(4, dtype=model.dtype, device=model.device).expand(1, J, 4, 4)
            raw = a(pose_parameters=eye, phenotype_kwargs=self.shape[None])
            zero_pose = raw["bone_poses"][0]
            to_zero = zero_pose @ torch.linalg.inv(raw["rest_bone_poses"][0])  # per bone, Z-up
            rest_v = raw["rest_vertices"][0]
            h0 = (zero_pose[:, :3, 3] @ c.T).double()  # (J, 3) Y-up, root at the origin
            idx = a.vertex_bone_indices.long()
            w = a.vertex_bone_weights
            # per-bone zero-pose positions of each vertex: u_vk = to_zero_k v (Y-up), minus h0_k
            vh = torch.cat([rest_v, torch.ones_like(rest_v[:, :1])], dim=1)
            u = (to_zero[idx] @ vh[:, None, :, None])[..., :3, 0] @ c.T
            u = u.double() - h0[idx]
            # the same as bone transforms on Y-up rest vertices, for anny's own (warp) skinning kernel
            zr = c @ to_zero[:, :3, :3] @ c.T
            zt = to_zero[:, :3, 3] @ c.T
            rest_y = rest_v @ c.T
            t_local = roma.rotvec_to_rotmat(tpose(model, self.shape).double())
            t_glob = model.local_to_global(t_local[None])[0]  # (J, 3, 3)
        parents = model.bone_parents
        self.parents = torch.as_tensor(parents, device=self.device)
        self._parent_or_root = self.parents.clamp(min=0)  # the root's own index for the root (its edge is zero)
        self.h0 = h0.to(self.device, dtype)
        edge = np.zeros((J, 3))
        for j in range(1, J):
            edge[j] = (h0[j] - h0[parents[j]]).cpu().numpy()
        self.edges = torch.as_tensor(edge, device=self.device, dtype=dtype)
        path = np.zeros((J, J))
        for j in range(J):
            k = j
            while k > 0:  # root's own edge is zero
                path[j, k] = 1.0
                k = parents[k]
        self.path = torch.as_tensor(path, device=self.device, dtype=dtype)
        # which driven segment owns each bone
        bone_seg = {}
        for s, name in enumerate(MVN_SEGMENTS):
            for b in self.mapping[name].bones:
                bone_seg[model.bone_index(b)] = s
        owner = np.zeros(J, dtype=np.int64)
        for j in range(J):
            k = j
            while k not in bone_seg:
                k = parents[k]
            owner[j] = bone_seg[k]
        self.owner = torch.as_tensor(owner, device=self.device)
        self.segment_bones = torch.as_tensor([model.bone_index(self.mapping.bone_of(s)) for s in MVN_SEGMENTS],
                                             device=self.device)  # fmt: skip
        b = torch.as_tensor(SEGMENT_TPOSE_FRAME, dtype=torch.float64)
        #: (S, 3, 3) constant: segment frame = A @ S
        self.seg_frame = (t_glob[self.segment_bones.cpu()].cpu().transpose(-1, -2) @ b).to(self.device, dtype)
        self._zero_rot = zr.to(self.device, dtype)
        self._zero_t = (zt.double() - h0).to(self.device, dtype)
        self._rest_y = rest_y.to(self.device, dtype).contiguous()
        self._skin = getattr(a, "_skinning_method", None)
        self._u_all = u.to(self.device, dtype)
        self._idx_all = idx.to(self.device)
        self._w_all = w.to(self.device, dtype)
        # the same weights as (vertex, bone) pairs with a nonzero weight, vertex by vertex (2.5 a vertex
        # of anny's 9 slots): skin_at reads only these
        nz = (w > 0).cpu()
        self._nz_ptr = torch.as_tensor(np.r_[0, np.cumsum(nz.sum(1).numpy())], device=self.device)
        self._nz_bone = idx.cpu()[nz].to(self.device)
        self._nz_w = w.cpu()[nz].to(self.device, dtype)
        self._nz_u = u.cpu()[nz].to(self.device, dtype)
        self._nz_wp: tuple | None = None  # the same as warp arrays, for _skin_sparse (made on first use)
        self.num_vertices = int(rest_v.shape[0])
        self._subsets: dict = {}
        self._linear: dict = {}
        self.set_vertices(None)
        self._init_hands(model)

    def _init_hands(self, model) -> None:
        """The finger bones the four hand openings move (:mod:`dualhuman_builder.body.hands`):
        per bone its open-hand rotation vector and opening slot, and every bone below one of them
        (they inherit the change), grouped by depth so :meth:`bone_rotations` walks down the
        fingers level by level."""
        from dualhuman_builder.body.hands import SIDES, open_hand, opening_slot

        with torch.no_grad():
            rest = model.rest(self.shape[None])
        heads = rest.bone_heads[0].double().cpu().numpy()
        verts = rest.vertices[0].double().cpu().numpy()
        names, parents = list(model.bone_names), np.asarray(model.bone_parents)
        rv, slot = {}, {}
        for side in SIDES:
            for b, R in open_hand(names, parents, heads, verts, model.vertex_bone(), side).items():
                rv[b] = roma.rotmat_to_rotvec(torch.as_tensor(R)).numpy()
                slot[b] = opening_slot(names, b)
        moved = set(rv)
        for j in range(len(parents)):  # parents precede children in anny's bone order
            if parents[j] >= 0 and parents[j] in moved:
                moved.add(j)
        depth = {}
        for j in sorted(moved):
            depth[j] = depth.get(int(parents[j]), 0) + 1
        order = sorted(moved)
        self._moved_by_openings = order
        #: ``(V,)`` int: which hand's openings move each vertex (a nonzero weight on a finger bone they
        #: turn): 1 the left, 2 the right, 0 neither
        w, idx = self._w_all.cpu().numpy(), self._idx_all.cpu().numpy()
        side = np.zeros(len(parents), np.int64)
        for j in order:
            side[j] = 1 + SIDES.index(names[j].rsplit(".", 1)[-1])
        self.opening_groups = np.where(w > 0, side[idx], 0).max(axis=1)
        #: ``(V,)`` bool: the vertices the hand openings move
        self.opening_vertices = self.opening_groups > 0
        # bones below an opened one keep a zero rotation vector (identity at any opening): they are
        # only re-composed with their parent's new rotation
        self._open_rv = torch.as_tensor(np.array([rv.get(j, np.zeros(3)) for j in order]), device=self.device, dtype=self.dtype)
        self._open_slot = torch.as_tensor([slot.get(j, 0) for j in order], device=self.device)
        self._open_levels = []
        for d in sorted(set(depth.values())):
            pos = [i for i, j in enumerate(order) if depth[j] == d]
            bones = [order[i] for i in pos]
            self._open_levels.append((torch.as_tensor(bones, device=self.device),
                                      torch.as_tensor(parents[bones], device=self.device),
                                      torch.as_tensor(pos, device=self.device)))  # fmt: skip

    def set_vertices(self, vertex_ids) -> None:
        """Skin only ``vertex_ids`` (None: all) in :meth:`pose`."""
        if vertex_ids is None:
            self.vertex_ids = None
            self._u, self._idx, self._w = self._u_all, self._idx_all, self._w_all
        else:
            ids = torch.as_tensor(np.asarray(vertex_ids, dtype=np.int64), device=self.device)
            self.vertex_ids = ids
            self._u, self._idx, self._w = self._u_all[ids], self._idx_all[ids], self._w_all[ids]

    # ------------------------------------------------------------------ forward
    def bone_rotations(self, seg_rot: torch.Tensor, opening: torch.Tensor | None = None) -> torch.Tensor:
        """``(B, S, 3, 3)`` driven-bone rotations -> ``(B, J, 3, 3)`` for every anny bone.
        ``opening (B, 4)`` (:data:`~dualhuman_builder.body.hands.OPENINGS`; None: all 0) opens the
        fingers: each moved finger bone's local rotation is its open-hand rotation with the angle
        scaled by its opening (0 the relaxed rest hand, 1 flat), differentiably."""
        # index_select rather than rot[:, idx]: the same values, and its backward is an index_add,
        # cheaper on the CPU than advanced indexing's accumulating index_put
        rot = seg_rot.index_select(1, self.owner)
        if opening is None:
            return rot
        rv = opening.index_select(1, self._open_slot)[..., None] * self._open_rv  # (B, M, 3)
        local = rotvec_to_rotmat(rv)
        for bones, parents, pos in self._open_levels:
            rot = rot.index_copy(1, bones, rot.index_select(1, parents) @ local.index_select(1, pos))
        return rot

    def add_linear(self, name: str, bones, vertex_ids) -> None:
        """Register ``bones (Jn,)`` and ``vertex_ids (n,)`` for :meth:`pose_linear`. None of them may
        be moved by the hand openings (their bones and skinning bones are not finger bones): those
        are linear in the driven rotations alone. See :meth:`pose_linear` for the matrix."""
        bones = np.asarray(bones, np.int64).ravel()
        ids = np.asarray(vertex_ids, np.int64).ravel()
        fingers = set(self._moved_by_openings)
        idx = self._idx_all.cpu().numpy()[ids]
        w = self._w_all.cpu().double().numpy()[ids]
        if fingers.intersection(bones.tolist()) or fingers.intersection(idx[w > 0].tolist()):
            raise ValueError(f"linear subset {name!r}: bones or vertices moved by the hand openings")
        S = len(MVN_SEGMENTS)
        J = len(self.parents)
        owner = self.owner.cpu().numpy()
        # E[i, s]: the edges on the path root -> i that segment s's rotation turns, summed (J, S, 3);
        # bone i's head is transl + sum_s A_s E[i, s]
        par_owner = owner[self.parents.clamp(min=0).cpu().numpy()]
        turned = np.zeros((J, S, 3))
        turned[np.arange(J), par_owner] = self.edges.cpu().double().numpy()
        E = np.einsum("ij,jsd->isd", self.path.cpu().double().numpy(), turned)
        # G[v, s]: sum_k w_vk ([owner(k) = s] u_vk + E[k, s]); vertex v is (sum_k w_vk) transl + sum_s A_s G[v, s]
        u = self._u_all.cpu().double().numpy()[ids]  # (n, K, 3)
        G = np.einsum("nk,nksd->nsd", w, E[idx])
        np.add.at(G, (np.arange(len(ids))[:, None].repeat(idx.shape[1], 1), owner[idx]), w[..., None] * u)
        L = np.concatenate([E[bones], G], 0)  # (Jn + n, S, 3)
        mat = torch.as_tensor(L.transpose(1, 2, 0).reshape(S * 3, -1), device=self.device, dtype=self.dtype)
        wsum = torch.as_tensor(np.r_[np.ones(len(bones)), w.sum(1)], device=self.device, dtype=self.dtype)
        self._linear[name] = (mat, wsum, len(bones))

    def pose_linear(self, seg_rot: torch.Tensor, transl: torch.Tensor, name: str) -> tuple[torch.Tensor, torch.Tensor]:
        """Heads ``(B, Jn, 3)`` of the bones and positions ``(B, n, 3)`` of the vertices registered
        with :meth:`add_linear`, for driven-bone rotations ``seg_rot (B, S, 3, 3)`` and ``transl
        (B, 3)`` (metres, Y-up): the same as :meth:`pose` (any hand opening), in one matrix product.
        Every bone outside the fingers turns with its driven segment, so a head is ``transl + sum_s
        A_s E_s`` and a skinned vertex ``(sum_k w_k) transl + sum_s A_s G_s``, with ``E``, ``G``
        constant ``(S, 3)`` per bone and vertex (see :meth:`add_linear`): ``(B, 3, 3S) @ (3S, Jn + n)``
        instead of per-bone rotations, a tree walk and a nine-bone blend per vertex (the fitter's
        skeleton terms read only these, so its skeleton energy skins no mesh)."""
        mat, wsum, nb = self._linear[name]
        out = linear_pose(seg_rot, transl, mat, wsum)  # (B, Jn + n, 3)
        return out[:, :nb], out[:, nb:]

    def linear(self, name: str) -> tuple[torch.Tensor, torch.Tensor, int]:
        """The matrix ``(3S, Jn + n)``, the weight sums ``(Jn + n,)`` and the bone count ``Jn`` that
        :meth:`add_linear` registered as ``name`` (for :func:`linear_pose` on stacks of rigs)."""
        return self._linear[name]

    def add_subset(self, name: str, vertex_ids) -> None:
        """Register a named vertex subset that :meth:`pose` can skin with ``vertices=name``."""
        ids = torch.as_tensor(np.asarray(vertex_ids, dtype=np.int64), device=self.device)
        self._subsets[name] = (self._u_all[ids], self._idx_all[ids], self._w_all[ids])

    def pose(self, seg_rot: torch.Tensor, transl: torch.Tensor, vertices: bool | str = True,
             opening: torch.Tensor | None = None) -> Posed:  # fmt: skip
        """Pose ``seg_rot (B, S, 3, 3)``, ``transl (B, 3)``, hand ``opening (B, 4)`` or None (see
        :meth:`bone_rotations`). ``vertices``: True skins the current vertex set
        (:meth:`set_vertices`), a name skins a subset from :meth:`add_subset`, False none."""
        rot = self.bone_rotations(seg_rot, opening)
        parent_rot = rot.index_select(1, self._parent_or_root)
        e = (parent_rot @ self.edges[None, :, :, None])[..., 0]  # (B, J, 3); root's edge is zero
        heads = transl[:, None, :] + torch.einsum("jk,bkd->bjd", self.path, e)
        verts = None
        if isinstance(vertices, str):
            u, idx, w = self._subsets[vertices]
            p = (rot[:, idx] @ u[None, ..., None])[..., 0] + heads[:, idx]
            return Posed(heads, rot, (p * w[None, ..., None]).sum(2))
        if vertices and self.vertex_ids is None and self._sparse_ok(rot, heads):
            verts = self._skin_sparse(rot, heads)
        elif vertices and self.vertex_ids is None and self._skin is not None and self._skin.__module__.endswith("warp_skinning"):
            # the whole mesh: anny's own skinning kernel with T_k = [A_k Z_k | A_k z_k + h_k]
            t = torch.zeros(*rot.shape[:2], 4, 4, dtype=rot.dtype, device=rot.device)
            t[..., :3, :3] = rot @ self._zero_rot
            t[..., :3, 3] = (rot @ self._zero_t[..., None])[..., 0] + heads
            t[..., 3, 3] = 1.0
            rest = self._rest_y.expand(rot.shape[0], -1, -1)
            verts = self._skin(rest, bone_weights=self._w[None], bone_indices=self._idx[None], bone_transforms=t)
        elif vertices and self._u.shape[0]:
            rk = rot[:, self._idx]  # (B, V, K, 3, 3)
            p = (rk @ self._u[None, ..., None])[..., 0] + heads[:, self._idx]
            verts = (p * self._w[None, ..., None]).sum(2)
        return Posed(heads, rot, verts)

    def _sparse_ok(self, rot: torch.Tensor, heads: torch.Tensor) -> bool:
        """Whether :meth:`_skin_sparse` can skin these bones: float32 on the CPU, no gradient wanted."""
        grad = torch.is_grad_enabled() and (rot.requires_grad or heads.requires_grad)
        return not grad and _warp_cpu(rot, heads) and self._u_all.shape[0] > 0

    def _skin_sparse(self, rot: torch.Tensor, heads: torch.Tensor) -> torch.Tensor:
        """Every vertex ``(B, V, 3)`` for bone rotations ``rot (B, J, 3, 3)`` and heads ``heads (B, J,
        3)``, without gradient: the linear blend ``v = sum_k w_vk (A_k u_vk + h_k)`` over each vertex's
        nonzero weights only (2.5 of anny's 9 slots on average; :func:`_skin_nonzero`, one warp CPU
        kernel), where anny's own kernel reads all nine slots through 4x4 transforms: the same
        vertices to float rounding, in fewer operations. The fit skins its full meshes without
        gradient only (to find the contacts, to measure depths), so that is where this runs."""
        B, V = rot.shape[0], self.num_vertices
        out = torch.empty(B, V, 3, dtype=torch.float32)
        if B == 0:
            return out
        r = wp.from_torch(rot.detach().contiguous(), dtype=wp.mat33)
        h = wp.from_torch(heads.detach().contiguous(), dtype=wp.vec3)
        wp.launch(_skin_nonzero, dim=(B, V), inputs=[r, h, *self._nonzero_wp()], outputs=[wp.from_torch(out, dtype=wp.vec3)],
                  device="cpu")  # fmt: skip
        return out

    def _nonzero_wp(self) -> tuple:
        """The nonzero skinning weights as warp CPU arrays (made on first use): per vertex the range
        ``ptr[v] .. ptr[v + 1] - 1`` of its ``bone``, ``u`` and ``w`` rows."""
        if self._nz_wp is None:
            self._nz_wp = (wp.array(self._nz_ptr.cpu().numpy().astype(np.int32), dtype=wp.int32, device="cpu"),
                           wp.array(self._nz_bone.cpu().numpy().astype(np.int32), dtype=wp.int32, device="cpu"),
                           wp.array(self._nz_u.cpu().numpy().astype(np.float32), dtype=wp.vec3, device="cpu"),
                           wp.array(self._nz_w.cpu().numpy().astype(np.float32), dtype=wp.float32, device="cpu"))  # fmt: skip
        return self._nz_wp

    def skin_at(self, posed: Posed, frames: torch.Tensor, vertex_ids: torch.Tensor) -> torch.Tensor:
        """Positions ``(M, 3)`` of vertices ``vertex_ids (M,)`` in frames ``frames (M,)`` (rows of
        ``posed``), differentiable through ``posed.rot`` and ``posed.heads``: the same linear blend
        skinning as :meth:`pose`, for scattered (frame, vertex) pairs only. The collision term needs
        a gradient at a few thousand such pairs, not at every vertex of every frame. Only each
        vertex's nonzero weights are read (2.5 of anny's 9 slots on average). On the CPU in float32
        two warp kernels do it (:class:`_SkinAt`), elsewhere tensor operations (:meth:`_skin_at_torch`)."""
        vertex_ids, frames = vertex_ids.to(self.device), frames.to(self.device)
        if _warp_cpu(posed.rot, posed.heads):
            return _SkinAt.apply(posed.rot, posed.heads, frames, vertex_ids, self._nonzero_wp())
        return self._skin_at_torch(posed, frames, vertex_ids)

    def _skin_at_torch(self, posed: Posed, frames: torch.Tensor, vertex_ids: torch.Tensor) -> torch.Tensor:
        """:meth:`skin_at` in tensor operations, on any device and dtype: the bones as rows of one table
        (``index_select``, whose backward adds rows: cheaper than a 4-D gather, whose backward
        scatters)."""
        first = self._nz_ptr[vertex_ids]
        n = self._nz_ptr[vertex_ids + 1] - first  # nonzero weights of each vertex
        which = torch.repeat_interleave(torch.arange(len(vertex_ids), device=self.device), n)  # (N,) pair -> point
        start = torch.cumsum(n, 0) - n
        pair = first[which] + torch.arange(len(which), device=self.device) - start[which]  # rows of the _nz_ arrays
        B, J = posed.rot.shape[:2]
        # each pair's bone rotation and head, read as rows of one (B J, 12) table: the backward pass
        # adds rows back (index_add) instead of scattering into a 4-D tensor
        table = torch.cat([posed.rot.reshape(B * J, 9), posed.heads.reshape(B * J, 3)], dim=1)
        g = table.index_select(0, frames[which] * J + self._nz_bone[pair])
        p = (g[:, :9].reshape(-1, 3, 3) @ self._nz_u[pair, :, None])[..., 0] + g[:, 9:]
        out = torch.zeros(len(vertex_ids), 3, dtype=p.dtype, device=p.device)
        return out.index_add(0, which, p * self._nz_w[pair, None])

    def segment_frames(self, seg_rot: torch.Tensor) -> torch.Tensor:
        """Suit-style segment orientations ``(B, S, 3, 3)`` of driven-bone rotations."""
        return seg_rot @ self.seg_frame

    def retarget(self, seg_frames: torch.Tensor) -> torch.Tensor:
        """Closed-form retarget: suit segment orientations ``(B, S, 3, 3)`` -> driven-bone
        rotations ``A = R_seg S^T``."""
        return seg_frames @ self.seg_frame.transpose(-1, -2)

    def local_pose(self, seg_rot: torch.Tensor, opening: torch.Tensor | None = None) -> torch.Tensor:
        """anny pose parameters ``(B, J, 3)`` rotation vectors (what a BodyTrack stores)."""
        rot = self.bone_rotations(seg_rot, opening)
        return roma.rotmat_to_rotvec(self.model.global_to_local(rot))


def linear_pose(seg_rot: torch.Tensor, transl: torch.Tensor, mat: torch.Tensor, wsum: torch.Tensor) -> torch.Tensor:
    """:meth:`BodyRig.pose_linear`'s product for any leading axes ``...``: ``seg_rot (..., S, 3, 3)``,
    ``transl (..., 3)``, ``mat (..., 3S, N)`` and ``wsum (..., N)`` (broadcast against the leading
    axes: one rig's, or a stack of rigs' with a frame axis of 1) -> positions ``(..., N, 3)``."""
    lead = seg_rot.shape[:-3]
    x = seg_rot.transpose(-3, -2).reshape(*lead, 3, -1)  # (..., 3, 3S)
    if len(lead) >= 2 and mat.dim() == x.dim() and mat.shape[-3] == 1:
        # a stack of rigs with a frame axis of 1: the frames folded into the rows, one (3n, 3S) @ (3S, N)
        # product per rig, instead of broadcasting `mat` to every frame (a copy of it per frame and
        # evaluation, and many 3 x 3S @ 3S x N products)
        y = (x.reshape(*lead[:-1], lead[-1] * 3, x.shape[-1]) @ mat.squeeze(-3)).reshape(*lead, 3, -1)
    else:
        y = x @ mat
    return y.transpose(-1, -2) + wsum[..., :, None] * transl[..., None, :]


def _warp_cpu(rot: torch.Tensor, heads: torch.Tensor) -> bool:
    """Whether the warp CPU kernels below can read these bones: float32 tensors on the CPU."""
    return rot.dtype == heads.dtype == torch.float32 and rot.device.type == "cpu"


@wp.func
def _blend(rot: wp.array2d(dtype=wp.mat33), heads: wp.array2d(dtype=wp.vec3), b: int, v: int, ptr: wp.array(dtype=wp.int32),
           bone: wp.array(dtype=wp.int32), u: wp.array(dtype=wp.vec3), w: wp.array(dtype=wp.float32)):  # fmt: skip
    """Vertex ``v`` of frame ``b``: ``sum_i w_i (rot[b, bone_i] u_i + heads[b, bone_i])`` over its nonzero
    weights ``i`` in ``ptr[v] .. ptr[v + 1] - 1``."""
    acc = wp.vec3(0.0, 0.0, 0.0)
    for i in range(ptr[v], ptr[v + 1]):
        j = bone[i]
        acc += w[i] * (rot[b, j] * u[i] + heads[b, j])
    return acc


@wp.kernel
def _skin_nonzero(rot: wp.array2d(dtype=wp.mat33), heads: wp.array2d(dtype=wp.vec3), ptr: wp.array(dtype=wp.int32),
                  bone: wp.array(dtype=wp.int32), u: wp.array(dtype=wp.vec3), w: wp.array(dtype=wp.float32),
                  out: wp.array2d(dtype=wp.vec3)):  # fmt: skip
    """Every vertex ``v`` of every frame ``b`` (:meth:`BodyRig._skin_sparse`)."""
    b, v = wp.tid()
    out[b, v] = _blend(rot, heads, b, v, ptr, bone, u, w)


@wp.kernel
def _skin_pairs(rot: wp.array2d(dtype=wp.mat33), heads: wp.array2d(dtype=wp.vec3), frames: wp.array(dtype=wp.int64),
                verts: wp.array(dtype=wp.int64), ptr: wp.array(dtype=wp.int32), bone: wp.array(dtype=wp.int32),
                u: wp.array(dtype=wp.vec3), w: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.vec3)):  # fmt: skip
    """Point ``i``: vertex ``verts[i]`` of frame ``frames[i]`` (:class:`_SkinAt`)."""
    i = wp.tid()
    out[i] = _blend(rot, heads, int(frames[i]), int(verts[i]), ptr, bone, u, w)


@wp.kernel
def _skin_pairs_grad(grad: wp.array(dtype=wp.vec3), frames: wp.array(dtype=wp.int64), verts: wp.array(dtype=wp.int64),
                     ptr: wp.array(dtype=wp.int32), bone: wp.array(dtype=wp.int32), u: wp.array(dtype=wp.vec3),
                     w: wp.array(dtype=wp.float32), grad_rot: wp.array2d(dtype=wp.mat33),
                     grad_heads: wp.array2d(dtype=wp.vec3)):  # fmt: skip
    """The gradient of :func:`_skin_pairs`: ``w g u^T`` into each read bone's rotation, ``w g`` into its head."""
    i = wp.tid()
    b = int(frames[i])
    v = int(verts[i])
    g = grad[i]
    for k in range(ptr[v], ptr[v + 1]):
        j = bone[k]
        wp.atomic_add(grad_rot, b, j, w[k] * wp.outer(g, u[k]))
        wp.atomic_add(grad_heads, b, j, w[k] * g)


class _SkinAt(torch.autograd.Function):
    """:meth:`BodyRig.skin_at` on the CPU in float32 as two warp kernels (forward and backward) instead of
    ~10 tensor operations over every (point, weight) pair and their backward: a collision pass's
    evaluation reads ~5,000-50,000 points, whose gathers and scatters as tensor operations would be
    most of its cost (``benchmarks/probes/probe_skin_at.py`` times both; docs/decisions/0020-collision-term-cost.md).
    A CPU launch runs its points in order, so the gradient's sums are the same from run to run (the rig
    test backs both)."""

    @staticmethod
    def forward(ctx, rot, heads, frames, verts, nz):
        rot, heads = rot.detach().contiguous(), heads.detach().contiguous()
        frames, verts = frames.to(torch.int64).contiguous(), verts.to(torch.int64).contiguous()
        out = torch.empty(len(verts), 3, dtype=torch.float32)
        ctx.save_for_backward(frames, verts)
        ctx.nz, ctx.shape = nz, rot.shape[:2]
        if len(verts):
            wp.launch(_skin_pairs, dim=len(verts), device="cpu",
                      inputs=[wp.from_torch(rot, dtype=wp.mat33), wp.from_torch(heads, dtype=wp.vec3),
                              wp.from_torch(frames), wp.from_torch(verts), *nz], outputs=[wp.from_torch(out, dtype=wp.vec3)])  # fmt: skip
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        frames, verts = ctx.saved_tensors
        B, J = ctx.shape
        grad_rot = torch.zeros(B, J, 3, 3, dtype=torch.float32)
        grad_heads = torch.zeros(B, J, 3, dtype=torch.float32)
        if len(verts):
            wp.launch(_skin_pairs_grad, dim=len(verts), device="cpu",
                      inputs=[wp.from_torch(grad.to(torch.float32).contiguous(), dtype=wp.vec3), wp.from_torch(frames),
                              wp.from_torch(verts), *ctx.nz],
                      outputs=[wp.from_torch(grad_rot, dtype=wp.mat33), wp.from_torch(grad_heads, dtype=wp.vec3)])  # fmt: skip
        return grad_rot, grad_heads, None, None, None


def sole_vertices(model, per_foot: int = 40) -> dict[str, np.ndarray]:
    """The ``per_foot`` lowest vertices under each foot of anny's rest mesh (foot and toe bones):
    the points that touch the floor in stance. ``{"L": (n,), "R": (n,)}`` vertex indices."""
    out = {}
    with torch.no_grad():
        rest = model.rest().vertices[0].cpu().numpy()
    bone_of = model.vertex_bone()
    for side in ("L", "R"):
        feet = [i for i, n in enumerate(model.bone_names) if n.endswith(f".{side}") and (n.startswith("foot") or n.startswith("toe"))]
        cand = np.flatnonzero(np.isin(bone_of, feet))
        out[side] = cand[np.argsort(rest[cand, 1])[:per_foot]]
    return out


#: the bones whose vertices make the torso (root, pelvis, spine): see :func:`torso_vertices`
TORSO_BONES = ("root", "pelvis", "spine")


def torso_vertices(model) -> np.ndarray:
    """``(n,)`` indices of anny's vertices skinned mostly to the root, pelvis and spine bones (~1,400
    of 13,718). Their centroid is where the body is: unlike the whole body's, it does not move when
    the arms wrap round a partner, so two actors' torso centroids stay far apart in a close hug. The
    collision term's coincidence guard compares them (docs/decisions/0014-hand-openings-and-torso-guard.md)."""
    bones = [i for i, n in enumerate(model.bone_names) if n.startswith(TORSO_BONES)]
    return np.flatnonzero(np.isin(model.vertex_bone(), bones))

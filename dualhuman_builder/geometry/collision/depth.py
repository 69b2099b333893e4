"""The differentiable depth of located contacts, the robust penalty, and the depth diagnostics.

A contact is a query vertex ``p`` with the closest point ``c = sum_k w_k x_k`` on a triangle
``x_0 x_1 x_2`` of the other body (barycentric weights ``w`` from the query, held). Its depth is
``(c - p) . n`` with ``n`` held fixed: for an exact evaluation ``n = (c - p) / |c - p|``, which makes
the gradient that of the distance itself (``-n`` on ``p``, ``+w_k n`` on the triangle's corners: the
vertex is pushed out and the surface pushed back); for held contacts ``n`` is the outward normal
found when they were located (:mod:`.linearised`). Positions in metres; the loss is dimensionless.
"""

from __future__ import annotations

import numpy as np
import torch

from dualhuman_builder.geometry.collision.locate import Contacts

#: the robust penalties ``rho(d)`` of a depth ``d`` at scale ``s`` (see :func:`robust_penalty`)
RHOS = ("pseudo_huber", "geman_mcclure", "squared")


def robust_penalty(depth: torch.Tensor, rho: str, sigma: float) -> torch.Tensor:
    """``rho(depth)`` (depths in metres, >= 0; dimensionless) at scale ``sigma`` metres:
    ``"pseudo_huber"`` ``sqrt(1 + (d/s)^2) - 1`` (quadratic for shallow depths, linear for deep ones,
    so a deep vertex keeps a push of ``1/s``), ``"geman_mcclure"`` ``(d/s)^2 / ((d/s)^2 + 1)``
    (saturates: deep overlaps are barely pushed), ``"squared"`` ``(d/s)^2``."""
    x = depth / sigma
    if rho == "pseudo_huber":
        return torch.sqrt(1.0 + x * x) - 1.0
    if rho == "geman_mcclure":
        return x * x / (x * x + 1.0)
    return x * x


def outward_normals(diff: torch.Tensor, x: torch.Tensor, inside: torch.Tensor | None = None) -> torch.Tensor:
    """The obstacle's outward unit normal ``(M, 3)`` at each contact's closest point: along ``diff =
    c - p`` (``(M, 3)``) for a vertex inside, against it outside (``inside (M,)`` bool; None: all
    inside), and the triangle ``x (M, 3, 3)``'s own normal where ``p`` lies on it (``|diff| <= 1e-9``)."""
    dist = diff.norm(dim=1, keepdim=True)
    fn = torch.linalg.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], dim=1)
    fn = fn / fn.norm(dim=1, keepdim=True).clamp_min(1e-20)
    d = diff if inside is None else torch.where(inside[:, None], diff, -diff)
    return torch.where(dist > 1e-9, d / dist.clamp_min(1e-20), fn)


def _assembly(c: Contacts, V: int, dev, dtype, obstacle_faces: np.ndarray) -> tuple:
    """Index tensors that read each (body, frame, vertex) the contacts ``c`` need once: ``reads``
    ``[(body, frames, vertices)]``, the row of each contact's query point ``(M,)`` and of its
    triangle's corners ``(M, 3)`` in the concatenated reads, the weights ``(M, 3)`` and frames ``(M,)``."""
    M = len(c.frame)
    tri = obstacle_faces[c.face]  # (M, 3)
    q_idx = np.empty(M, np.int64)
    o_idx = np.empty((M, 3), np.int64)
    reads, offset = [], 0
    for body in (0, 1):  # side 0: b's vertices (body 1) against a (body 0); side 1: a's against b
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
    return ((str(dev), dtype), reads, torch.as_tensor(q_idx, device=dev), torch.as_tensor(o_idx, device=dev),
            torch.as_tensor(c.bary, device=dev, dtype=dtype), torch.as_tensor(c.frame, device=dev))  # fmt: skip


def assemble(c: Contacts, B: int, V: int, dev, dtype, points, obstacle_faces: np.ndarray, rho,
             normals: np.ndarray | None = None) -> torch.Tensor:  # fmt: skip
    """Differentiable ``sum rho(depth) / (2V)`` per frame ``(B,)`` over the contacts ``c``, depths
    clamped at 0; positions from ``points(body, frames, vertices) -> (M, 3)`` (body 0: a, 1: b), each
    (body, frame, vertex) read once; ``rho``: depths -> penalties. ``normals (M, 3)``: the outward
    normals held at the contacts; None: every contact is inside and ``n = (c - p) / |c - p|``, the
    exact distance's gradient. The read indices are cached on ``c`` per device and dtype."""
    out = torch.zeros(B, device=dev, dtype=dtype)
    if len(c.frame) == 0:
        return out
    if c.assembly is None or c.assembly[0] != (str(dev), dtype):
        c.assembly = _assembly(c, V, dev, dtype, obstacle_faces)
    _, reads, q_t, o_t, w, frame_t = c.assembly
    pos = torch.cat([points(body, f, v).to(dtype) for body, f, v in reads])
    p = pos.index_select(0, q_t)  # (M, 3); index_select: its backward (index_add) is cheaper than indexing's
    x = pos.index_select(0, o_t.reshape(-1)).reshape(-1, 3, 3)  # (M, 3, 3)
    closest = (w[:, :, None] * x).sum(dim=1)
    diff = closest - p
    if normals is None:
        with torch.no_grad():
            n = outward_normals(diff, x)
    else:
        n = torch.as_tensor(normals, device=dev, dtype=dtype)
    depth = (diff * n).sum(dim=1).clamp_min(0.0)
    out = out.index_add(0, frame_t, rho(depth))
    return out / (2 * V)


def depth_maps(c: Contacts, B: int, V: int, dev, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """``(depth_a (B, V), depth_b (B, V))``, metres, no gradient: how deep each vertex of a lies
    inside b and of b inside a, from the contacts (0 where none; negative for those outside within
    a margin)."""
    maps = []
    for side in (1, 0):  # depth_a: a's vertices against b (side 1)
        d = np.zeros((B, V), np.float64)
        m = c.side == side
        d[c.frame[m], c.vert[m]] = c.depth[m]
        maps.append(torch.as_tensor(d, device=dev, dtype=dtype))
    return maps[0], maps[1]


def penetration_summary(depth_a: torch.Tensor, depth_b: torch.Tensor, active: torch.Tensor, eps: float) -> dict:
    """The diagnostics of the depth maps ``(B, V)`` as numpy, entries ``<= eps`` (metres) counting as 0:
    ``max_depth_m (B,)``, ``share (B,)`` (penetrating share of both bodies' ``2V`` vertices),
    ``penetrating (B,)`` int64, ``active (B,)`` bool, ``depth_a``, ``depth_b`` ``(B, V)`` float64."""
    da = depth_a.double().cpu().numpy()
    db = depth_b.double().cpu().numpy()
    both = np.concatenate([da, db], axis=1)
    pen = both > eps
    return {
        "max_depth_m": np.where(pen, both, 0.0).max(axis=1),
        "share": pen.sum(axis=1) / (2.0 * da.shape[1]),
        "penetrating": pen.sum(axis=1).astype(np.int64),
        "active": active.cpu().numpy(),
        "depth_a": np.where(da > eps, da, 0.0),
        "depth_b": np.where(db > eps, db, 0.0),
    }

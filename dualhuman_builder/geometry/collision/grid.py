"""Method ``"grid"``: Jiang et al.'s voxel formulation, kept for comparison with the exact methods.

Per body and active frame, a ``R^3`` grid of the inside distance (0 outside) over the body's
obstacle-vertex box grown by 20 %, filled by closest-point queries, is sampled at the other body's
vertices by trilinear interpolation (``torch.nn.functional.grid_sample``). The grid is a constant, so
each direction pushes only the querying body's vertices; its cells are a few centimetres on a body.
Cost and error against the exact methods: ``docs/decisions/0010-exact-collision-term.md``, measured
by ``benchmarks/bench_collision.py``.
"""

from __future__ import annotations

import numpy as np
import torch

from dualhuman_builder.geometry.collision.queries import MeshPool

#: growth of a body's box for its grid, as a share of the box's size (half of it on each side), so
#: that the surface lies inside the grid with cells to spare
GRID_MARGIN = 0.2


def grid_terms(pool: MeshPool, obstacle_vertices: np.ndarray, rho, R: int, va: torch.Tensor, vb: torch.Tensor,
               frames: np.ndarray) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # fmt: skip
    """Loss ``(B,)`` (``sum rho(depth) / (2V)``, differentiable w.r.t. the sampled vertices) and the
    interpolated depth maps ``depth_a``, ``depth_b`` ``(B, V)`` (metres; a inside b, b inside a) of the
    bodies ``va``, ``vb`` ``(B, V, 3)`` in the active ``frames``, with ``R`` grid cells per axis. The
    query points are the ``obstacle_vertices``, as for the exact methods."""
    import torch.nn.functional as tnf

    B, V = va.shape[:2]
    dev, dtype = va.device, va.dtype
    ft = torch.as_tensor(frames, device=dev)
    A = va.detach()[ft].cpu().numpy().astype(np.float32)
    Bv = vb.detach()[ft].cpu().numpy().astype(np.float32)
    K = len(frames)
    O = np.empty((2 * K, V, 3), np.float32)
    O[0::2], O[1::2] = A, Bv  # grid 2k: inside a (sampled at b), 2k+1: inside b (sampled at a)
    ov = O[:, obstacle_vertices]
    lo, hi = ov.min(axis=1), ov.max(axis=1)
    pad = GRID_MARGIN * (hi - lo) / 2
    lo, hi = lo - pad, hi + pad
    t = np.linspace(0.0, 1.0, R, dtype=np.float32)
    zz, yy, xx = np.meshgrid(t, t, t, indexing="ij")  # phi[z, y, x], grid_sample's (D, H, W)
    unit = np.stack([xx, yy, zz], axis=-1).reshape(-1, 3)
    nodes = lo[:, None] + unit[None] * (hi - lo)[:, None]  # (P, R^3, 3)
    ids = pool.meshes(O)
    P = 2 * K
    which = np.repeat(np.arange(P, dtype=np.int32), R**3)
    big = np.repeat(np.linalg.norm(hi - lo, axis=1), R**3)
    sd, face, _ = pool.query(ids, which, nodes.reshape(-1, 3), big)
    phi = np.where((face >= 0) & (sd < 0), -sd, 0.0).astype(np.float32).reshape(P, 1, R, R, R)
    phi_t = torch.as_tensor(phi, device=dev, dtype=dtype)
    lo_t = torch.as_tensor(lo, device=dev, dtype=dtype)
    hi_t = torch.as_tensor(hi, device=dev, dtype=dtype)
    query = torch.stack([vb[ft], va[ft]], dim=1).reshape(P, V, 3)  # grid 2k sampled at b
    g = 2.0 * (query - lo_t[:, None]) / (hi_t - lo_t)[:, None] - 1.0
    depth = tnf.grid_sample(phi_t, g[:, None, None], mode="bilinear", padding_mode="zeros",
                            align_corners=True).reshape(P, V)  # fmt: skip
    surface = torch.zeros(V, device=dev, dtype=dtype)
    surface[torch.as_tensor(obstacle_vertices, device=dev)] = 1.0
    depth = depth.clamp_min(0.0) * surface
    per = rho(depth).sum(dim=1).reshape(K, 2).sum(dim=1) / (2 * V)
    loss = torch.zeros(B, device=dev, dtype=dtype).index_add(0, ft, per)
    dd = depth.detach().reshape(K, 2, V)
    depth_b = torch.zeros(B, V, device=dev, dtype=dtype)
    depth_a = torch.zeros_like(depth_b)
    depth_b[ft] = dd[:, 0]
    depth_a[ft] = dd[:, 1]
    return loss, depth_a, depth_b

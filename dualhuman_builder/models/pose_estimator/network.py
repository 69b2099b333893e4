"""The two-person pose estimator's network (the Dual-Human paper, §3.2): an image backbone, a
decoder-only Transformer over Pose, Transl, Prob and Track queries with interaction-aware
self-attention, and the heads; plus :func:`to_camera`, which turns a translation output into a root
position in camera metres.

* **Backbone** (:class:`ResNetBackbone`): a small ResNet of basic blocks with GroupNorm (any batch
  size, the same in training and evaluation), plain torch, trained from scratch: the paper's HRNet-W48
  needs ImageNet weights that cannot be downloaded here. ``backbone_width`` channels in the first stage,
  doubled per stage; ``backbone_blocks`` blocks per stage; stride 2 in the stem and in every stage but
  the first (a 64-pixel image gives 8 x 8 tokens with three stages). ``backbone_weights``: a local
  safetensors state dict of this backbone, loaded when the module is built.
* **Tokens**: the features projected to ``d_model`` plus a fixed 2-D sine positional encoding (DETR's:
  half the channels encode the row, half the column).
* **Decoder** (:class:`DecoderLayer`, pre-norm): per layer the intra-human then the inter-human masked
  self-attention (:mod:`.attention`), or one plain self-attention with ``interaction_attention =
  false``; cross-attention to the image tokens; a feed-forward network.
* **Queries**: one learned embedding per query (:data:`.attention.NUM_QUERIES`). A ``Track`` query adds
  a projection of the previous frame's root of its person (``prev_root``, the ``transl`` of the previous
  rendered frame) where ``has_prev``, and a learned "no track" embedding elsewhere.
* **Heads**: per Pose query a joint in metres relative to the person's root, in camera axes (X right,
  Y down, Z forward; the root's own output is subtracted, so joint 0 is exactly 0); per Transl query the
  normalised translation ``(u_n, v_n, z_n)`` of :func:`~dualhuman_builder.export.writer.normalised_root`;
  per Prob query a logit of the saliency (the share of the person's joints visible).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.models.pose_estimator.attention import (JOINTS, NUM_QUERIES, PER_PERSON, PERSONS, PROB, TRACK, TRANSL,
                                                              inter_mask, intra_mask, query_index)  # fmt: skip

#: ImageNet statistics, so a user's backbone weights trained the usual way see the inputs they expect.
IMAGE_MEAN = (0.485, 0.456, 0.406)
IMAGE_STD = (0.229, 0.224, 0.225)


def _groups(channels: int) -> int:
    for g in (8, 4, 2):
        if channels % g == 0:
            return g
    return 1


class BasicBlock(nn.Module):
    """Two 3 x 3 convolutions with GroupNorm and a residual (a 1 x 1 projection where the shape changes)."""

    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.norm1 = nn.GroupNorm(_groups(cout), cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.norm2 = nn.GroupNorm(_groups(cout), cout)
        self.skip = None
        if stride != 1 or cin != cout:
            self.skip = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.GroupNorm(_groups(cout), cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = torch.relu(self.norm1(self.conv1(x)))
        y = self.norm2(self.conv2(y))
        return torch.relu(y + (x if self.skip is None else self.skip(x)))


class ResNetBackbone(nn.Module):
    """Image ``(B, 3, S, S)`` in [0, 1] -> features ``(B, C, S / stride, S / stride)`` (module docstring)."""

    def __init__(self, width: int = 16, blocks: list[int] | tuple[int, ...] = (1, 1, 1)):
        super().__init__()
        if int(width) < 1 or not blocks or any(int(n) < 1 for n in blocks):
            raise DualhumanError(f"backbone width {width!r} and blocks {list(blocks)!r} cannot build a network",
                                 fix="use a positive width and at least one stage of at least one block, e.g. "
                                     "--set backbone_width=16 --set backbone_blocks='[1, 1, 1]'")  # fmt: skip
        width = int(width)
        self.stem = nn.Sequential(nn.Conv2d(3, width, 3, 2, 1, bias=False), nn.GroupNorm(_groups(width), width), nn.ReLU())
        layers, cin = [], width
        for i, n in enumerate(blocks):
            cout = width * 2**i
            for k in range(int(n)):
                layers.append(BasicBlock(cin, cout, 2 if (k == 0 and i > 0) else 1))
                cin = cout
        self.stages = nn.Sequential(*layers)
        self.out_channels = cin
        self.stride = 2 ** len(blocks)
        self.register_buffer("mean", torch.tensor(IMAGE_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGE_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.stages(self.stem((image - self.mean) / self.std))


def sine_positions(height: int, width: int, dim: int, device=None) -> torch.Tensor:
    """DETR's 2-D sine positional encoding ``(height * width, dim)``, row-major: the first ``dim / 2``
    channels encode the row, the others the column (sin and cos interleaved, temperature 10000)."""
    if dim % 4:
        raise DualhumanError(f"d_model must be a multiple of 4 for the 2-D positional encoding, got {dim}",
                             fix="use e.g. --set d_model=128")  # fmt: skip
    half = dim // 2
    freq = 10000.0 ** (2 * (torch.arange(half // 2, device=device, dtype=torch.float32)) / half)
    ys = (torch.arange(height, device=device, dtype=torch.float32) + 0.5) / height * 2 * math.pi
    xs = (torch.arange(width, device=device, dtype=torch.float32) + 0.5) / width * 2 * math.pi

    def enc(v: torch.Tensor) -> torch.Tensor:
        a = v[:, None] / freq[None]
        return torch.stack([a.sin(), a.cos()], dim=-1).flatten(1)  # (n, half)

    ey, ex = enc(ys), enc(xs)
    return torch.cat([ey[:, None].expand(height, width, half), ex[None].expand(height, width, half)], dim=-1).reshape(-1, dim)


class DecoderLayer(nn.Module):
    """Self-attention (two masked stages, or one plain stage), cross-attention to the image tokens, a
    feed-forward network; pre-norm residuals."""

    def __init__(self, d_model: int, heads: int, ff: int, dropout: float, interaction: bool):
        super().__init__()
        self.interaction = bool(interaction)
        self.norm_intra = nn.LayerNorm(d_model)
        self.intra = nn.MultiheadAttention(d_model, heads, dropout=dropout, batch_first=True)
        if self.interaction:
            self.norm_inter = nn.LayerNorm(d_model)
            self.inter = nn.MultiheadAttention(d_model, heads, dropout=dropout, batch_first=True)
        self.norm_cross = nn.LayerNorm(d_model)
        self.cross = nn.MultiheadAttention(d_model, heads, dropout=dropout, batch_first=True)
        self.norm_ff = nn.LayerNorm(d_model)
        self.ff = nn.Sequential(nn.Linear(d_model, ff), nn.GELU(), nn.Dropout(dropout), nn.Linear(ff, d_model))
        self.drop = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, memory: torch.Tensor, intra: torch.Tensor | None,
                inter: torch.Tensor | None) -> torch.Tensor:  # fmt: skip
        h = self.norm_intra(x)
        x = x + self.drop(self.intra(h, h, h, attn_mask=intra if self.interaction else None, need_weights=False)[0])
        if self.interaction:
            h = self.norm_inter(x)
            x = x + self.drop(self.inter(h, h, h, attn_mask=inter, need_weights=False)[0])
        h = self.norm_cross(x)
        x = x + self.drop(self.cross(h, memory, memory, need_weights=False)[0])
        return x + self.drop(self.ff(self.norm_ff(x)))


def _mlp(d: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d, d), nn.GELU(), nn.Linear(d, out))


class PoseEstimator(nn.Module):
    """The whole network (module docstring). ``config``: the spec's merged settings."""

    def __init__(self, config: dict[str, Any]):
        super().__init__()
        c = self.config = dict(config)
        d, heads = int(c["d_model"]), int(c["heads"])
        if d < 4 or heads < 1 or d % heads:
            raise DualhumanError(f"d_model {d} must be divisible by heads {heads}", fix="use e.g. --set d_model=128 --set heads=4")
        self.size = int(c["size"])
        self.backbone = ResNetBackbone(int(c["backbone_width"]), [int(n) for n in c["backbone_blocks"]])
        if c.get("backbone_weights"):
            load_backbone(self.backbone, c["backbone_weights"])
        self.proj = nn.Conv2d(self.backbone.out_channels, d, 1)
        self.queries = nn.Parameter(torch.randn(NUM_QUERIES, d) * 0.02)
        self.track_proj = nn.Sequential(nn.Linear(3, d), nn.GELU(), nn.Linear(d, d))
        self.no_track = nn.Parameter(torch.zeros(d))
        self.layers = nn.ModuleList(DecoderLayer(d, heads, int(c["ff"]), float(c["dropout"]), bool(c["interaction_attention"]))
                                    for _ in range(int(c["layers"])))  # fmt: skip
        self.norm = nn.LayerNorm(d)
        self.pose_head = _mlp(d, 3)
        self.transl_head = _mlp(d, 3)
        self.prob_head = nn.Linear(d, 1)
        self.register_buffer("intra_mask", intra_mask(), persistent=False)
        self.register_buffer("inter_mask", inter_mask(), persistent=False)
        idx = lambda kind: torch.tensor([query_index(p, kind) for p in range(PERSONS)])
        self.register_buffer("pose_idx", torch.tensor([p * PER_PERSON + j for p in range(PERSONS) for j in range(JOINTS)]),
                             persistent=False)  # fmt: skip
        self.register_buffer("transl_idx", idx(TRANSL), persistent=False)
        self.register_buffer("prob_idx", idx(PROB), persistent=False)
        self.register_buffer("track_idx", idx(TRACK), persistent=False)

    def tokens(self, image: torch.Tensor) -> torch.Tensor:
        """Image ``(B, 3, S, S)`` -> tokens ``(B, N, d_model)`` with their positional encoding."""
        f = self.proj(self.backbone(image))
        _, d, h, w = f.shape
        return f.flatten(2).transpose(1, 2) + sine_positions(h, w, d, f.device).to(f.dtype)

    def forward(self, image: torch.Tensor, prev_root: torch.Tensor | None = None,
                has_prev: torch.Tensor | None = None) -> dict[str, torch.Tensor]:  # fmt: skip
        """``image (B, 3, S, S)`` in [0, 1]; ``prev_root (B, 2, 3)`` and ``has_prev (B,)`` bool (None: no
        track). Returns ``pose (B, 2, 22, 3)`` m root-relative, ``transl (B, 2, 3)`` normalised,
        ``prob_logit (B, 2)``, in query order (with a track: the track's order)."""
        B = image.shape[0]
        memory = self.tokens(image)
        x = self.queries.unsqueeze(0).expand(B, -1, -1).to(memory.dtype)
        if prev_root is None or has_prev is None:
            track = self.no_track.expand(B, PERSONS, -1).to(x.dtype)
        else:
            on = has_prev.to(torch.bool).view(B, 1, 1)
            track = torch.where(on, self.track_proj(prev_root.to(x.dtype)).to(x.dtype), self.no_track.to(x.dtype))
        x = x.index_add(1, self.track_idx, track)
        for layer in self.layers:
            x = layer(x, memory, self.intra_mask, self.inter_mask)
        x = self.norm(x)
        raw = self.pose_head(x[:, self.pose_idx]).view(B, PERSONS, JOINTS, 3)
        return {"pose": raw - raw[:, :, :1], "transl": self.transl_head(x[:, self.transl_idx]),
                "prob_logit": self.prob_head(x[:, self.prob_idx]).squeeze(-1)}  # fmt: skip


def load_backbone(backbone: nn.Module, path: str | Path) -> None:
    """Load a local safetensors state dict into ``backbone`` (all of its keys, matching shapes)."""
    p = Path(path).expanduser()
    fix = "point backbone_weights to a safetensors file holding this backbone's state dict, or leave it null"
    if not p.is_file():
        raise DualhumanError(f"backbone weights {p} do not exist", fix=fix)
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    try:
        state = load_file(str(p))
    except (SafetensorError, OSError, ValueError) as e:
        raise DualhumanError(f"backbone weights {p} are not a readable safetensors file ({type(e).__name__}: {e})", fix=fix) from None
    try:
        backbone.load_state_dict(state, strict=True)
    except RuntimeError as e:
        first = str(e).strip().splitlines()
        raise DualhumanError(f"backbone weights {p} do not fit the configured backbone ({' '.join(first[:3])[:400]})",
                             fix=fix + " (backbone_width and backbone_blocks must match the weights)") from None  # fmt: skip


def to_camera(transl: Any, K: Any, size: float) -> Any:
    """Root positions ``(..., 3)`` in camera metres (X right, Y down, Z forward) of normalised translations
    ``transl (..., 3)`` ``(u_n, v_n, z_n)`` seen by intrinsics ``K (..., 3, 3)`` of a ``size`` x ``size``
    image: ``u = (u_n + 1) size / 2``, ``v = (v_n + 1) size / 2``, ``z = z_n fx / size`` and the pixel
    back-projected at depth ``z`` (skew included). The inverse of
    :func:`~dualhuman_builder.export.writer.normalised_root`; torch in, torch out (differentiable), numpy
    in, numpy out."""
    if isinstance(transl, np.ndarray) or isinstance(K, np.ndarray):
        return to_camera(torch.as_tensor(np.asarray(transl, np.float64)), torch.as_tensor(np.asarray(K, np.float64)),
                         size).numpy()  # fmt: skip
    K = K.to(transl.dtype)
    fx, fy, s, cx, cy = K[..., 0, 0], K[..., 1, 1], K[..., 0, 1], K[..., 0, 2], K[..., 1, 2]
    z = transl[..., 2] * fx / size
    u, v = (transl[..., 0] + 1.0) * size / 2.0, (transl[..., 1] + 1.0) * size / 2.0
    y = (v - cy) * z / fy
    x = (u - cx) * z / fx - s * y / fx
    return torch.stack([x, y, z], dim=-1)


__all__ = ["DecoderLayer", "PoseEstimator", "ResNetBackbone", "load_backbone", "sine_positions", "to_camera"]

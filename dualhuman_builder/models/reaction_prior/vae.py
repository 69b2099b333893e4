"""The motion VAE of the reaction prior (paper §3.1), following MLD's ``mld_vae.py`` pattern.

Encoder: each frame ``(B, L, F)`` is embedded to ``latent_dim``, ``2 * tokens`` learned **distribution
tokens** (MLD's ``global_motion_token`` of ``latent_size * 2`` tokens; ``tokens`` is MLD's
``latent_size``) are put in front, sinusoidal positions are added, and a Transformer encoder runs over
the ``L + 2 * tokens`` tokens; the outputs at the first ``tokens`` are ``mu`` and at the next ``tokens``
``logvar``, each flattened to ``(B, tokens * latent_dim)``, the code's ``code_dim`` numbers. Decoder: ``L``
queries that are the frames' positional encodings alone attend to ``memory = z (B, tokens, latent_dim)``
through a Transformer decoder, and a linear layer maps each to the ``F`` numbers of a frame.

Sizes: the defaults of the spec (latent 64, 2 layers, 4 heads, feed-forward 128, one token) are for a
CPU; MLD's setting, which the paper follows, is latent 256, 9 layers, 4 heads, feed-forward 1024, one
token (pass them as config overrides on a GPU). More tokens cost little compute, the window's frames
outnumbering them; ``benchmarks/probes/probe_prior_code.py`` measures what they describe.
"""

from __future__ import annotations

import math

import torch
from torch import nn


def sinusoid(length: int, dim: int) -> torch.Tensor:
    """``(length, dim)`` sinusoidal position encodings (Vaswani et al.)."""
    pos = torch.arange(length, dtype=torch.float32)[:, None]
    div = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(10000.0) / dim))
    pe = torch.zeros(length, dim)
    pe[:, 0::2] = torch.sin(pos * div)
    pe[:, 1::2] = torch.cos(pos * div)[:, : dim // 2]
    return pe


class MotionVAE(nn.Module):
    """Transformer VAE of one person's motion window ``(B, L, feats)`` (normalised units).

    :meth:`encode` -> ``(mu, logvar)`` each ``(B, code_dim)``, ``code_dim = tokens * latent_dim``;
    :meth:`decode` ``(z, length)`` -> ``(B, length, feats)``. ``max_len``: longest window the position
    table covers."""

    def __init__(self, feats: int, latent_dim: int = 64, layers: int = 2, heads: int = 4, ff: int = 128,
                 dropout: float = 0.1, max_len: int = 512, tokens: int = 1):  # fmt: skip
        super().__init__()
        if int(tokens) < 1:
            raise ValueError(f"the VAE needs at least one latent token, got {tokens!r}")
        self.feats, self.latent_dim, self.tokens = int(feats), int(latent_dim), int(tokens)
        self.code_dim = self.tokens * self.latent_dim
        self.embed = nn.Linear(feats, latent_dim)
        self.dist_tokens = nn.Parameter(torch.randn(2 * self.tokens, latent_dim) * 0.02)
        self.register_buffer("pe", sinusoid(max_len + 2 * self.tokens, latent_dim), persistent=False)
        enc = nn.TransformerEncoderLayer(latent_dim, heads, ff, dropout, activation="gelu", batch_first=True,
                                         norm_first=True)  # fmt: skip
        self.encoder = nn.TransformerEncoder(enc, layers, norm=nn.LayerNorm(latent_dim), enable_nested_tensor=False)
        dec = nn.TransformerDecoderLayer(latent_dim, heads, ff, dropout, activation="gelu", batch_first=True,
                                         norm_first=True)  # fmt: skip
        self.decoder = nn.TransformerDecoder(dec, layers, norm=nn.LayerNorm(latent_dim))
        self.out = nn.Linear(latent_dim, feats)

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        B, L, _ = x.shape
        t = self.tokens
        h = torch.cat([self.dist_tokens.expand(B, -1, -1), self.embed(x)], dim=1) + self.pe[: L + 2 * t]
        h = self.encoder(h)
        return h[:, :t].reshape(B, self.code_dim), h[:, t : 2 * t].reshape(B, self.code_dim).clamp(-20.0, 10.0)

    def decode(self, z: torch.Tensor, length: int) -> torch.Tensor:
        t = self.tokens
        queries = self.pe[2 * t : length + 2 * t].expand(z.shape[0], -1, -1)
        return self.out(self.decoder(queries, z.reshape(z.shape[0], t, self.latent_dim)))


class DCTCodec(nn.Module):
    """The "without motion VAE" ablation's fixed code: the first ``coeffs`` coefficients of an
    orthonormal DCT-II along time of each of the ``feats`` numbers, so ``mu (B, code_dim)``,
    ``code_dim = feats * coeffs``;
    ``logvar`` is the constant ``log_std * 2`` (a fixed, not learned, spread; default unit deviation in
    normalised units, the scale a VAE's KL term pulls its codes to). :meth:`decode` is the
    inverse DCT of the kept coefficients (a low-pass projection). Nothing here is trained; it gives
    the prior a code of equal dimension for both people so the mapper works as with the VAE."""

    def __init__(self, feats: int, length: int, coeffs: int = 8, log_std: float = 0.0):
        super().__init__()
        self.feats, self.length, self.coeffs = int(feats), int(length), int(min(coeffs, length))
        self.code_dim = self.feats * self.coeffs
        self.log_std = float(log_std)
        n = torch.arange(length, dtype=torch.float64)
        k = torch.arange(self.coeffs, dtype=torch.float64)
        basis = torch.cos(math.pi / length * (n[:, None] + 0.5) * k[None, :]) * math.sqrt(2.0 / length)
        basis[:, 0] /= math.sqrt(2.0)
        self.register_buffer("basis", basis.float(), persistent=False)  # (L, K), orthonormal columns

    def _check(self, length: int) -> None:
        if length != self.length:
            raise ValueError(f"the DCT code is built for windows of {self.length} frames, got {length}")

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        self._check(x.shape[1])
        mu = torch.einsum("blf,lk->bfk", x, self.basis).reshape(x.shape[0], -1)
        return mu, torch.full_like(mu, 2.0 * self.log_std)

    def decode(self, z: torch.Tensor, length: int) -> torch.Tensor:
        self._check(length)
        return torch.einsum("bfk,lk->blf", z.reshape(z.shape[0], self.feats, self.coeffs), self.basis)


_LOG_STD_RANGE = (-8.0, 4.0)  # log sigma clamped inside the KL only, so an outlier cannot overflow exp


def kl_gauss(mu1: torch.Tensor, logstd1: torch.Tensor, mu2: torch.Tensor, logstd2: torch.Tensor) -> torch.Tensor:
    """``KL[N(mu1, s1) || N(mu2, s2)]`` of diagonal Gaussians, per element (nats), ``s = exp(logstd)``."""
    l1, l2 = logstd1.clamp(*_LOG_STD_RANGE), logstd2.clamp(*_LOG_STD_RANGE)
    return l2 - l1 + (torch.exp(2 * l1) + (mu1 - mu2) ** 2) / (2 * torch.exp(2 * l2)) - 0.5

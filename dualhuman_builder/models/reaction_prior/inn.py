"""The reaction generator: an invertible network from the actor's latent distribution parameters to
the reactor's (paper §3.1, Eq. 3), and the MLP that replaces it in the paper's ablation (Table 4 b).

Both map ``p = [mu, log sigma]`` ``(B, 2D)`` to ``[mu~, log sigma~]`` of the same size (an INN needs
equal input and output dimensions). :class:`CouplingINN` is a stack of affine coupling blocks of our
own (no extra dependency): each block splits the coordinates into two halves by a fixed random
permutation, runs two couplings (the second half scaled and shifted by functions of the first, then the
reverse) and puts the coordinates back in their order, so that a block whose subnets output zero is the
identity and the ``mu`` and ``log sigma`` halves keep their places; the log-scales are soft-clamped
(``clamp * tanh(s / clamp)``) and the last layer of each subnet starts at zero, so a fresh network is
the identity (the prior starts as "the reactor moves like the actor"). :meth:`CouplingINN.inverse`
undoes it exactly up to float rounding, which gives the reverse direction (reactor -> actor) for free.
"""

from __future__ import annotations

import torch
from torch import nn

from dualhuman_builder.errors import DualhumanError


def _subnet(dim_in: int, dim_out: int, hidden: int) -> nn.Sequential:
    net = nn.Sequential(nn.Linear(dim_in, hidden), nn.GELU(), nn.Linear(hidden, hidden), nn.GELU(),
                        nn.Linear(hidden, dim_out))  # fmt: skip
    nn.init.zeros_(net[-1].weight)
    nn.init.zeros_(net[-1].bias)
    return net


class NoInverseError(DualhumanError, NotImplementedError):
    """The reverse direction was asked of a generator that has none (the MLP of the INN ablation)."""


class CouplingINN(nn.Module):
    """Invertible map of ``(B, dim)`` (``dim`` even): ``blocks`` blocks of permutation + two affine
    couplings with subnets of ``hidden`` units; ``clamp`` bounds each log-scale."""

    invertible = True

    def __init__(self, dim: int, blocks: int = 4, hidden: int = 128, clamp: float = 2.0, seed: int = 0):
        super().__init__()
        if dim % 2 or dim < 2:
            raise ValueError(f"the invertible network needs an even dimension, got {dim}")
        self.dim, self.half, self.clamp = int(dim), int(dim) // 2, float(clamp)
        g = torch.Generator().manual_seed(seed)
        for k in range(blocks):
            self.register_buffer(f"perm{k}", torch.randperm(dim, generator=g))
        self.nets = nn.ModuleList(
            nn.ModuleList([_subnet(self.half, 2 * self.half, hidden), _subnet(self.half, 2 * self.half, hidden)])
            for _ in range(blocks)
        )

    def _st(self, net: nn.Module, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        s, t = net(x).chunk(2, dim=-1)
        return self.clamp * torch.tanh(s / self.clamp), t

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Actor parameters -> reactor parameters."""
        for k, (n1, n2) in enumerate(self.nets):
            perm = getattr(self, f"perm{k}")
            x = x[:, perm]
            a, b = x[:, : self.half], x[:, self.half :]
            s, t = self._st(n1, a)
            b = b * torch.exp(s) + t
            s, t = self._st(n2, b)
            a = a * torch.exp(s) + t
            x = torch.cat([a, b], dim=-1)[:, torch.argsort(perm)]  # back to the input order
        return x

    def inverse(self, y: torch.Tensor) -> torch.Tensor:
        """Reactor parameters -> actor parameters (exact inverse of :meth:`forward`)."""
        for k in reversed(range(len(self.nets))):
            n1, n2 = self.nets[k]
            perm = getattr(self, f"perm{k}")
            y = y[:, perm]
            a, b = y[:, : self.half], y[:, self.half :]
            s, t = self._st(n2, b)
            a = (a - t) * torch.exp(-s)
            s, t = self._st(n1, a)
            b = (b - t) * torch.exp(-s)
            y = torch.cat([a, b], dim=-1)[:, torch.argsort(perm)]
        return y


class MLPMapper(nn.Module):
    """The ablation's generator: a plain MLP ``(B, dim) -> (B, dim)`` with ``blocks`` hidden layers of
    ``hidden`` units; one direction only (no inverse)."""

    invertible = False

    def __init__(self, dim: int, blocks: int = 4, hidden: int = 128):
        super().__init__()
        layers: list[nn.Module] = [nn.Linear(dim, hidden), nn.GELU()]
        for _ in range(max(0, blocks - 1)):
            layers += [nn.Linear(hidden, hidden), nn.GELU()]
        layers.append(nn.Linear(hidden, dim))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)

    def inverse(self, y: torch.Tensor) -> torch.Tensor:
        """Refused: an MLP is not invertible, which is what the ablation measures."""
        raise NoInverseError("the MLP generator (the INN ablation, mapper 'mlp') has no inverse: it maps the actor's "
                             "code to the reactor's only", fix="use mapper 'inn' for the reverse direction")  # fmt: skip

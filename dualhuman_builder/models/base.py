"""What every bundled model gives the shared training loop, and the registry of models by name.

A model is a :class:`ModelSpec`: it builds a ``torch.nn.Module`` from a JSON-able config, names
the phases it trains in (the reaction prior trains its VAE, then its invertible network), picks the
parameters each phase optimises, and computes the losses of one batch. The loop
(:mod:`dualhuman_builder.models.training`) owns everything else: data loading, optimiser, seeding,
device, mixed precision, checkpoints, resume, logs and curves. So a new model is one spec and
one :func:`register` call, and every model gets the same run folder.

Batches are dicts of tensors (and lists of strings) made by :mod:`dualhuman_builder.models.data`;
see :data:`BATCH_KEYS` for the keys a window dataset gives.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, Protocol, runtime_checkable

import torch

from dualhuman_builder.errors import DualhumanError

#: Keys of a batch of windows (``B`` windows of ``L`` frames, ``J = 22`` joints, metres, the export's
#: world frame: Y up, right-handed). "actor"/"reactor" follow the sequence's roles in ``text.json``
#: (a symmetric sequence: person a acts). Models read what they need and ignore the rest.
BATCH_KEYS = {
    "joints_actor": "(B, L, J, 3) float32, metres, world frame",
    "joints_reactor": "(B, L, J, 3) float32, metres, world frame",
    "visibility_actor": "(B, L, J) float32 in [0, 1]: share of a ring of virtual cameras that sees the joint",
    "visibility_reactor": "(B, L, J) float32 in [0, 1]",
    "labels": "(B, C) float32 multi-hot over the export's labels.json",
    "text": "list of B str",
    "seq_id": "list of B str",
    "start": "(B,) int64 first frame of the window",
}


@dataclass(frozen=True)
class Phase:
    """One stage of training: ``steps`` optimiser steps over the parameters :meth:`ModelSpec.parameters` gives."""

    name: str
    steps: int
    lr: float = 1e-4  # the paper's AdamW settings (models-and-metrics reference)
    weight_decay: float = 5e-4


@runtime_checkable
class ModelSpec(Protocol):
    """A trainable model, as the shared loop sees it."""

    name: str  #: registry key, also the CLI's MODEL argument (``reaction-prior``)

    def default_config(self) -> dict[str, Any]:
        """Hyper-parameters, JSON-able; a run stores the merged config in ``RUN/config.json``."""

    def build(self, config: dict[str, Any]) -> torch.nn.Module:
        """A fresh module (random weights drawn from torch's seeded generator)."""

    def phases(self, config: dict[str, Any]) -> list[Phase]:
        """The phases in training order; a run resumes inside the phase it stopped in."""

    def parameters(self, module: torch.nn.Module, phase: str) -> Iterable[torch.nn.Parameter]:
        """The parameters ``phase`` optimises (the others are frozen during it)."""

    def losses(self, module: torch.nn.Module, batch: dict[str, Any], phase: str) -> dict[str, torch.Tensor]:
        """Scalar losses of one batch; ``"loss"`` is the one minimised, the others are logged."""

    def evaluate(self, module: torch.nn.Module, batches: Iterator[dict[str, Any]], device: torch.device) -> dict[str, float]:
        """Figures on held-out batches (module in eval mode, no grad), logged and written by ``evaluate``."""


#: Optional on a spec: a tuple of config keys naming files the fresh module's weights start from
#: (the pose estimator's local ``backbone_weights``). A module about to take a checkpoint's weights
#: is built with them set to None, so a run folder loads after those files moved or went away.
INIT_KEYS = "init_keys"

#: Optional on a spec: ``make_dataset(export_dir, split, config, seed)`` returns the dataset the loop
#: draws batches from (``__len__``, ``batch(indices) -> dict``, ``set_epoch(epoch)``), for a model that
#: reads something else than windows of motion (the pose estimator reads images). Without it the loop
#: uses :class:`~dualhuman_builder.models.data.InteractionWindows`.
DATASET_HOOK = "make_dataset"

_REGISTRY: dict[str, Callable[[], ModelSpec]] = {}


def register(name: str, factory: Callable[[], ModelSpec]) -> None:
    """Make ``factory()`` reachable as ``dualhuman train NAME``."""
    _REGISTRY[name] = factory


def get_model(name: str) -> ModelSpec:
    """The spec registered as ``name``; a clear error listing the known ones otherwise."""
    _load_builtin()
    if name not in _REGISTRY:
        raise DualhumanError(f"no model named {name!r}", fix=f"choose one of: {', '.join(sorted(_REGISTRY)) or '(none)'}")
    return _REGISTRY[name]()


def model_names() -> list[str]:
    _load_builtin()
    return sorted(_REGISTRY)


def _load_builtin() -> None:
    """Import the bundled models, which register themselves (kept lazy: torch models load on demand)."""
    import importlib

    for module in ("dualhuman_builder.models.reaction_prior", "dualhuman_builder.models.pose_estimator",
                   "dualhuman_builder.models.temporal", "dualhuman_builder.models.lifting"):
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as e:  # a bundled model not present in this checkout
            if e.name != module:
                raise

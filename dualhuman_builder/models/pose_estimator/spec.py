"""The pose estimator as a trainable model: :class:`PoseEstimatorSpec` (``dualhuman train pose-estimator``),
:func:`predict` (the network's outputs as both people's joints in camera metres) and the settings.

One phase, ``estimator``, trains the whole network on :class:`~dualhuman_builder.models.images.ImageFrames`
of the export's train split (flip and crop jitter on; ``size`` pixels square) with the losses of
:mod:`.losses`. In training, the two people's order is swapped in a share ``swap_persons`` of the items
(targets and previous roots together; the image is untouched), so a query can only follow a person
through its Track query, never by learning "query 0 is person a".

Sizes: :data:`DEFAULTS` fit a CPU (64-pixel images, a three-stage backbone 16 channels wide, 2 decoder
layers of width 128) and use lr 1e-4, since the backbone starts from random weights. The paper's
setting, for a GPU: ``--set size=512 --set backbone_width=64 --set 'backbone_blocks=[2, 2, 2, 2]'
--set d_model=256 --set heads=8 --set layers=6 --set ff=1024 --set lr=1e-5`` and ``steps`` for 300
epochs of the training images (the paper's HRNet-W48 starts from ImageNet weights and decays the
learning rate by 5; the shared loop keeps it constant).

Evaluation (:meth:`PoseEstimatorSpec.evaluate`): the predictions are put in the truth's order (the
track's order where an item has a previous frame and ``eval_tracks`` is true, the Hungarian matching
of :mod:`.losses` otherwise), turned into camera-frame joints (:func:`~.network.to_camera` of the
translation plus the root-relative pose) and scored with :func:`~dualhuman_builder.models.metrics.pose_errors`
(MPJPE root-relative, PA-MPJPE, translation error of the root, mm) over both people and per person
(``_a``, ``_b``: the export's persons a and b). The tracks of the test split are the true previous
roots, so with ``eval_tracks`` the figures are those of a perfect tracker; ``dualhuman estimate``
feeds the network its own previous outputs instead.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from dualhuman_builder.models.base import Phase
from dualhuman_builder.models.data import TRAINING_SPLITS
from dualhuman_builder.models.pose_estimator.losses import LOSS_DEFAULTS, estimator_losses, gather_people, hungarian, pair_costs, root_relative
from dualhuman_builder.models.pose_estimator.network import PoseEstimator, to_camera

NAME = "pose-estimator"

#: CPU-sized defaults (module docstring for the paper's GPU setting).
DEFAULTS: dict[str, Any] = {
    "size": 64,
    "views": None,
    "backbone_width": 16,
    "backbone_blocks": [1, 1, 1],
    "backbone_weights": None,
    "d_model": 128,
    "heads": 4,
    "layers": 2,
    "ff": 256,
    "dropout": 0.1,
    "interaction_attention": True,
    "swap_persons": 0.5,
    **LOSS_DEFAULTS,
    "steps": 2000,
    "lr": 1e-4,
    "weight_decay": 5e-4,
    "eval_tracks": True,
}


def _swap(batch: dict[str, Any], share: float) -> dict[str, Any]:
    """``batch`` with the two people's order swapped in a random share of its items (targets and previous roots)."""
    if share <= 0:
        return batch
    B = batch["joints_cam"].shape[0]
    flip = torch.rand(B) < share
    if not bool(flip.any()):
        return batch
    perm = torch.stack([flip.long(), 1 - flip.long()], dim=1)
    out = dict(batch)
    for k in ("joints_cam", "transl", "prob", "prev_root", "keypoints2d"):
        if k in out and torch.is_tensor(out[k]):
            out[k] = gather_people(out[k], perm.to(out[k].device))
    return out


@torch.no_grad()
def predict(module: nn.Module, batch: dict[str, Any], use_track: bool = True) -> dict[str, torch.Tensor]:
    """Both people's estimates for a batch of :class:`~dualhuman_builder.models.images.ImageFrames` keys
    (``image``, ``K``; ``prev_root`` and ``has_prev`` when ``use_track``), without gradients, on the module's
    device, float32 (call ``module.eval()`` first: dropout stays on in training mode):

    * ``joints_cam (B, 2, 22, 3)``: joints in camera metres (X right, Y down, Z forward), the pose plus
      the root from :func:`~.network.to_camera`;
    * ``pose (B, 2, 22, 3)``: the same relative to the root; ``root_cam (B, 2, 3)``;
    * ``transl (B, 2, 3)``: the normalised translation; ``prob (B, 2)``: the saliency in [0, 1].

    People are in query order, which is the track's order (the order of ``prev_root``) where
    ``has_prev``; elsewhere it is arbitrary."""
    dev = next(module.parameters()).device
    image = batch["image"].to(dev).float()
    prev = has = None
    if use_track and "prev_root" in batch and "has_prev" in batch:
        prev, has = batch["prev_root"].to(dev).float(), batch["has_prev"].to(dev).bool()
    out = module(image, prev, has)
    pose, transl = out["pose"].float(), out["transl"].float()
    root = to_camera(transl, batch["K"].to(dev).float()[:, None], float(image.shape[-1]))
    return {"joints_cam": pose + root[:, :, None], "pose": pose, "root_cam": root, "transl": transl,
            "prob": torch.sigmoid(out["prob_logit"].float())}  # fmt: skip


class PoseEstimatorSpec:
    """:class:`~dualhuman_builder.models.base.ModelSpec` of the pose estimator (module docstring)."""

    name = NAME
    init_keys = ("backbone_weights",)  # a run's checkpoint holds the backbone: the file is read once, at the start
    about = ("the Dual-Human paper's two-person pose estimator: an image backbone and a decoder-only Transformer over "
             "Pose, Transl, Prob and Track queries with interaction-aware attention, trained on rendered exports")

    def default_config(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, list) else v) for k, v in DEFAULTS.items()}

    def build(self, config: dict[str, Any]) -> nn.Module:
        return PoseEstimator({**DEFAULTS, **config})

    def phases(self, config: dict[str, Any]) -> list[Phase]:
        c = {**DEFAULTS, **config}
        return [Phase("estimator", int(c["steps"]), float(c["lr"]), float(c["weight_decay"]))]

    def parameters(self, module: nn.Module, phase: str) -> Iterable[nn.Parameter]:
        if phase != "estimator":
            raise ValueError(f"the pose estimator has one phase 'estimator', not {phase!r}")
        return list(module.parameters())

    def make_dataset(self, export_dir: str | Path, split: str, config: dict[str, Any], seed: int):
        from dualhuman_builder.models.images import ImageFrames

        c = {**DEFAULTS, **config}
        return ImageFrames(export_dir, split, size=int(c["size"]), augment=(split in TRAINING_SPLITS), seed=int(seed), views=c["views"])

    def losses(self, module: nn.Module, batch: dict[str, Any], phase: str) -> dict[str, torch.Tensor]:
        if phase != "estimator":
            raise ValueError(f"the pose estimator has one phase 'estimator', not {phase!r}")
        c = module.config
        if module.training:
            batch = _swap(batch, float(c["swap_persons"]))
        out = module(batch["image"].float(), batch.get("prev_root"), batch.get("has_prev"))
        return estimator_losses(out, batch, c)

    def evaluate(self, module: nn.Module, batches: Iterator[dict[str, Any]], device: torch.device) -> dict[str, float]:
        from dualhuman_builder.models.metrics import pose_errors

        c = module.config
        preds, truths, probs, true_probs, swapped = [], [], [], [], 0
        for batch in batches:
            use_track = bool(c["eval_tracks"])
            p = predict(module, batch, use_track=use_track)
            truth = batch["joints_cam"].to(p["pose"].device).float()
            cost = pair_costs(p["pose"], p["transl"], root_relative(truth), batch["transl"].to(truth.device).float(), c)
            perm = hungarian(cost).to(truth.device)  # perm[b, i]: the true person of prediction i
            if use_track:
                ident = torch.arange(2, device=perm.device).expand_as(perm)
                perm = torch.where(batch["has_prev"].to(perm.device).bool()[:, None], ident, perm)
            inv = torch.argsort(perm, dim=1)  # predictions in the truth's order
            preds.append(gather_people(p["joints_cam"], inv).cpu())
            probs.append(gather_people(p["prob"], inv).cpu())
            truths.append(truth.cpu())
            true_probs.append(batch["prob"].float().cpu())
            swapped += int((perm[:, 0] != 0).sum())
        if not preds:
            return {}
        pred, truth = torch.cat(preds).numpy(), torch.cat(truths).numpy()
        out = dict(pose_errors(pred, truth))
        for k, tag in enumerate("ab"):
            for name, v in pose_errors(pred[:, k], truth[:, k]).items():
                out[name.replace("_mm", f"_{tag}_mm")] = v
        prob, tprob = torch.cat(probs).numpy(), torch.cat(true_probs).numpy()
        out["prob_mae"] = float(np.abs(prob - tprob).mean())
        differ = np.abs(tprob[:, 0] - tprob[:, 1]) > 1e-6
        if differ.any():  # which person is the more visible one (the paper's use of the saliency)
            out["salient_accuracy"] = float(((prob[:, 0] > prob[:, 1]) == (tprob[:, 0] > tprob[:, 1]))[differ].mean())
        out["frames"] = float(len(pred))
        out["swapped_share"] = swapped / len(pred)
        return out


__all__ = ["DEFAULTS", "NAME", "PoseEstimatorSpec", "predict"]

"""The pose estimator's losses and the matching of its two predicted people to the two true ones
(the Dual-Human paper, §3.4).

``L = lambda_pose * L_pose + lambda_transl * L_transl + lambda_prob * L_prob`` (lambdas 10, 1, 1):

* ``L_pose``: smooth-L1 (Huber with ``beta = smooth_l1_beta`` metres, torch's ``smooth_l1_loss``) of the
  root-relative joints in camera axes, mean over people, joints and axes;
* ``L_transl``: squared error of the normalised translation ``(u_n, v_n, z_n)``, mean over people and axes;
* ``L_prob``: binary cross-entropy of the saliency logit against the soft target (the share of the
  person's joints visible), mean over people.

**Matching**: without a track (``has_prev`` False) the network's query order means nothing, so each
item's two predictions are assigned to the two true people by the Hungarian algorithm
(``scipy.optimize.linear_sum_assignment``) on the cost ``lambda_pose * L_pose + lambda_transl *
L_transl`` of every (prediction, truth) pair; with a track the order is the track's (query ``p`` is
the person whose previous root fed Track query ``p``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment

#: Loss weights and the Huber threshold (metres) of the pose term.
LOSS_DEFAULTS = {"lambda_pose": 10.0, "lambda_transl": 1.0, "lambda_prob": 1.0, "smooth_l1_beta": 0.05}


def root_relative(joints: torch.Tensor) -> torch.Tensor:
    """``joints (..., 22, 3)`` minus their root (joint 0)."""
    return joints - joints[..., :1, :]


def pair_costs(pred_pose: torch.Tensor, pred_transl: torch.Tensor, true_pose: torch.Tensor, true_transl: torch.Tensor,
               config: dict[str, Any]) -> torch.Tensor:  # fmt: skip
    """Matching cost ``(B, P, P)``: ``[b, i, j]`` of prediction ``i`` against true person ``j`` (root-relative
    poses ``(B, P, 22, 3)`` m, translations ``(B, P, 3)``), the weighted pose and translation losses."""
    c = {**LOSS_DEFAULTS, **config}
    beta = float(c["smooth_l1_beta"])
    B, P = pred_pose.shape[:2]
    a = pred_pose[:, :, None].expand(B, P, true_pose.shape[1], *pred_pose.shape[2:])
    b = true_pose[:, None].expand(B, P, true_pose.shape[1], *true_pose.shape[2:])
    pose = F.smooth_l1_loss(a, b, reduction="none", beta=beta).mean(dim=(-1, -2))
    transl = ((pred_transl[:, :, None] - true_transl[:, None]) ** 2).mean(-1)
    return float(c["lambda_pose"]) * pose + float(c["lambda_transl"]) * transl


def hungarian(cost: torch.Tensor | np.ndarray) -> torch.Tensor:
    """Per item of ``cost (B, P, P)``, the true person assigned to each prediction: ``(B, P)`` int64
    (``linear_sum_assignment`` on the item's cost; ties keep the query order)."""
    c = cost.detach().float().cpu().numpy() if torch.is_tensor(cost) else np.asarray(cost, dtype=np.float64)
    out = np.empty(c.shape[:2], dtype=np.int64)
    for b in range(c.shape[0]):
        rows, cols = linear_sum_assignment(c[b])
        out[b, rows] = cols
    return torch.from_numpy(out)


def assignment(out: dict[str, torch.Tensor], batch: dict[str, Any], config: dict[str, Any]) -> torch.Tensor:
    """``(B, P)`` int64: the true person each prediction is scored against: the track's order (identity)
    where ``batch["has_prev"]``, the Hungarian matching elsewhere (module docstring)."""
    true_pose = root_relative(batch["joints_cam"].float())
    with torch.no_grad():
        cost = pair_costs(out["pose"].float(), out["transl"].float(), true_pose, batch["transl"].float(), config)
    perm = hungarian(cost).to(cost.device)
    B, P = perm.shape
    has_prev = batch.get("has_prev")
    if has_prev is not None:
        ident = torch.arange(P, device=perm.device).expand(B, P)
        perm = torch.where(has_prev.to(perm.device).bool().view(B, 1), ident, perm)
    return perm


def gather_people(x: torch.Tensor, perm: torch.Tensor) -> torch.Tensor:
    """``x (B, P, ...)`` reordered per item: ``out[b, i] = x[b, perm[b, i]]``."""
    idx = perm.to(x.device).view(*perm.shape, *([1] * (x.dim() - 2))).expand(-1, -1, *x.shape[2:])
    return torch.gather(x, 1, idx)


def estimator_losses(out: dict[str, torch.Tensor], batch: dict[str, Any], config: dict[str, Any]) -> dict[str, torch.Tensor]:
    """The weighted loss (``"loss"``) and its detached terms ``pose``, ``transl``, ``prob``, and
    ``swapped`` (the share of items whose matching swapped the two people) of network outputs ``out``
    (:meth:`~.network.PoseEstimator.forward`) on ``batch`` (:class:`~dualhuman_builder.models.images.ImageFrames` keys)."""
    c = {**LOSS_DEFAULTS, **config}
    perm = assignment(out, batch, c)
    true_pose = gather_people(root_relative(batch["joints_cam"].float()), perm)
    true_transl = gather_people(batch["transl"].float(), perm)
    true_prob = gather_people(batch["prob"].float(), perm)
    pose = F.smooth_l1_loss(out["pose"].float(), true_pose, beta=float(c["smooth_l1_beta"]))
    transl = F.mse_loss(out["transl"].float(), true_transl)
    prob = F.binary_cross_entropy_with_logits(out["prob_logit"].float(), true_prob.clamp(0.0, 1.0))
    loss = float(c["lambda_pose"]) * pose + float(c["lambda_transl"]) * transl + float(c["lambda_prob"]) * prob
    swapped = (perm[:, 0] != 0).float().mean()
    return {"loss": loss, "pose": pose.detach(), "transl": transl.detach(), "prob": prob.detach(), "swapped": swapped}


__all__ = ["LOSS_DEFAULTS", "assignment", "estimator_losses", "gather_people", "hungarian", "pair_costs", "root_relative"]

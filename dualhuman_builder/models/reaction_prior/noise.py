"""Noise that corrupts a motion as an image-based pose estimator would, driven by per-joint visibility.

The paper trains its prior on ground truth "with noise augmentation ... according to the probability"
of each joint being visible from a ring of virtual cameras (§3.1), and evaluates it on estimates of
image-based estimators. :func:`corrupt` draws, for joints ``(B, T, 22, 3)`` and visibility
``(B, T, 22)`` in ``[0, 1]`` (share of the camera ring that sees the joint):

- **pose noise**, smooth in time (white noise averaged over a Gaussian window of ``smooth_frames``
  standard deviation, rescaled to keep its variance: an estimator's error on an occluded limb drifts,
  it does not flicker), per axis of standard deviation ``visible_m * v + occluded_m * (1 - v)``;
- **jitter**, white per frame and joint, ``jitter_m`` per axis;
- **root bias**, one offset of the whole body per item (window or sequence), ``root_bias_m`` per axis
  ``(x, y, z)``: monocular depth and placement errors.

Magnitudes (:class:`NoiseModel` defaults) and why:

- ``visible_m = 0.025``: a 3-D Gaussian of per-axis deviation s has a mean norm of about 1.6 s, so a
  visible joint is off by about 40 mm, the PA-MPJPE level of the image-based estimators in the
  paper's Table 2 (45-60 mm, mostly visible joints);
- ``occluded_m = 0.08``: about 130 mm for a joint no camera sees, three times a visible one ("occluded
  joints far noisier"; the paper's errors grow most on severely occluded motions, and occlusion
  benchmarks report MPJPE two to three times the unoccluded figure);
- ``jitter_m = 0.008``: white noise of deviation s gives an acceleration error of about 4 s per
  frame², so about 30 mm/frame², the range SmoothNet reports for single-frame estimators;
- ``root_bias_m = (0.06, 0.02, 0.06)``: a mean offset of about 100 mm, the translation error of the
  paper's best estimator (106-112 mm; others 200-375 mm), mostly horizontal (the floor fixes height);
- ``smooth_frames = 4``: errors correlated over about a fifth of a second at 20 fps.

None of these come from the toolkit's simulator.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import torch


@dataclass(frozen=True)
class NoiseModel:
    """Magnitudes of :func:`corrupt` (metres; ``smooth_frames`` in frames). See the module docstring."""

    visible_m: float = 0.025
    occluded_m: float = 0.08
    jitter_m: float = 0.008
    root_bias_m: tuple[float, float, float] = (0.06, 0.02, 0.06)
    smooth_frames: float = 4.0

    def as_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}


def _smooth(noise: torch.Tensor, sigma_frames: float) -> torch.Tensor:
    """White noise ``(B, T, ...)`` filtered along T by a Gaussian of ``sigma_frames``, unit variance kept."""
    if sigma_frames <= 0 or noise.shape[1] < 2:
        return noise
    r = max(1, round(3 * sigma_frames))
    t = torch.arange(-r, r + 1, dtype=noise.dtype, device=noise.device)
    w = torch.exp(-0.5 * (t / sigma_frames) ** 2)
    w = w / w.square().sum().sqrt()  # unit-variance white noise stays unit variance
    B, T = noise.shape[:2]
    x = noise.reshape(B, T, -1).permute(0, 2, 1).reshape(-1, 1, T)
    x = torch.nn.functional.pad(x, (r, r), mode="reflect" if T > r else "replicate")
    y = torch.nn.functional.conv1d(x, w.view(1, 1, -1))
    return y.reshape(B, -1, T).permute(0, 2, 1).reshape(noise.shape)


def corrupt(joints: torch.Tensor, visibility: torch.Tensor, model: NoiseModel = NoiseModel(),
            generator: torch.Generator | None = None) -> torch.Tensor:  # fmt: skip
    """``joints (B, T, 22, 3)`` metres plus visibility-driven noise (see the module docstring);
    ``visibility (B, T, 22)`` in [0, 1]. ``generator``: torch generator for reproducible draws (on the
    joints' device), None for torch's global one."""
    j = joints
    v = visibility.to(j.dtype).clamp(0.0, 1.0)[..., None]

    def randn(*shape):
        return torch.randn(*shape, generator=generator, dtype=j.dtype, device=j.device)

    sigma = model.visible_m * v + model.occluded_m * (1.0 - v)
    pose = _smooth(randn(*j.shape), model.smooth_frames) * sigma
    jitter = randn(*j.shape) * model.jitter_m
    bias = randn(j.shape[0], 1, 1, 3) * torch.tensor(model.root_bias_m, dtype=j.dtype, device=j.device)
    return j + pose + jitter + bias


def noise_model(config: dict[str, Any]) -> NoiseModel:
    """The :class:`NoiseModel` of a model config's ``noise`` settings (defaults for those not set)."""
    n = dict(config.get("noise") or {})
    if "root_bias_m" in n:
        n["root_bias_m"] = tuple(float(x) for x in n["root_bias_m"])
    return NoiseModel(**n)

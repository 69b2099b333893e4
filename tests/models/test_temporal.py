"""The temporal refinement network (SmoothNet-style) and the lifting baseline: exact feature recovery,
identity before training, the loss falls, and a trained network lowers the error of a noisy sequence."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tiny_render_export import make_tiny_render_export

from dualhuman_builder.export.features import motion_features, recover_joints
from dualhuman_builder.models.base import register
from dualhuman_builder.models.lifting import NAME as LIFT
from dualhuman_builder.models.lifting import LiftingBaselineSpec, lifting_input
from dualhuman_builder.models.reaction_prior.noise import NoiseModel, corrupt
from dualhuman_builder.models.temporal import (
    NAME,
    TemporalRefiner,
    TemporalRefinerSpec,
    accel_error_mm,
    recover_joints_torch,  # fmt: skip
    refine_motion,
)

register(NAME, TemporalRefinerSpec)
register(LIFT, LiftingBaselineSpec)

TINY = {"window": 16, "hidden": 64, "res_hidden": 32, "blocks": 2, "dropout": 0.0, "stats_batches": 2}
JITTER = NoiseModel(visible_m=0.0, occluded_m=0.0, jitter_m=0.02, root_bias_m=(0.0, 0.0, 0.0))


@pytest.fixture(autouse=True)
def _threads():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _walk(T: int, seed: int = 0) -> np.ndarray:
    """A smooth person ``(T, 22, 3)`` world metres: a skeleton with hips and shoulders across X, walking
    along +Z and swaying its joints."""
    rng = np.random.default_rng(seed)
    rest = rng.normal(size=(22, 3)) * 0.12 + [0.0, 1.0, 0.0]
    rest[1], rest[2], rest[16], rest[17] = [0.1, 0.9, 0], [-0.1, 0.9, 0], [0.2, 1.4, 0], [-0.2, 1.4, 0]
    t = np.arange(T)[:, None, None] / 20.0
    sway = 0.08 * np.sin(2 * np.pi * (0.7 * t + rng.uniform(0, 1, (1, 22, 3))))
    return (rest[None] + sway + t * np.array([0.05, 0.0, 0.6])).astype(np.float32)


def _batch(B: int, L: int, seed: int = 0) -> dict:
    starts = np.random.default_rng(seed).integers(0, 40, B)
    j = np.stack([_walk(80, seed + k)[s : s + L] for k, s in enumerate(starts)])
    jt = torch.from_numpy(j)
    return {"joints_actor": jt, "joints_reactor": jt.flip(0).contiguous(), "visibility_actor": torch.ones(B, L, 22),
            "visibility_reactor": torch.ones(B, L, 22), "fps": torch.full((B,), 20.0)}  # fmt: skip


def _train(spec, module, batches, steps: int, lr: float = 3e-3) -> list[float]:
    opt = torch.optim.AdamW(spec.parameters(module, spec.phases(module.config)[0].name), lr=lr)
    module.train()
    losses = []
    for k in range(steps):
        torch.manual_seed(k)
        out = spec.losses(module, batches[k % len(batches)], spec.phases(module.config)[0].name)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        losses.append(float(out["loss"].detach()))
    return losses


def test_recover_joints_torch_is_the_exports_inverse():
    j = np.stack([_walk(20, s) for s in range(3)]).astype(np.float64)
    f = np.stack([motion_features(w, 20.0) for w in j])
    r = recover_joints_torch(torch.from_numpy(f)).numpy()
    assert np.abs(r - j).max() < 1e-6
    assert np.abs(r[1] - recover_joints(f[1])).max() < 1e-5


@pytest.mark.parametrize("representation", ["features", "joints"])
def test_untrained_refiner_is_the_identity_on_any_length(representation):
    m = TemporalRefiner({**TINY, "representation": representation})
    for T in (5, 16, 37):
        j = _walk(T)
        assert np.abs(refine_motion(m, j, 20.0) - j).max() < 1e-4


def test_temporal_loss_falls_and_lowers_the_error_of_a_noisy_sequence():
    torch.manual_seed(0)
    spec = TemporalRefinerSpec()
    cfg = {**spec.default_config(), **TINY, "noise": {**JITTER.as_dict(), "root_bias_m": [0.0, 0.0, 0.0]}}
    module = spec.build(cfg)
    batches = [_batch(8, 16, seed=s) for s in range(4)]
    losses = _train(spec, module, batches, 60)
    assert np.mean(losses[-10:]) < 0.8 * np.mean(losses[:5])
    truth = _walk(60, seed=11)
    noisy = corrupt(torch.from_numpy(truth)[None], torch.ones(1, 60, 22), JITTER, torch.Generator().manual_seed(3))[0].numpy()
    refined = refine_motion(module, noisy, 20.0)
    before, after = np.linalg.norm(noisy - truth, axis=-1).mean(), np.linalg.norm(refined - truth, axis=-1).mean()
    assert after < 0.9 * before
    assert accel_error_mm(refined, truth) < 0.6 * accel_error_mm(noisy, truth)
    figures = spec.evaluate(module.eval(), iter([batches[0]]), torch.device("cpu"))
    assert figures["after_accel_mm"] < figures["before_accel_mm"] and figures["windows"] == 16


def test_lifting_input_hides_occluded_keypoints():
    kp = torch.tensor([[[[10.0, 20.0, 1.0]] * 21 + [[99.0, 99.0, 0.0]]] * 2])
    K = torch.tensor([[[50.0, 0, 16], [0, 50.0, 16], [0, 0, 1]]])
    x, mean = lifting_input(kp, K)
    assert x.shape == (1, 2, 68) and torch.allclose(mean[0, 0], torch.tensor([-6 / 50, 4 / 50]))
    assert torch.all(x[0, 0, 63:66] == 0)  # the hidden joint: no position, visibility 0


def test_lifting_baseline_loss_falls(tmp_path):
    export = make_tiny_render_export(tmp_path)
    spec = LiftingBaselineSpec()
    cfg = {**spec.default_config(), "size": 16, "hidden": 64, "blocks": 1, "dropout": 0.0}
    ds = spec.make_dataset(export, "train", cfg, 0)
    assert ds.num_sequences == 1 and len(ds) == 8
    batches = [ds.batch(np.arange(len(ds)))]
    torch.manual_seed(0)
    module = spec.build(cfg)
    losses = _train(spec, module, batches, 40)
    assert losses[-1] < 0.5 * losses[0]
    figures = spec.evaluate(module.eval(), iter(batches), torch.device("cpu"))
    assert set(figures) >= {"mpjpe_mm", "pa_mpjpe_mm", "translation_mm", "a_mpjpe_mm", "b_translation_mm"}

"""The reaction prior: invertibility, training signal, checkpoint reload, refinement, the refined export."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dualhuman_builder.models.base import get_model
from dualhuman_builder.models.reaction_prior.inn import CouplingINN, MLPMapper
from dualhuman_builder.models.reaction_prior.noise import NoiseModel, corrupt
from dualhuman_builder.models.reaction_prior.refine import (blend_weights, refine_sequence, refine_sequences,
                                                            window_starts)  # fmt: skip
from dualhuman_builder.export.features import recover_joints
from dualhuman_builder.models.motion_torch import recover_joints_torch, window_features
from dualhuman_builder.models.reaction_prior.representation import (canonical_pair, flat, rotate_y, to_canonical,
                                                                    to_world, window_frame)  # fmt: skip

TINY = {"window": 16, "latent_dim": 16, "layers": 1, "heads": 2, "ff": 32, "dropout": 0.0, "mapper_blocks": 2,
        "mapper_hidden": 32, "vae_steps": 6, "inn_steps": 4, "stats_batches": 4, "eval_refine_windows": 2,
        "eval_refine_iterations": 3, "refine_iterations": 3}  # fmt: skip


@pytest.fixture(autouse=True)
def _threads():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _motion(B: int, L: int, seed: int = 0, dx: float = 1.3) -> tuple[torch.Tensor, torch.Tensor]:
    """Smooth two-person windows ``(B, L, 22, 3)``: a skeleton swaying and drifting, the other facing it
    ``dx`` metres away and answering with a lag."""
    g = torch.Generator().manual_seed(seed)
    rest = torch.randn(22, 3, generator=g) * 0.15 + torch.tensor([0.0, 1.0, 0.0])
    rest[1], rest[2], rest[16], rest[17] = (torch.tensor([0.1, 0.9, 0.0]), torch.tensor([-0.1, 0.9, 0.0]),
                                            torch.tensor([0.2, 1.4, 0.0]), torch.tensor([-0.2, 1.4, 0.0]))  # fmt: skip
    t = torch.linspace(0, 1, L)[None, :, None, None]
    phase = torch.rand(B, 1, 1, 1, generator=g) * 6.28
    amp = 0.1 + 0.1 * torch.rand(B, 1, 22, 3, generator=g)
    a = rest + amp * torch.sin(6.28 * t + phase)
    a = a + torch.tensor([0.3, 0.0, 0.0]) * t
    b = rest * torch.tensor([-1.0, 1.0, -1.0]) + torch.tensor([dx, 0.0, 0.0]) + amp * torch.sin(6.28 * t + phase - 0.5)
    return a, b


def _batch(B: int = 8, L: int = 16, seed: int = 0) -> dict:
    a, b = _motion(B, L, seed)
    g = torch.Generator().manual_seed(seed + 1)
    return {"joints_actor": a, "joints_reactor": b, "visibility_actor": torch.rand(B, L, 22, generator=g),
            "visibility_reactor": torch.rand(B, L, 22, generator=g)}  # fmt: skip


def _scramble(net: torch.nn.Module, seed: int = 0) -> None:
    """Random weights everywhere (a fresh INN is the identity: its last layers start at zero)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * 0.1)


def test_inn_inverts_to_float_precision_both_directions():
    inn = CouplingINN(24, blocks=4, hidden=32)
    _scramble(inn)
    x = torch.randn(64, 24, generator=torch.Generator().manual_seed(1))
    assert torch.equal(CouplingINN(24, blocks=2, hidden=8)(x), x)  # a fresh network is the identity
    y = inn(x)
    assert (y - x).abs().max() > 0.5  # it does something
    assert torch.allclose(inn.inverse(y), x, atol=1e-5, rtol=0)
    assert torch.allclose(inn(inn.inverse(x)), x, atol=1e-5, rtol=0)
    inn64 = inn.double()
    assert torch.allclose(inn64.inverse(inn64(x.double())), x.double(), atol=1e-12, rtol=0)
    with pytest.raises(NotImplementedError):
        MLPMapper(24).inverse(x)
    with pytest.raises(ValueError):
        CouplingINN(7)


@settings(max_examples=30, deadline=None)
@given(half=st.integers(1, 12), blocks=st.integers(1, 4), seed=st.integers(0, 2**16), scale=st.floats(0.0, 0.15))
def test_inn_inverts_for_any_size_and_weights(half, blocks, seed, scale):
    inn = CouplingINN(2 * half, blocks=blocks, hidden=8, seed=seed)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in inn.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * scale)
    x = torch.randn(5, 2 * half, generator=g, dtype=torch.float64) * 3
    inn = inn.double()
    assert torch.allclose(inn.inverse(inn(x)), x, atol=1e-9, rtol=0)
    assert torch.allclose(inn(inn.inverse(x)), x, atol=1e-9, rtol=0)


def test_losses_run_under_bf16_autocast():
    """The shared loop trains under bf16 autocast on a GPU; the same mixed dtypes on the CPU."""
    spec = get_model("reaction-prior")
    module = spec.build({**spec.default_config(), **TINY})
    module.train()
    for phase in ("vae", "inn"):
        with torch.autocast("cpu", dtype=torch.bfloat16):
            loss = spec.losses(module, _batch(B=2), phase)["loss"]
        loss.float().backward()
        assert torch.isfinite(loss)


def test_window_frame_puts_actor_at_origin_facing_plus_z():
    a, b = _motion(3, 8, seed=2)
    yaw = torch.tensor([0.3, -2.0, 1.0])
    a, b = rotate_y(a, yaw) + torch.tensor([2.0, 0.0, -1.0]), rotate_y(b, yaw) + torch.tensor([2.0, 0.0, -1.0])
    ca, cb, origin, w = canonical_pair(a, b)
    assert torch.allclose(ca[:, 0, 0, [0, 2]], torch.zeros(3, 2), atol=1e-5)
    assert torch.allclose(window_frame(ca)[1], torch.zeros(3), atol=1e-5)
    assert torch.allclose(ca[..., 1], a[..., 1], atol=1e-6)  # heights kept
    gap = lambda x, y: (x[:, :, 0] - y[:, :, 0]).norm(dim=-1)
    assert torch.allclose(gap(ca, cb), gap(a, b), atol=1e-5)  # one frame for both people
    assert torch.allclose(to_world(to_canonical(b, origin, w), origin, w), b, atol=1e-5)


def test_feature_windows_invert_exactly_and_differentiably():
    """The torch inverse of the features equals the export's numpy ``recover_joints`` and gives the
    window back (the reactor where it stands relative to the actor, not at the origin), and a loss on
    the recovered joints reaches every feature row."""
    a, b = _motion(3, 16, seed=2)
    _, cr, _, _ = canonical_pair(a.double(), b.double())
    f = window_features(cr, 20.0)
    assert f.shape == (3, 15, 269)
    back = recover_joints_torch(f.double(), world_from="mean")
    ref = np.stack([recover_joints(x) for x in f.numpy()])
    assert np.abs(back.numpy() - ref).max() < 1e-5
    assert (back - cr).abs().max() < 1e-5 and cr[:, :, 0].norm(dim=-1).min() > 1.0
    x = f.double().requires_grad_(True)
    recover_joints_torch(x, world_from="mean").square().sum().backward()
    assert (x.grad[:, :, 4:67].abs().sum(-1) > 0).all()  # every row's ric positions reach the joints


def test_a_representation_the_prior_does_not_know_is_refused():
    spec = get_model("reaction-prior")
    with pytest.raises(ValueError, match="representation must be one of joints, features"):
        spec.build({**spec.default_config(), **TINY, "representation": "quaternions"})
    with pytest.raises(ValueError, match="features_fps"):
        spec.build({**spec.default_config(), **TINY, "features_fps": 0})


def test_noise_is_larger_where_joints_are_hidden_and_seeded():
    j = torch.zeros(4, 200, 22, 3)
    vis = torch.ones(4, 200, 22)
    vis[..., 11:] = 0.0
    m = NoiseModel(root_bias_m=(0.0, 0.0, 0.0))
    n1 = corrupt(j, vis, m, generator=torch.Generator().manual_seed(3))
    n2 = corrupt(j, vis, m, generator=torch.Generator().manual_seed(3))
    assert torch.equal(n1, n2)
    seen, hidden = n1[..., :11, :].std(), n1[..., 11:, :].std()
    assert 0.015 < seen < 0.04 and hidden > 2.5 * seen
    bias = corrupt(j, torch.ones(4, 200, 22), NoiseModel(visible_m=0.0, occluded_m=0.0, jitter_m=0.0),
                   generator=torch.Generator().manual_seed(4))  # fmt: skip
    assert torch.allclose(bias, bias[:, :1, :1].expand_as(bias))  # one offset of the whole body per item


def test_windows_cover_every_frame_and_blend_without_seams():
    for T, L in [(64, 64), (100, 64), (200, 64), (10, 64), (33, 16)]:
        starts = window_starts(T, L)
        covered = np.zeros(max(T, L), int)
        for s in starts:
            covered[s : s + L] += 1
        assert covered[:T].min() >= 1 and starts[-1] + L >= T
    w = blend_weights(8)
    assert w.tolist() == [1, 2, 3, 4, 4, 3, 2, 1]


def _train(spec, module, phase: str, batch: dict, steps: int, lr: float = 3e-3) -> list[float]:
    opt = torch.optim.AdamW(list(spec.parameters(module, phase)), lr=lr)
    module.train()
    out = []
    for _ in range(steps):
        loss = spec.losses(module, batch, phase)["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        out.append(float(loss.detach()))
    return out


@pytest.mark.parametrize("overrides", [{}, {"mapper": "mlp"}, {"use_vae": False, "noise_augment": False},
                                       {"representation": "features"}, {"latent_tokens": 3}])
def test_losses_fall_on_constructed_windows(overrides):
    torch.manual_seed(0)
    spec = get_model("reaction-prior")
    cfg = {**spec.default_config(), **TINY, **overrides}
    module = spec.build(cfg)
    names = [p.name for p in spec.phases(cfg)]
    assert names == (["vae", "inn"] if cfg["use_vae"] else ["inn"])
    batch = _batch()
    for phase in names:
        frozen = {n: p.detach().clone() for n, p in module.named_parameters()}
        mine = {id(p) for p in spec.parameters(module, phase)}
        # the features' 269 numbers a row (velocities, contacts) start slower than the joints' 66
        fall = 0.9 if cfg["representation"] == "features" and phase == "vae" else 0.8
        losses = _train(spec, module, phase, batch, 40 if phase == "vae" else 15)
        assert np.isfinite(losses).all() and np.mean(losses[-3:]) < fall * losses[0], (phase, losses)
        for n, p in module.named_parameters():  # the other phase's parameters stay as they were
            if id(p) not in mine:
                assert torch.equal(p, frozen[n]), n
    assert int(module.norm.ready) == min(cfg["stats_batches"], 40)
    assert module.norm.std.min() >= 0.01


def test_a_vae_of_several_tokens_codes_each_window_in_all_of_them():
    """MLD's latent_size: ``tokens`` codes of latent_dim numbers, flattened; the decoder reads every one."""
    from dualhuman_builder.models.reaction_prior.vae import MotionVAE

    torch.manual_seed(0)
    one, three = MotionVAE(6, 8, 1, 2, 16, 0.0), MotionVAE(6, 8, 1, 2, 16, 0.0, tokens=3)
    assert (one.code_dim, three.code_dim) == (8, 24)
    x = torch.randn(2, 10, 6)
    mu, logvar = three.encode(x)
    assert mu.shape == logvar.shape == (2, 24)
    for part in range(3):  # moving any one token's numbers changes the decoding
        z = mu.detach().clone()
        z[:, 8 * part : 8 * part + 8] += 1.0
        assert not torch.allclose(three.decode(z, 10), three.decode(mu, 10), atol=1e-4)
    spec = get_model("reaction-prior")
    module = spec.build({**spec.default_config(), **TINY, "latent_tokens": 2})
    assert module.code_dim == 2 * TINY["latent_dim"]
    with pytest.raises(ValueError, match="at least one latent token"):
        MotionVAE(6, 8, tokens=0)


@pytest.mark.parametrize("representation", ["joints", "features"])
def test_refinement_lowers_the_error_on_a_noisy_case(representation):
    """A code that keeps slow motion (the no-VAE ablation's DCT) and white noise on a smooth reactor:
    the windowed, blended optimisation must come out closer to the truth than the noisy input."""
    torch.manual_seed(0)
    spec = get_model("reaction-prior")
    cfg = {**spec.default_config(), **TINY, "use_vae": False, "dct_coeffs": 4, "representation": representation}
    module = spec.build(cfg)
    a, b = _motion(1, 40, seed=5)
    module.norm.observe(module.rows(torch.cat(canonical_pair(a, b)[:2])))
    noisy = b[0] + torch.randn(40, 22, 3, generator=torch.Generator().manual_seed(6)) * 0.03
    refined, n = refine_sequence(module, a[0].numpy(), noisy.numpy(), window=16, iterations=60, lr=0.05)
    assert n == len(window_starts(40, 16)) == 4
    before = (noisy - b[0]).norm(dim=-1).mean()
    after = torch.from_numpy(refined).sub(b[0]).norm(dim=-1).mean()
    assert after < 0.7 * before, (float(before), float(after))
    assert refined.shape == (40, 22, 3) and refined.dtype == np.float32



def test_pooled_refinement_matches_one_sequence_at_a_time(monkeypatch):
    """Windows of several sequences optimised in shared chunks (one split across two chunks) come
    out as each sequence refined alone: every window's code has its own loss and Adam moments."""
    import dualhuman_builder.models.reaction_prior.refine as refine_mod

    torch.manual_seed(0)
    spec = get_model("reaction-prior")
    module = spec.build({**spec.default_config(), **TINY, "use_vae": False, "dct_coeffs": 4})
    pairs = []
    for k, T in enumerate((40, 10, 25)):  # 4 windows, one padded short sequence, 3 windows
        a, b = _motion(1, T, seed=10 + k)
        noisy = b[0] + torch.randn(T, 22, 3, generator=torch.Generator().manual_seed(k)) * 0.03
        pairs.append((a[0].numpy(), noisy.numpy()))
    module.norm.observe(flat(torch.cat(canonical_pair(*_motion(2, 16, seed=9))[:2])))
    alone = [refine_sequence(module, a, n, window=16, iterations=20) for a, n in pairs]
    monkeypatch.setattr(refine_mod, "CHUNK_WINDOWS", 3)
    pooled = refine_sequences(module, pairs, window=16, iterations=20)
    assert [n for _, n in pooled] == [n for _, n in alone] == [4, 1, 3]
    for (p, _), (s, _), (a, _) in zip(pooled, alone, pairs):
        assert p.shape == a.shape
        np.testing.assert_allclose(p, s, atol=1e-5)
    with pytest.raises(ValueError, match="sequence 1"):
        refine_sequences(module, [pairs[0], (pairs[1][0], pairs[0][1])], window=16, iterations=1)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A tiny reaction prior trained by the shared loop on the tiny export: ``(export, run)``."""
    from dualhuman_builder.models.training import train
    from tests.models.tiny_export import make_tiny_export

    root = tmp_path_factory.mktemp("prior")
    export = make_tiny_export(root, n_sequences=4, frames=40)
    torch.set_num_threads(1)
    run = train("reaction-prior", export, root / "run", config_overrides=TINY, batch_size=4, seed=0, progress=False)
    return export, run


def test_an_ablation_starts_from_another_runs_vae_and_trains_only_its_generator(tiny_run, tmp_path):
    """``vae_from``: the MLP generator trained on the full run's VAE runs only the inn phase, keeps that
    VAE and normalisation bit for bit, reloads without the source folder, and a VAE of another shape
    or a run without one is refused with a fix."""
    import shutil

    from dualhuman_builder.errors import DualhumanError
    from dualhuman_builder.models.runs import read_metrics
    from dualhuman_builder.models.training import load_run, train

    export, run = tiny_run
    source = tmp_path / "source"
    shutil.copytree(run, source)
    out = train("reaction-prior", export, tmp_path / "mlp", batch_size=4, seed=1, progress=False,
                config_overrides={**TINY, "mapper": "mlp", "vae_from": str(source)})  # fmt: skip
    assert [r["phase"] for r in read_metrics(out)] == ["inn"] * TINY["inn_steps"]
    full, mlp = load_run(run)[2], load_run(out)[2]
    for k, v in full.state_dict().items():
        if k.startswith(("codec.", "norm.")):
            assert torch.equal(v, mlp.state_dict()[k]), k
    shutil.rmtree(source)
    assert torch.equal(load_run(out)[2].codec.decode(torch.zeros(1, 16), 16), mlp.codec.decode(torch.zeros(1, 16), 16))
    spec = get_model("reaction-prior")
    with pytest.raises(DualhumanError, match="latent_dim") as e:
        spec.build({**spec.default_config(), **TINY, "latent_dim": 8, "vae_from": str(run)})
    assert e.value.fix
    with pytest.raises(DualhumanError, match="use_vae"):
        spec.build({**spec.default_config(), **TINY, "use_vae": False, "vae_from": str(run)})


def test_training_on_the_tiny_export_lowers_the_loss_and_reloads_identically(tiny_run):
    from dualhuman_builder.models.runs import read_metrics
    from dualhuman_builder.models.training import load_run

    run = tiny_run[1]
    records = read_metrics(run)
    assert [r["phase"] for r in records] == ["vae"] * TINY["vae_steps"] + ["inn"] * TINY["inn_steps"]
    vae = [r["loss"] for r in records if r["phase"] == "vae"]
    assert np.mean(vae[-2:]) < vae[0]
    m1 = load_run(run)[2]
    _, _, m2 = load_run(run)
    assert int(m1.norm.ready) == TINY["stats_batches"] and not torch.equal(m1.norm.std, torch.ones(66))
    for (k, a), (_, b) in zip(m1.state_dict().items(), m2.state_dict().items()):
        assert torch.equal(a, b), k
    batch = _batch(B=3, L=16, seed=9)
    ca = canonical_pair(batch["joints_actor"], batch["joints_reactor"])[0]
    with torch.no_grad():
        out1 = m1.decode(m1.react(*m1.encode(ca))[0])
        out2 = m2.decode(m2.react(*m2.encode(ca))[0])
    assert torch.equal(out1, out2)
    with torch.no_grad():
        figures = get_model("reaction-prior").evaluate(m1, iter([batch]), torch.device("cpu"))
    assert figures["windows"] == 3 and np.isfinite(list(figures.values())).all()
    assert figures["refine_before_mpjpe_mm"] > 0 and "recon_mpjpe_mm" in figures
    from dualhuman_builder.models.training import evaluate

    result = evaluate(run, tiny_run[0], "test", batch_size=8)
    assert result["windows"] >= 1 and result["figures"]["recon_mpjpe_mm"] > 0


def test_refine_export_writes_an_export_that_verifies(tiny_run, tmp_path):
    from dualhuman_builder.export.files import load_motion, read_manifest
    from dualhuman_builder.export.verify import verify_export
    from dualhuman_builder.models.reaction_prior.refine import refine_export

    export, run = tiny_run
    out = tmp_path / "refined"
    lines = []
    summary = refine_export(run, export, out, window=16, iterations=2, say=lines.append)
    assert verify_export(out) == []
    assert summary["sequences"] == 4 and len(lines) == 5 and summary["windows"] >= 4
    src, dst = read_manifest(export), read_manifest(out)
    assert {s: i["split"] for s, i in src["sequences"].items()} == {s: i["split"] for s, i in dst["sequences"].items()}
    assert dst["refinement"]["noise"] is not None and "reactor pose and shape of the input (not refined)" in \
        dst["refinement"]["carried_over"]
    sid = "tiny01"  # person b acts: person a is the reactor
    m_in = load_motion(export / "sequences" / sid / "motion.npz")
    m_out = load_motion(out / "sequences" / sid / "motion.npz")
    assert summary["per_sequence"][sid]["reactor"] == "a"
    for k in ("pose", "transl", "shape", "joints", "features"):
        assert np.array_equal(m_in[f"b.{k}"], m_out[f"b.{k}"]), k  # the actor is carried over
    assert np.array_equal(m_in["a.pose"], m_out["a.pose"]) and np.array_equal(m_in["a.shape"], m_out["a.shape"])
    assert not np.allclose(m_in["a.joints"], m_out["a.joints"])
    moved = m_out["a.joints"][:, 0] - m_in["a.joints"][:, 0]
    assert np.allclose(m_out["a.transl"] - m_in["a.transl"], moved, atol=1e-5)
    # the same noisy input given as an export: refining it again gives the same joints
    again = refine_export(run, export, tmp_path / "again", window=16, iterations=2, noisy_from=export, progress=False)
    assert again["before"]["joint_error_mm"] == 0.0 and "the reactor of" in again["noisy_reactor"]
    assert verify_export(tmp_path / "again") == []


def test_refine_export_refuses_what_it_cannot_refine(tiny_run, tmp_path):
    import shutil

    from dualhuman_builder.errors import DualhumanError
    from dualhuman_builder.models.reaction_prior.refine import refine_export

    export, run = tiny_run
    with pytest.raises(DualhumanError, match="into itself"):
        refine_export(run, export, export, progress=False)
    other = tmp_path / "other"
    shutil.copytree(export, other)
    manifest = (other / "manifest.json").read_text().replace('"tiny00"', '"tinyXX"')
    (other / "manifest.json").write_text(manifest)
    with pytest.raises(DualhumanError, match="no sequence 'tiny00'"):
        refine_export(run, export, tmp_path / "out", window=16, iterations=1, noisy_from=other, progress=False)


def test_the_prior_on_the_papers_features_trains_reloads_and_refines_from_the_cli(tiny_run, tmp_path):
    """``--set representation=features``: the run's VAE codes 269-dim feature rows, reloads bit for
    bit, refines an export that verifies, cannot lend its VAE to a run on joints, and refuses an
    export at another frame rate than its features'."""
    from click.testing import CliRunner

    from dualhuman_builder.cli import main
    from dualhuman_builder.errors import DualhumanError
    from dualhuman_builder.export.verify import verify_export
    from dualhuman_builder.models.training import load_run, train

    export = tiny_run[0]
    run, out = tmp_path / "features", tmp_path / "refined"
    sets = [x for k, v in TINY.items() for x in ("--set", f"{k}={v}")] + ["--set", "representation=features"]
    res = CliRunner().invoke(main, ["train", "reaction-prior", str(export), "--out", str(run), "--batch-size", "4",
                                    *sets])  # fmt: skip
    assert res.exit_code == 0, res.output
    m1, m2 = load_run(run)[2], load_run(run)[2]
    assert m1.representation == "features" and m1.norm.mean.shape == (269,) and int(m1.norm.ready) > 0
    ca = canonical_pair(*_motion(2, 16, seed=3))[0]
    with torch.no_grad():
        assert torch.equal(m1.decode(m1.encode(ca)[0]), m2.decode(m2.encode(ca)[0]))
        assert m1.decode(m1.encode(ca)[0]).shape == (2, 16, 22, 3)
    res = CliRunner().invoke(main, ["refine", str(run), str(export), "--out", str(out), "--window", "16",
                                    "--iterations", "2"])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert verify_export(out) == []
    with pytest.raises(DualhumanError, match="representation"):
        train("reaction-prior", export, tmp_path / "mlp", config_overrides={**TINY, "mapper": "mlp", "vae_from": str(run)},
              batch_size=4, seed=0, progress=False)  # fmt: skip
    with pytest.raises(DualhumanError, match="at 20 fps, but this reaction prior's features are computed at 30 fps"):
        train("reaction-prior", export, tmp_path / "fps", config_overrides={**TINY, "representation": "features",
              "features_fps": 30.0}, batch_size=4, seed=0, progress=False)  # fmt: skip

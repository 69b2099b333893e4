"""The two-person pose estimator: attention masks, matching, losses, shapes, the ablation switch, bf16,
local backbone weights, and a few training steps through the shared loop on a tiny rendered export."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dualhuman_builder.body.joints import JOINT22_NAMES, JOINT22_PARENTS
from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.export.writer import normalised_root, root_from_normalised
from dualhuman_builder.models.base import get_model
from dualhuman_builder.models.pose_estimator import PoseEstimatorSpec, predict, to_camera
from dualhuman_builder.models.pose_estimator.attention import NUM_QUERIES, PER_PERSON, inter_mask, intra_mask, query_index
from dualhuman_builder.models.pose_estimator.losses import assignment, estimator_losses, hungarian, root_relative

TINY = {"size": 32, "backbone_width": 8, "backbone_blocks": [1, 1], "d_model": 32, "heads": 2, "layers": 1, "ff": 64,
        "dropout": 0.0}  # fmt: skip
J = JOINT22_NAMES.index


@pytest.fixture(autouse=True)
def _threads():
    n = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors: more threads only spin against the other workers on this machine
    yield
    torch.set_num_threads(n)


def _build(**over):
    spec = PoseEstimatorSpec()
    torch.manual_seed(0)
    return spec, spec.build({**spec.default_config(), **TINY, **over})


def _batch(B: int = 4, size: int = 32, seed: int = 0) -> dict:
    """A batch in ImageFrames' format with consistent targets: random poses 3 m in front of a camera."""
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[40.0, 0.0, size / 2], [0.0, 40.0, size / 2], [0.0, 0.0, 1.0]]).expand(B, 3, 3).clone()
    root = torch.stack([torch.tensor([-0.4, 0.0, 3.0]), torch.tensor([0.4, 0.1, 3.2])]).expand(B, 2, 3).clone()
    root = root + 0.05 * torch.randn(B, 2, 3, generator=g)
    joints = root[:, :, None] + 0.3 * torch.randn(B, 2, 22, 3, generator=g)
    joints[:, :, 0] = root
    transl = torch.from_numpy(normalised_root(root.numpy(), K[:, None].numpy(), size, size)).float()
    return {"image": torch.rand(B, 3, size, size, generator=g), "K": K, "joints_cam": joints, "transl": transl,
            "prob": torch.rand(B, 2, generator=g), "keypoints2d": torch.zeros(B, 2, 22, 3),
            "prev_root": transl + 0.01, "has_prev": torch.zeros(B, dtype=torch.bool),
            "seq_id": ["s"] * B, "camera": ["view00"] * B, "frame": torch.arange(B)}  # fmt: skip


# ------------------------------------------------------------------ masks
def _chain(j: int) -> set[int]:
    out = set()
    while JOINT22_PARENTS[j] >= 0:
        j = JOINT22_PARENTS[j]
        out.add(j)
    return out


def test_intra_mask_lets_a_pose_query_see_only_its_skeleton_neighbours_and_its_track():
    blocked = intra_mask()
    assert blocked.shape == (NUM_QUERIES, NUM_QUERIES) and not blocked.diagonal().any()
    for p in range(2):
        for j in range(22):
            i = query_index(p, "pose", j)
            for k in range(22):
                near = k == j or k in _chain(j) or JOINT22_PARENTS[k] == j
                assert bool(blocked[i, query_index(p, "pose", k)]) == (not near), (p, JOINT22_NAMES[j], JOINT22_NAMES[k])
                assert blocked[i, query_index(1 - p, "pose", k)]  # never the other person in the intra stage
            assert not blocked[i, query_index(p, "track")]
            assert blocked[i, query_index(p, "transl")] and blocked[i, query_index(p, "prob")]
    lw = query_index(0, "pose", J("left_wrist"))
    for other in ("right_knee", "right_wrist", "left_hip", "head"):  # not adjacent on the skeleton
        assert blocked[lw, query_index(0, "pose", J(other))], other
    for seen in ("left_elbow", "left_shoulder", "left_collar", "spine3", "pelvis"):
        assert not blocked[lw, query_index(0, "pose", J(seen))], seen
    knee = query_index(1, "pose", J("left_knee"))
    assert not blocked[knee, query_index(1, "pose", J("left_ankle"))]  # a child
    assert blocked[knee, query_index(1, "pose", J("left_foot"))]  # a grandchild
    for kind in ("transl", "prob", "track"):  # the person's summaries see the whole person, not the other one
        row = blocked[query_index(0, kind)]
        assert not row[:PER_PERSON].any() and row[PER_PERSON:].all()


def test_inter_mask_lets_both_people_pose_and_transl_meet_and_prob_see_only_prob():
    blocked = inter_mask()
    assert not blocked.diagonal().any()
    probs = [query_index(p, "prob") for p in range(2)]
    for i in probs:
        assert [k for k in range(NUM_QUERIES) if not blocked[i, k]] == probs
        assert blocked[[k for k in range(NUM_QUERIES) if k not in probs], i].all()  # no one else sees Prob
    group = [query_index(p, "pose", j) for p in range(2) for j in range(22)] + [query_index(p, "transl") for p in range(2)]
    sub = blocked[group][:, group]
    assert not sub.any()
    assert not blocked[query_index(0, "pose", J("left_wrist")), query_index(1, "pose", J("right_foot"))]


def test_attention_masks_zero_the_blocked_weights_in_the_network():
    _, model = _build()
    layer = model.layers[0]
    h = torch.randn(2, NUM_QUERIES, 32)
    for attn, mask in ((layer.intra, model.intra_mask), (layer.inter, model.inter_mask)):
        _, w = attn(h, h, h, attn_mask=mask, need_weights=True)
        assert torch.all(w[:, mask] == 0) and torch.all(w[:, ~mask] > 0)


# ------------------------------------------------------------------ matching and losses
def _perfect(batch: dict, swap: torch.Tensor) -> dict:
    """Network outputs equal to the truth, with the two people swapped where ``swap``."""
    pose, transl = root_relative(batch["joints_cam"]), batch["transl"].clone()
    logit = torch.logit(batch["prob"].clamp(1e-4, 1 - 1e-4))
    s = swap.view(-1, 1)
    return {"pose": torch.where(s[..., None, None], pose.flip(1), pose), "transl": torch.where(s[..., None], transl.flip(1), transl),
            "prob_logit": torch.where(s, logit.flip(1), logit)}  # fmt: skip


def test_hungarian_matches_swapped_ground_truth_back():
    batch = _batch(6)
    swap = torch.tensor([True, False, True, True, False, False])
    out = _perfect(batch, swap)
    perm = assignment(out, batch, {})
    assert perm.tolist() == [[1, 0] if s else [0, 1] for s in swap.tolist()]
    losses = estimator_losses(out, batch, {})
    assert float(losses["pose"]) < 1e-9 and float(losses["transl"]) < 1e-9
    assert float(losses["swapped"]) == pytest.approx(0.5)
    assert hungarian(np.array([[[5.0, 1.0], [1.0, 5.0]], [[1.0, 5.0], [5.0, 1.0]]])).tolist() == [[1, 0], [0, 1]]


def test_a_track_overrides_the_matching():
    batch = _batch(4)
    batch["has_prev"] = torch.tensor([True, False, True, False])
    out = _perfect(batch, torch.ones(4, dtype=torch.bool))  # every prediction in the wrong order
    perm = assignment(out, batch, {})
    assert perm.tolist() == [[0, 1], [1, 0], [0, 1], [1, 0]]
    tracked = estimator_losses(out, batch, {})
    assert float(tracked["pose"]) > 0.01  # the tracked items are scored in the track's (wrong) order
    batch["has_prev"][:] = False
    assert float(estimator_losses(out, batch, {})["pose"]) < 1e-9


# ------------------------------------------------------------------ network
def test_shapes_predict_and_to_camera():
    _, model = _build()
    batch = _batch(3)
    out = model(batch["image"], batch["prev_root"], batch["has_prev"])
    assert out["pose"].shape == (3, 2, 22, 3) and out["transl"].shape == (3, 2, 3) and out["prob_logit"].shape == (3, 2)
    assert torch.all(out["pose"][:, :, 0] == 0)
    model.eval()
    p = predict(model, batch)
    assert p["joints_cam"].shape == (3, 2, 22, 3) and p["prob"].shape == (3, 2)
    assert torch.allclose(p["joints_cam"][:, :, 0], p["root_cam"]) and ((p["prob"] >= 0) & (p["prob"] <= 1)).all()
    # to_camera inverts the translation target, for a flipped crop (negative x axis of K) and a skewed K too
    root = batch["joints_cam"][:, :, 0].double()
    for K in (batch["K"].double(), torch.tensor([[-40.0, 0.0, 20.0], [0.0, 41.0, 15.0], [0.0, 0.0, 1.0]]).expand(3, 3, 3),
              torch.tensor([[40.0, 2.0, 16.0], [0.0, 41.0, 15.0], [0.0, 0.0, 1.0]]).expand(3, 3, 3)):  # fmt: skip
        t = torch.from_numpy(normalised_root(root.numpy(), K[:, None].numpy(), 32, 32))
        assert torch.allclose(to_camera(t, K[:, None], 32), root, atol=1e-9)
        assert np.allclose(to_camera(t.numpy(), K[:, None].numpy(), 32), root.numpy(), atol=1e-9)
    K = batch["K"][:, None].double().numpy()
    t = normalised_root(root.numpy(), K, 32, 32)
    assert np.allclose(to_camera(t, K, 32), root_from_normalised(t, K, 32, 32))
    assert isinstance(get_model("pose-estimator"), PoseEstimatorSpec)


def test_track_queries_use_the_previous_roots_only_where_there_are_some():
    _, model = _build()
    model.eval()
    batch = _batch(2)
    moved = {**batch, "prev_root": batch["prev_root"] + 0.5}
    with torch.no_grad():
        off = model(batch["image"], batch["prev_root"], torch.tensor([False, False]))
        off_moved = model(batch["image"], moved["prev_root"], torch.tensor([False, False]))
        on = model(batch["image"], batch["prev_root"], torch.tensor([True, False]))
        none = model(batch["image"])
    for k in off:
        assert torch.equal(off[k], off_moved[k]) and torch.equal(off[k], none[k]), k  # no track: prev_root is ignored
        assert not torch.equal(on[k][0], off[k][0]) and torch.equal(on[k][1], off[k][1]), k  # per item
    images_only = {k: batch[k] for k in ("image", "K")}
    assert torch.equal(predict(model, images_only)["joints_cam"], predict(model, batch, use_track=False)["joints_cam"])


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(0.0, 100.0, allow_nan=False), min_size=9, max_size=9))
def test_hungarian_picks_the_cheapest_assignment(values):
    import itertools

    cost = np.asarray(values).reshape(1, 3, 3)
    perm = hungarian(cost)[0].tolist()
    assert sorted(perm) == [0, 1, 2]
    best = min(sum(cost[0, i, q[i]] for i in range(3)) for q in itertools.permutations(range(3)))
    assert sum(cost[0, i, perm[i]] for i in range(3)) == pytest.approx(best)


def test_loss_falls_over_a_few_steps_on_a_fixed_batch():
    spec, model = _build()
    batch = _batch(4)
    batch["has_prev"] = torch.tensor([True, False, True, False])
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    model.train()
    values = []
    for step in range(25):
        torch.manual_seed(step)
        loss = spec.losses(model, batch, "estimator")["loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        values.append(float(loss.detach()))
    assert np.isfinite(values).all()
    assert np.mean(values[-5:]) < 0.5 * values[0], values


def test_the_ablation_switch_replaces_both_masked_stages_by_one_plain_self_attention():
    spec, full = _build()
    _, plain = _build(interaction_attention=False)
    assert hasattr(full.layers[0], "inter") and not hasattr(plain.layers[0], "inter")
    assert not any(".inter." in k for k in plain.state_dict())
    assert len(spec.default_config()) and spec.default_config()["interaction_attention"] is True
    batch = _batch(2)
    for model in (full, plain):
        loss = spec.losses(model, batch, "estimator")["loss"]
        loss.backward()
        assert torch.isfinite(loss)
    # without masks a pose query's output depends on every other query; with them, after one layer's intra stage
    # alone, the left wrist's state does not depend on the right knee's embedding
    h = torch.randn(1, NUM_QUERIES, 32, requires_grad=True)
    layer = full.layers[0]
    y = layer.intra(h, h, h, attn_mask=full.intra_mask, need_weights=False)[0]
    y[0, query_index(0, "pose", J("left_wrist"))].sum().backward()
    assert torch.all(h.grad[0, query_index(0, "pose", J("right_knee"))] == 0)
    assert torch.any(h.grad[0, query_index(0, "pose", J("left_elbow"))] != 0)


def test_bf16_autocast_runs_a_training_step_on_the_cpu():
    spec, model = _build()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3)
    batch = _batch(2)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        losses = spec.losses(model, batch, "estimator")
    opt.zero_grad()
    losses["loss"].float().backward()
    opt.step()
    assert torch.isfinite(losses["loss"]) and all(torch.isfinite(p).all() for p in model.parameters())


def test_local_backbone_weights_are_loaded_and_bad_ones_refused(tmp_path):
    from safetensors.torch import save_file

    _, model = _build()
    state = {k: v.clone() + 1.0 for k, v in model.backbone.state_dict().items()}
    path = tmp_path / "backbone.safetensors"
    save_file(state, str(path))
    _, loaded = _build(backbone_weights=str(path))
    for k, v in loaded.backbone.state_dict().items():
        assert torch.equal(v, state[k]), k
    with pytest.raises(DualhumanError, match="do not exist"):
        _build(backbone_weights=str(tmp_path / "missing.safetensors"))
    with pytest.raises(DualhumanError, match="do not fit"):
        _build(backbone_weights=str(path), backbone_width=16)
    (tmp_path / "junk.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(DualhumanError, match="not a readable"):
        _build(backbone_weights=str(tmp_path / "junk.safetensors"))


def test_evaluate_scores_predictions_in_the_truths_order():
    spec, model = _build()
    model.eval()
    batch = _batch(4)
    figures = spec.evaluate(model, iter([batch]), torch.device("cpu"))
    for k in ("mpjpe_mm", "pa_mpjpe_mm", "translation_mm", "mpjpe_a_mm", "translation_b_mm", "prob_mae"):
        assert np.isfinite(figures[k]) and figures[k] >= 0, k
    assert figures["frames"] == 4
    assert json.dumps(figures)


# ------------------------------------------------------------------ the shared loop on a tiny rendered export
def test_training_on_a_tiny_render_export_lowers_the_loss_and_resumes_to_identical_outputs(tmp_path):
    from tiny_render_export import make_tiny_render_export

    from dualhuman_builder.models import training

    from safetensors.torch import save_file

    export = make_tiny_render_export(tmp_path)
    weights = tmp_path / "backbone.safetensors"  # a user's local backbone: read at the start only
    save_file(_build()[1].backbone.state_dict(), str(weights))
    over = {**TINY, "steps": 16, "lr": 3e-3, "backbone_weights": str(weights)}
    kw = {"config_overrides": over, "batch_size": 8, "progress": False, "tensorboard": False}
    run = training.train("pose-estimator", export, tmp_path / "run", **kw)
    losses = [json.loads(line)["loss"] for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert len(losses) == 16 and np.isfinite(losses).all()
    assert np.mean(losses[-4:]) < 0.8 * np.mean(losses[:2]), losses
    resumed = tmp_path / "resumed"
    training.train("pose-estimator", export, resumed, max_steps=7, **kw)
    weights.unlink()  # the run and its resumption need only their checkpoints now
    training.train("pose-estimator", export, resumed, **kw)
    _, config, a = training.load_run(run)
    _, _, b = training.load_run(resumed)
    from dualhuman_builder.models.images import ImageFrames

    batch = ImageFrames(export, "test", size=config["size"]).batch(np.arange(4))
    pa, pb = predict(a, batch), predict(b, batch)
    for k in pa:
        assert torch.equal(pa[k], pb[k]), k
    assert pa["joints_cam"].shape == (4, 2, 22, 3)
    result = training.evaluate(run, export, "test")
    assert result["figures"]["frames"] == 8 and np.isfinite(result["figures"]["mpjpe_mm"])

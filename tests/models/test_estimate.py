"""`estimate_export` and `dualhuman estimate`: the whole pose pipeline on a real tiny rendered export,
written as an export that `export verify` accepts, with what was estimated and carried over recorded."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st
from tiny_render_export import make_tiny_render_export

import dualhuman_builder.cli.estimate  # noqa: F401  (registers `dualhuman estimate`)
from dualhuman_builder.cli.app import main
from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.export.files import load_motion, read_manifest
from dualhuman_builder.export.verify import verify_export
from dualhuman_builder.models.base import Phase, register
from dualhuman_builder.models.estimate import estimate_export, fill_frames
from dualhuman_builder.models.lifting import NAME as LIFT
from dualhuman_builder.models.lifting import LiftingBaselineSpec
from dualhuman_builder.models.temporal import NAME as TEMPORAL
from dualhuman_builder.models.temporal import TemporalRefinerSpec
from dualhuman_builder.models.training import train


class OracleSpec(LiftingBaselineSpec):
    """An 'estimator' that returns the frame's true camera-space joints, in swapped person order on
    frames 0 and 6 (the first one among them), so linking, identity and the world transform are exact."""

    name = "oracle-estimator"
    predict_keys = ("joints_cam", "frame")

    def phases(self, config):
        return [Phase("lift", 1)]

    @staticmethod
    def predict(module, batch):
        j = batch["joints_cam"].clone()
        swap = (batch["frame"] // 3) % 2 == 0
        j[swap] = j[swap].flip(1)
        return {"joints_cam": j + 0.0 * next(module.parameters()).sum()}


register(LIFT, LiftingBaselineSpec)
register(TEMPORAL, TemporalRefinerSpec)
register(OracleSpec.name, OracleSpec)


@pytest.fixture(autouse=True)
def _threads():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    return make_tiny_render_export(tmp_path_factory.mktemp("estimate"))


@pytest.fixture(scope="module")
def runs(export, tmp_path_factory):
    root = tmp_path_factory.mktemp("runs")
    small = {"size": 16, "hidden": 32, "blocks": 1}
    out = {"oracle": train(OracleSpec.name, export, root / "oracle", config_overrides=small, progress=False),
           "lift": train(LIFT, export, root / "lift", config_overrides={**small, "steps": 3}, batch_size=4, progress=False),
           "temporal": train(TEMPORAL, export, root / "temporal", batch_size=2, progress=False,
                             config_overrides={"window": 8, "hidden": 16, "res_hidden": 8, "blocks": 1, "steps": 2}),
           "prior": train("reaction-prior", export, root / "prior", batch_size=2, progress=False,
                          config_overrides={"window": 8, "latent_dim": 8, "layers": 1, "heads": 2, "ff": 16, "mapper_blocks": 1,
                                            "mapper_hidden": 16, "vae_steps": 2, "inn_steps": 2, "stats_batches": 1})}  # fmt: skip
    return out


def test_fill_frames_interpolates_between_rendered_frames_and_holds_the_ends():
    v = np.array([[0.0, 10.0], [3.0, 40.0]])
    out = fill_frames(np.array([2, 5]), v, 8)
    assert out.shape == (8, 2)
    np.testing.assert_allclose(out[:, 0], [0, 0, 0, 1, 2, 3, 3, 3])
    np.testing.assert_allclose(out[3:6, 1], [20, 30, 40])


@given(st.lists(st.integers(0, 30), min_size=1, max_size=8, unique=True), st.integers(1, 40), st.integers(0, 2**31))
def test_fill_frames_keeps_known_frames_and_stays_between_them(frames, extra, seed):
    frames = np.sort(np.asarray(frames))
    T = int(frames.max()) + extra
    v = np.random.default_rng(seed).normal(size=(len(frames), 2, 3))
    out = fill_frames(frames, v, T)
    assert out.shape == (T, 2, 3) and np.isfinite(out).all()
    np.testing.assert_allclose(out[frames], v, atol=1e-5)
    assert (out >= v.min(0) - 1e-5).all() and (out <= v.max(0) + 1e-5).all()


def test_an_exact_estimator_gives_the_truth_in_the_world_on_rendered_frames(export, runs, tmp_path):
    out = tmp_path / "est"
    summary = estimate_export(runs["oracle"], export, out, progress=False)
    assert verify_export(out) == []
    assert summary["errors"]["estimate_rendered"]["mpjpe_mm"] < 0.05
    assert summary["errors"]["estimate_rendered"]["translation_mm"] < 0.05
    assert summary["stages"] == ["estimate", "fill"] and summary["rendered_frames"] == 8 and summary["frames"] == 24
    for sid in ("tiny00", "tiny01"):
        seq = summary["per_sequence"][sid]
        assert seq["first_frame_swapped"] and seq["rendered_frames"] == 4 and seq["filled_frames"] == 8
        truth = load_motion(export / f"sequences/{sid}/motion.npz")
        est = load_motion(out / f"sequences/{sid}/motion.npz")
        frames = np.arange(0, 12, 3)
        np.testing.assert_allclose(est["a.joints"][frames], truth["a.joints"][frames], atol=1e-4)
        np.testing.assert_allclose(est["b.joints"][frames], truth["b.joints"][frames], atol=1e-4)
        np.testing.assert_array_equal(est["a.pose"], truth["a.pose"])  # carried over, and said so
        meta = json.loads((out / f"sequences/{sid}/sequence.json").read_text())["meta"]["estimation"]
        assert "pose and shape" in " ".join(meta["carried_over"]) and meta["filled_frames"] == 8
    manifest = read_manifest(out)
    assert manifest["estimation"]["stages"] == ["estimate", "fill"] and "renders" in manifest["estimation"]["not_carried"]
    assert manifest["estimation"]["not_estimated"] == []
    assert manifest["sequences"]["tiny01"]["split"] == read_manifest(export)["sequences"]["tiny01"]["split"]


def test_the_cli_runs_the_lifting_baseline_the_temporal_network_and_the_prior(export, runs, tmp_path):
    out = tmp_path / "est"
    res = CliRunner().invoke(main, ["estimate", str(runs["lift"]), str(export), "--out", str(out), "--temporal",
                                    str(runs["temporal"]), "--prior", str(runs["prior"]), "--prior-window", "8",
                                    "--prior-iterations", "2", "--camera", "view01", "--json"])  # fmt: skip
    assert res.exit_code == 0, res.output
    doc = json.loads(res.output)
    assert doc["stages"] == ["estimate", "fill", "temporal", "prior"] and doc["estimator_model"] == LIFT
    assert set(doc["errors"]) >= {"estimate_rendered", "fill", "temporal", "prior", "final"}
    assert verify_export(out) == []
    assert read_manifest(out)["estimation"]["camera"] == "view01"
    again = CliRunner().invoke(main, ["estimate", str(runs["lift"]), str(export), "--out", str(out), "--temporal",
                                      str(runs["temporal"]), "--prior", str(runs["prior"]), "--prior-window", "8",
                                      "--prior-iterations", "2", "--camera", "view01", "--no-progress"])  # fmt: skip
    assert again.exit_code == 0 and "up to date: 2 sequences" in again.output, again.output


def test_wrong_runs_and_cameras_are_clear_errors(export, runs, tmp_path):
    with pytest.raises(DualhumanError, match="cannot estimate"):
        estimate_export(runs["temporal"], export, tmp_path / "a", progress=False)
    with pytest.raises(DualhumanError, match="not of the temporal refiner"):
        estimate_export(runs["oracle"], export, tmp_path / "b", temporal_run=runs["lift"], progress=False)
    with pytest.raises(DualhumanError):
        estimate_export(runs["oracle"], export, tmp_path / "c", camera="nope", progress=False)
    with pytest.raises(DualhumanError, match="into itself"):
        estimate_export(runs["oracle"], export, export, progress=False)
    (tmp_path / "empty").mkdir()
    with pytest.raises(DualhumanError):  # not an export: said so, not a missing-file traceback
        estimate_export(runs["oracle"], tmp_path / "empty", tmp_path / "d", progress=False)


def test_the_prior_weight_is_the_callers_when_given_and_recorded(export, runs, tmp_path):
    kw = {"prior_run": runs["prior"], "prior_window": 8, "prior_iterations": 3, "progress": False}
    light = estimate_export(runs["oracle"], export, tmp_path / "light", prior_lambda=0.0, **kw)
    heavy = estimate_export(runs["oracle"], export, tmp_path / "heavy", prior_lambda=1e3, **kw)
    assert read_manifest(tmp_path / "light")["estimation"]["prior"]["lambda_prior"] == 0.0
    assert read_manifest(tmp_path / "heavy")["estimation"]["prior"]["lambda_prior"] == 1e3
    assert light["errors"]["prior"]["mpjpe_mm"] != heavy["errors"]["prior"]["mpjpe_mm"]  # the weight reaches the optimiser
    with pytest.raises(DualhumanError, match="finite number >= 0"):
        estimate_export(runs["oracle"], export, tmp_path / "bad", prior_lambda=-1.0, **kw)


def test_an_estimate_of_the_same_runs_input_and_settings_is_read_back_not_made_again(export, runs, tmp_path):
    out = tmp_path / "est"
    kw = {"temporal_run": runs["temporal"], "prior_run": runs["prior"], "prior_window": 8, "prior_iterations": 2,
          "progress": False}  # fmt: skip
    first = estimate_export(runs["lift"], export, out, **kw)
    stamp = (out / "manifest.json").stat().st_mtime_ns
    again = estimate_export(runs["lift"], export, out, **kw)
    assert not first["up_to_date"] and again["up_to_date"]
    assert (out / "manifest.json").stat().st_mtime_ns == stamp  # nothing rewritten
    assert {k: v for k, v in again.items() if k != "up_to_date"} == {k: v for k, v in first.items() if k != "up_to_date"}
    assert not estimate_export(runs["lift"], export, out, force=True, **kw)["up_to_date"]
    other = estimate_export(runs["lift"], export, out, **{**kw, "prior_lambda": 5.0})  # another setting: estimated again
    assert not other["up_to_date"] and read_manifest(out)["estimation"]["prior"]["lambda_prior"] == 5.0
    assert not estimate_export(runs["oracle"], export, out, **{**kw, "prior_lambda": 5.0})["up_to_date"]  # another run
    assert verify_export(out) == []


def test_frames_estimated_together_are_the_frames_estimated_one_at_a_time(export, tmp_path):
    """The sequences' frames go through the estimator in lockstep batches; with track inputs from each
    sequence's own previous estimate, a batch of many gives what batches of one give."""
    from dualhuman_builder.models.estimate import _estimate_views, _predictor
    from dualhuman_builder.models.images import ImageFrames
    from dualhuman_builder.models.training import load_run

    tiny = {"size": 32, "backbone_width": 8, "backbone_blocks": [1, 1], "d_model": 32, "heads": 2, "layers": 1,
            "ff": 64, "steps": 3}  # fmt: skip
    run = train("pose-estimator", export, tmp_path / "pe", config_overrides=tiny, batch_size=2, progress=False)
    spec, config, module = load_run(run)
    module.eval()
    predict, keys = _predictor(spec)
    assert "prev_root" in keys
    ds = ImageFrames(export, "all", size=int(config["size"]), augment=False, cache_mb=0)
    jobs = []
    for k in range(len(ds.ids)):
        rows = np.flatnonzero((ds.index[:, 0] == k) & (ds.index[:, 1] == 0))
        jobs.append((rows[np.argsort(ds.index[rows, 2])], np.zeros((2, 22, 3))))
    assert len(jobs) >= 2 and all(len(r) >= 2 for r, _ in jobs)
    one = _estimate_views(ds, jobs, predict, keys, module, torch.device("cpu"), batch_size=1)
    many = _estimate_views(ds, jobs, predict, keys, module, torch.device("cpu"))
    for (f1, j1, s1), (f2, j2, s2) in zip(one, many, strict=True):
        np.testing.assert_array_equal(f1, f2)
        np.testing.assert_allclose(j1, j2, atol=1e-5)
        assert s1 == s2

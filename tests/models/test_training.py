"""The shared training loop on a real tiny export, with a tiny two-phase model defined here: the loss
falls, the run folder holds what it promises, a checkpoint reloads to identical outputs, a resumed run
ends with the weights of an uninterrupted one, a changed config is refused; evaluate and the CLI."""

from __future__ import annotations

import json
from typing import Any, Iterable, Iterator

import pytest
import torch
from click.testing import CliRunner
from safetensors.torch import load_file
from tiny_export import make_tiny_export

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.models import runs
from dualhuman_builder.models.base import Phase, register
from dualhuman_builder.models.training import evaluate, load_run, merge_config, parse_set, resolve_device, train

torch.set_num_threads(1)


class TinyAE(torch.nn.Module):
    """A linear autoencoder of the reactor's root-relative joints and a map from the actor's code."""

    def __init__(self, hidden: int):
        super().__init__()
        self.enc = torch.nn.Linear(66, hidden)
        self.dec = torch.nn.Linear(hidden, 66)
        self.react = torch.nn.Linear(hidden, hidden)
        self.drop = torch.nn.Dropout(0.1)  # random draws: resume must replay them

    @staticmethod
    def flat(joints: torch.Tensor) -> torch.Tensor:
        return (joints - joints[..., :1, :]).flatten(-2)

    def forward(self, joints_actor: torch.Tensor) -> torch.Tensor:
        return self.dec(self.react(self.enc(self.flat(joints_actor))))


class TinySpec:
    """Two phases: ``ae`` (encoder and decoder, reconstruction with noise), ``react`` (the map alone)."""

    name = "tiny-test-ae"
    last_module: TinyAE | None = None

    def default_config(self) -> dict[str, Any]:
        return {"hidden": 8, "window": 16, "ae_steps": 24, "react_steps": 8, "lr": 3e-2, "cameras": 4}

    def build(self, config):
        TinySpec.last_module = TinyAE(int(config["hidden"]))
        return TinySpec.last_module

    def phases(self, config):
        return [Phase("ae", config["ae_steps"], lr=config["lr"], weight_decay=0.0),
                Phase("react", config["react_steps"], lr=config["lr"])]  # fmt: skip

    def parameters(self, module, phase) -> Iterable[torch.nn.Parameter]:
        if phase == "ae":
            return [*module.enc.parameters(), *module.dec.parameters()]
        return module.react.parameters()

    def losses(self, module, batch, phase) -> dict[str, torch.Tensor]:
        x = module.flat(batch["joints_reactor"])
        if phase == "ae":
            noisy = x + 0.01 * torch.randn_like(x)
            rec = module.dec(module.drop(module.enc(noisy)))
            l1 = (rec - x).abs().mean()
            return {"loss": l1, "l1": l1}
        pred = module.react(module.enc(module.flat(batch["joints_actor"])))
        loss = ((pred - module.enc(x).detach()) ** 2).mean()
        return {"loss": loss}

    def evaluate(self, module, batches: Iterator[dict[str, Any]], device) -> dict[str, float]:
        err, n = 0.0, 0
        for b in batches:
            x = module.flat(b["joints_reactor"])
            err += float((module.dec(module.enc(x)) - x).abs().sum())
            n += x.numel()
        return {"l1_m": err / n, "windows_seen": float(n // (16 * 66))}


register(TinySpec.name, TinySpec)
FAST = {"progress": False, "batch_size": 6}


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    return make_tiny_export(tmp_path_factory.mktemp("models-training"))


@pytest.fixture(scope="module")
def full_run(export, tmp_path_factory):
    run = tmp_path_factory.mktemp("runs") / "full"
    train(TinySpec.name, export, run, seed=3, **FAST)
    return run, TinySpec.last_module


def _weights(run):
    return load_file(str(run / "checkpoints" / "last.safetensors"))


def test_loss_falls_and_the_run_folder_holds_what_it_promises(full_run, export):
    run, _ = full_run
    recs = runs.read_metrics(run)
    assert [r["step"] for r in recs] == list(range(1, 33))
    assert [r["phase"] for r in recs] == ["ae"] * 24 + ["react"] * 8
    ae = [r["loss"] for r in recs if r["phase"] == "ae"]
    assert sum(ae[-4:]) / 4 < 0.6 * sum(ae[:4]) / 4
    assert all(0.0 <= r["loader_share"] <= 1.0 and r["windows_per_s"] > 0 and "l1" in r for r in recs[:24])
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["model"] == TinySpec.name and cfg["config"]["hidden"] == 8 and cfg["train"]["seed"] == 3
    assert cfg["export"]["manifest_sha256"] and cfg["toolkit_version"] and cfg["data"]["swapped"] == ["tiny01"]
    assert cfg["phases"][0] == {"name": "ae", "steps": 24, "lr": 3e-2, "weight_decay": 0.0}
    last = json.loads((run / "checkpoints" / "last.json").read_text())
    assert last["phase"] == "react" and last["global_step"] == 32 and last["phase_step"] == 8
    assert last["optimizer_state"]["param_groups"][0]["lr"] == 3e-2
    names = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert names == ["last.json", "last.safetensors", "model-000000032.safetensors", "optimizer-000000032.safetensors"]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["status"] == "complete" and summary["phases"]["ae"]["steps"] == 24
    assert summary["phases"]["ae"]["final"]["loss"] < ae[0] and summary["windows_per_s"] > 0
    assert "| ae | 24 |" in (run / "README.md").read_text()
    assert (run / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(run.rglob("*.partial")) and not list(run.rglob("*.pt"))


def test_checkpoint_reloads_to_identical_outputs(full_run):
    run, trained = full_run
    spec, config, module = load_run(run)
    assert spec.name == TinySpec.name and config["hidden"] == 8 and not module.training
    x = torch.randn(2, 16, 22, 3)
    trained.eval()
    with torch.no_grad():
        assert torch.equal(module(x), trained(x))
        _, _, again = load_run(run)
        assert torch.equal(again(x), module(x))


def test_a_damaged_or_half_written_checkpoint_is_never_loaded_silently(full_run, tmp_path):
    import shutil

    run = tmp_path / "copy"
    shutil.copytree(full_run[0], run)
    (run / "checkpoints" / ".model-000000040.safetensors.123-ab.partial").write_bytes(b"torn")  # a crash mid-write
    load_run(run)  # last.json still names the complete pair
    weights = run / "checkpoints" / "model-000000032.safetensors"
    weights.write_bytes(weights.read_bytes()[:-8] + b"\x00" * 8)
    with pytest.raises(DualhumanError, match="not the file last.json records") as e:
        load_run(run)
    assert "remove" in e.value.fix


def test_resume_continues_at_the_right_step_and_ends_with_the_same_weights(full_run, export, tmp_path):
    run = tmp_path / "resumed"
    train(TinySpec.name, export, run, seed=3, max_steps=13, **FAST)  # inside phase ae
    last = json.loads((run / "checkpoints" / "last.json").read_text())
    assert (last["phase"], last["phase_step"], last["global_step"]) == ("ae", 13, 13)
    assert json.loads((run / "summary.json").read_text())["status"] == "stopped"
    train(TinySpec.name, export, run, seed=3, max_steps=24, **FAST)  # to the phase's end exactly
    train(TinySpec.name, export, run, seed=3, **FAST)
    full = _weights(full_run[0])
    resumed = _weights(run)
    assert full.keys() == resumed.keys()
    for k in full:
        assert torch.equal(full[k], resumed[k]), k
    a, b = runs.read_metrics(full_run[0]), runs.read_metrics(run)
    assert [r["step"] for r in b] == list(range(1, 33))
    assert [r["loss"] for r in a] == [r["loss"] for r in b]
    steps_before = len(b)
    train(TinySpec.name, export, run, seed=3, **FAST)  # complete: nothing to train
    assert len(runs.read_metrics(run)) == steps_before


def test_a_changed_config_is_refused(full_run, export):
    run, _ = full_run
    with pytest.raises(DualhumanError, match=r"config\.hidden: 8 -> 4") as e:
        train(TinySpec.name, export, run, seed=3, config_overrides={"hidden": 4}, **FAST)
    assert "another --out" in e.value.fix
    with pytest.raises(DualhumanError, match=r"train\.seed: 3 -> 4"):
        train(TinySpec.name, export, run, seed=4, **FAST)
    with pytest.raises(DualhumanError, match="holds a run already"):
        train(TinySpec.name, export, run, seed=3, resume=False, **FAST)
    with pytest.raises(DualhumanError, match="split: train -> fit"):
        train(TinySpec.name, export, run, seed=3, split="fit", **FAST)


def test_a_setting_added_to_the_model_since_the_run_does_not_stop_it_resuming(full_run, export, tmp_path):
    """A run made before its model had a setting resumes as long as the setting keeps its default
    (the value loading the run takes); set to another value, it is refused by name."""
    import shutil

    run = tmp_path / "older"
    shutil.copytree(full_run[0], run)
    doc = json.loads((run / "config.json").read_text())
    hidden = doc["config"].pop("hidden")  # as written before the model had the setting
    (run / "config.json").write_text(json.dumps(doc))
    metrics = (run / "metrics.jsonl").read_bytes()
    train(TinySpec.name, export, run, seed=3, **FAST)  # complete: nothing to train, nothing refused
    assert (run / "metrics.jsonl").read_bytes() == metrics
    with pytest.raises(DualhumanError, match=rf"config\.hidden: {hidden} -> {hidden + 1}"):
        train(TinySpec.name, export, run, seed=3, config_overrides={"hidden": hidden + 1}, **FAST)


def test_a_run_on_the_fit_split_never_sees_the_validation_people(export, tmp_path):
    from dualhuman_builder.export.files import read_manifest
    from dualhuman_builder.models.data import split_ids

    run = train(TinySpec.name, export, tmp_path / "fit", seed=1, split="fit", max_steps=2, **FAST)
    data = json.loads((run / "config.json").read_text())["data"]
    fit = split_ids(export, read_manifest(export), "fit")
    assert data["split"] == "fit" and data["sequences"] == len(fit) < len(split_ids(export, read_manifest(export), "train"))
    assert evaluate(run, export, "validation", batch_size=4)["split"] == "validation"


def test_options_are_checked(export, tmp_path):
    with pytest.raises(DualhumanError, match="no setting 'hiden'") as e:
        train(TinySpec.name, export, tmp_path / "r", config_overrides={"hiden": 4}, **FAST)
    assert "hidden" in e.value.fix
    with pytest.raises(DualhumanError, match="is int"):
        merge_config({"hidden": 8}, {"hidden": "big"})
    assert merge_config({"hidden": 8, "lr": 1e-3}, {"hidden": 4.0, "lr": 1})["hidden"] == 4
    assert merge_config({"noise": {"sigma": 0.1, "on": True}}, {"noise.sigma": 0.2}) == {"noise": {"sigma": 0.2, "on": True}}
    with pytest.raises(DualhumanError, match="no setting 'noise.sigmx'"):
        merge_config({"noise": {"sigma": 0.1}}, {"noise.sigmx": 0.2})
    with pytest.raises(DualhumanError, match="is bool"):
        merge_config({"noise": {"on": True}}, {"noise.on": 1})
    assert parse_set(["a=3", "b=1e-4", "c=true", "d=mlp", "e=[1, 2]"]) == {"a": 3, "b": 1e-4, "c": True, "d": "mlp", "e": [1, 2]}
    with pytest.raises(DualhumanError, match="key=value"):
        parse_set(["novalue"])
    with pytest.raises(DualhumanError, match="no model named"):
        train("no-such-model", export, tmp_path / "r2", **FAST)
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    with pytest.raises(DualhumanError, match="not a run folder"):
        train(TinySpec.name, export, tmp_path / "busy", **FAST)
    with pytest.raises(DualhumanError, match="not a dataset export"):
        train(TinySpec.name, tmp_path, tmp_path / "r3", **FAST)
    if not torch.cuda.is_available():
        with pytest.raises(DualhumanError, match="no CUDA GPU") as e:
            resolve_device("cuda")
        assert "--device cpu" in e.value.fix
    with pytest.raises(DualhumanError, match="not supported|unknown device"):
        resolve_device("tpu")


def test_evaluate_writes_its_figures(full_run, export):
    run, _ = full_run
    result = evaluate(run, export, "test", batch_size=4)
    assert result["split"] == "test" and result["windows"] > 0 and result["figures"]["l1_m"] > 0
    assert json.loads((run / "eval-test.json").read_text()) == result


def test_cli_train_evaluate_and_models(export, tmp_path):
    from dualhuman_builder.cli import main
    from dualhuman_builder.cli import models as _models  # noqa: F401  (registers the commands)

    runner = CliRunner()
    run = tmp_path / "cli-run"
    res = runner.invoke(main, ["train", TinySpec.name, str(export), "--out", str(run), "--steps-scale", "0.25",
                               "--batch-size", "4", "--seed", "1", "--set", "hidden=4", "--no-progress"])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert json.loads((run / "config.json").read_text())["config"]["hidden"] == 4
    assert len(runs.read_metrics(run)) == 6 + 2  # 24 and 8 steps scaled by 0.25
    assert "summary" in res.output or "README" in res.output
    res = runner.invoke(main, ["evaluate", str(run), str(export), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["figures"]["l1_m"] > 0
    res = runner.invoke(main, ["evaluate", str(run), str(export), "--split", "validation", "--json"])
    assert res.exit_code == 0 and json.loads(res.output)["split"] == "validation", res.output
    res = runner.invoke(main, ["train", TinySpec.name, str(export), "--out", str(tmp_path / "fit"), "--split", "fit",
                               "--max-steps", "1", "--batch-size", "4", "--no-progress"])  # fmt: skip
    assert res.exit_code == 0 and json.loads((tmp_path / "fit" / "config.json").read_text())["data"]["split"] == "fit"
    res = runner.invoke(main, ["models"])
    assert res.exit_code == 0 and TinySpec.name in res.output
    res = runner.invoke(main, ["train", TinySpec.name, str(export), "--out", str(run), "--set", "hidden=5", "--no-progress"])
    assert res.exit_code == 2 and "config.hidden" in res.output
    res = runner.invoke(main, ["train", TinySpec.name, str(export), "--out", str(tmp_path / "x"), "--device", "cuda",
                               "--no-progress"])  # fmt: skip
    if not torch.cuda.is_available():
        assert res.exit_code == 2 and "CUDA" in res.output

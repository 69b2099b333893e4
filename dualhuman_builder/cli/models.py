"""`dualhuman train`, `evaluate`, `refine` and `models`: the bundled models, trained on a dataset export."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from dualhuman_builder.cli.app import console, main

_DEVICE = click.Choice(["cpu", "cuda"])


@main.command()
@click.argument("model", metavar="MODEL")
@click.argument("dataset", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--out", "out", type=click.Path(path_type=Path), required=True,
              help="The run folder: config, metrics, checkpoints, curves, summary. An existing run with the same "
                   "settings is continued; one with other settings is refused.")
@click.option("--steps-scale", type=click.FloatRange(min=0.0, min_open=True), default=1.0, show_default=True,
              help="Multiply every phase's steps (0.1 for a quick try; at least one step a phase).")
@click.option("--batch-size", type=click.IntRange(min=1), default=32, show_default=True, help="Windows per step.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the weights, the batches and every random draw.")
@click.option("--device", type=_DEVICE, default="cpu", show_default=True, help="Where to train; cuda needs an NVIDIA GPU.")
@click.option("--amp/--no-amp", default=None,
              help="bf16 mixed precision (default: on with --device cuda, off on the CPU).")
@click.option("--set", "settings", multiple=True, metavar="KEY=VALUE",
              help="Change one of the model's settings (repeatable; `dualhuman models --settings` lists them; a dotted "
                   "key reaches a nested one: noise.occluded_m=0.1). The value is read as JSON when it parses: 3, "
                   "1e-4, true, \"mlp\".")
@click.option("--max-steps", type=click.IntRange(min=0), default=None,
              help="Stop after this many steps of the whole run (a checkpoint is written); run again to continue.")
@click.option("--tensorboard/--no-tensorboard", default=None,
              help="Also log to RUN/tensorboard (default: when tensorboard is installed).")
@click.option("--split", type=click.Choice(["train", "fit"]), default="train", show_default=True,
              help="Train on the whole train split, or on `fit`: the train split without the people of the "
                   "`validation` split, to choose settings on people the model never saw (`evaluate --split validation`).")
@click.option("--progress/--no-progress", default=True, show_default=True, help="Show a progress display.")
def train(model: str, dataset: Path, out: Path, steps_scale: float, batch_size: int, seed: int, device: str,
          amp: bool | None, settings: tuple[str, ...], max_steps: int | None, tensorboard: bool | None, split: str,
          progress: bool):  # fmt: skip
    """Train MODEL on the train split of DATASET (a `dualhuman export` folder) into the run folder --out.

    Every phase of the model runs in order (the reaction prior: its motion VAE, then its invertible
    network), one AdamW optimiser each. Each step is logged to RUN/metrics.jsonl (losses,
    windows/s, the loader's share of the step); checkpoints are safetensors files in
    RUN/checkpoints, written at every phase's end, every ten minutes and on Ctrl-C. Run the same
    command again to continue an interrupted run where it stopped; it ends with the weights an
    uninterrupted run would have. At the end RUN/curves.png plots the losses and RUN/README.md
    says what was trained on what, how long it took and how fast it went.

    \b
    Examples:
      dualhuman train reaction-prior OUT --out runs/prior
      dualhuman train reaction-prior OUT --out runs/quick --steps-scale 0.05
      dualhuman train reaction-prior OUT --out runs/gpu --device cuda
      dualhuman train reaction-prior OUT --out runs/fit --split fit
    """
    from dualhuman_builder.models.training import parse_set
    from dualhuman_builder.models.training import train as run_training

    overrides = parse_set(settings)
    try:
        run = run_training(model, dataset, out, config_overrides=overrides, steps_scale=steps_scale, batch_size=batch_size,
                           seed=seed, device=device, amp=amp, progress=progress, max_steps=max_steps,
                           tensorboard=tensorboard, split=split)  # fmt: skip
    except KeyboardInterrupt:
        console.print(f"interrupted; the checkpoint in {out} continues the run with the same command", highlight=False)
        sys.exit(130)
    summary = json.loads((run / "summary.json").read_text(encoding="utf-8"))
    _print_summary(summary, run)


def _print_summary(summary: dict, run: Path) -> None:
    from rich.markup import escape
    from rich.table import Table

    table = Table(title=f"{summary['model']}: {summary['status']}, {summary['global_step']}/{summary['total_steps']} steps, "
                        f"{summary['time_s']:.1f} s", title_justify="left")  # fmt: skip
    for col in ("phase", "steps", "final loss", "windows/s", "loader share"):
        table.add_column(col, justify="left" if col == "phase" else "right")
    for name, p in summary["phases"].items():
        loss = p.get("final", {}).get("loss")
        wps = p.get("windows_per_s")
        table.add_row(escape(name), str(p.get("steps", 0)), "-" if loss is None else f"{loss:.4g}",
                      "-" if not wps else f"{wps:.1f}", f"{100 * p.get('loader_share', 0.0):.1f} %")  # fmt: skip
    console.print(table)
    console.print(f"run folder: {escape(str(run))} (summary: README.md, curves.png)", highlight=False, soft_wrap=True)


@main.command()
@click.argument("run", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.argument("dataset", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--split", type=click.Choice(["test", "train", "all", "fit", "validation"]), default="test",
              show_default=True, help="Which split of DATASET to measure on (`fit` and `validation` divide the train split "
                                      "by people; see `train --split`).")
@click.option("--batch-size", type=click.IntRange(min=1), default=64, show_default=True, help="Windows per batch.")
@click.option("--device", type=_DEVICE, default="cpu", show_default=True, help="Where to run the model.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the random draws the model's figures make.")
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON.")
def evaluate(run: Path, dataset: Path, split: str, batch_size: int, device: str, seed: int, as_json: bool):
    """Measure the trained model of RUN on a split of DATASET; write RUN/eval-SPLIT.json.

    The figures are the model's own (the reaction prior: reconstruction error of its VAE, and the
    refinement experiment's joint error before and after on a few windows, in mm). The result
    names the dataset's manifest digest, so a figure can be traced to the data it was measured on.

    \b
    Examples:
      dualhuman evaluate runs/prior WS/export
      dualhuman evaluate runs/prior other/export --split all --json
    """
    from rich.markup import escape

    from dualhuman_builder.models.training import evaluate as run_eval

    result = run_eval(run, dataset, split, batch_size=batch_size, device=device, seed=seed)
    if as_json:
        click.echo(json.dumps(result, indent=2))
        return
    console.print(f"{escape(result['model'])} on {result['split']}: {result['sequences']} sequences, "
                  f"{result['windows']} windows", highlight=False)  # fmt: skip
    for name, value in result["figures"].items():
        console.print(f"  {escape(name)}: {'-' if value is None else f'{value:.4g}'}", highlight=False)
    console.print(f"written to {escape(str(run / f'eval-{split}.json'))}", highlight=False, soft_wrap=True)


@main.command()
@click.argument("run", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.argument("dataset", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--out", "out", type=click.Path(path_type=Path), required=True,
              help="Where to write the refined dataset (an export folder; `dualhuman export verify` accepts it).")
@click.option("--window", type=click.IntRange(min=2), default=64, show_default=True,
              help="Frames per optimised window; windows overlap by half and are blended.")
@click.option("--lambda-prior", type=click.FloatRange(min=0.0), default=0.01, show_default=True,
              help="Weight of the prior term (the paper's 0.01). Its scale depends on the data: choose it on the "
                   "validation split (train --split fit; docs/guides/models.md).")
@click.option("--iterations", type=click.IntRange(min=1), default=100, show_default=True,
              help="Optimiser steps per window.")
@click.option("--noisy-from", type=click.Path(file_okay=False, exists=True, path_type=Path), default=None,
              help="Another export of the same sequences whose reactor is the motion to refine (e.g. an estimator's). "
                   "Default: DATASET's reactor corrupted by the model's visibility-driven noise, seeded.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the corruption (without --noisy-from).")
@click.option("--device", type=_DEVICE, default="cpu", show_default=True, help="Where to run the optimisation.")
@click.option("--progress/--no-progress", default=True, show_default=True, help="One line per sequence.")
def refine(run: Path, dataset: Path, out: Path, window: int, lambda_prior: float, iterations: int,
           noisy_from: Path | None, seed: int, device: str, progress: bool):  # fmt: skip
    """Refine the reactor of every sequence of DATASET with the reaction prior of RUN (test-time optimisation).

    For each sliding window the reactor's latent code is optimised so that the decoded motion stays
    close to the noisy reactor while the prior, given the actor, finds it likely (the paper's
    objective). The result is written as an export under --out with the actor unchanged and the
    reactor's joints, features and translation refined; its sequence.json files and manifest say
    what was refined, what was carried over, and the joint error before and after.

    \b
    Examples:
      dualhuman refine runs/prior WS/export --out WS/refined
      dualhuman refine runs/prior OUT --out REFINED --noisy-from EST --device cuda
    """
    from rich.markup import escape

    from dualhuman_builder.models.reaction_prior.refine import refine_export

    def say(text: str) -> None:
        console.print(escape(text), highlight=False, soft_wrap=True)

    summary = refine_export(run, dataset, out, window=window, lambda_prior=lambda_prior, iterations=iterations,
                            device=device, progress=progress, noisy_from=noisy_from, seed=seed, say=say)  # fmt: skip
    if not progress:
        console.print(f"refined {summary.get('sequences')} sequences into {escape(str(out))}", highlight=False, soft_wrap=True)


def _about(spec) -> str:
    """One sentence on a model: its ``about`` attribute, else the first sentence of its package's docstring
    (cross-reference markup removed)."""
    import re
    import sys

    text = getattr(spec, "about", None)
    if not text:
        module = type(spec).__module__
        package = sys.modules.get(module.rsplit(".", 1)[0] if module.count(".") > 2 else module)
        text = (getattr(package, "__doc__", None) or type(spec).__doc__ or "").strip()
    text = re.sub(r":\w+:`~?(?:[\w.]+\.)?([^`]+)`", r"\1", " ".join(str(text).split()))
    return text.split(". ")[0].rstrip(".") + "." if text else ""


@main.command("models")
@click.option("--settings", "show_settings", is_flag=True, help="Also list each model's settings and their defaults.")
@click.option("--json", "as_json", is_flag=True, help="Print names, phases and settings as JSON.")
def models_(show_settings: bool, as_json: bool):
    """List the models `dualhuman train` can train, with their phases (and settings).

    \b
    Examples:
      dualhuman models
      dualhuman models --settings
    """
    from rich.markup import escape

    from dualhuman_builder.models.base import get_model, model_names

    out = {}
    for name in model_names():
        spec = get_model(name)
        config = spec.default_config()
        out[name] = {"phases": [{"name": p.name, "steps": p.steps, "lr": p.lr} for p in spec.phases(config)],
                     "settings": config, "about": _about(spec)}  # fmt: skip
    if as_json:
        click.echo(json.dumps(out, indent=2))
        return
    if not out:
        console.print("no models are installed", highlight=False)
    for name, m in out.items():
        phases = ", ".join(f"{p['name']} ({p['steps']} steps)" for p in m["phases"])
        console.print(f"[bold]{escape(name)}[/]: {escape(m['about'])}", highlight=False, soft_wrap=True)
        console.print(f"  phases: {escape(phases)}", highlight=False, soft_wrap=True)
        if show_settings:
            for key, value in m["settings"].items():
                console.print(f"  {escape(key)} = {escape(json.dumps(value))}", highlight=False, soft_wrap=True)

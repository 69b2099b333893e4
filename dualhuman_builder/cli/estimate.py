"""`dualhuman estimate`: both people's motion estimated from a rendered dataset by a trained pose estimator."""

from __future__ import annotations

import json
from pathlib import Path

import click

from dualhuman_builder.cli.app import console, main


@main.command()
@click.argument("run", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.argument("dataset", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--out", "out", type=click.Path(path_type=Path), required=True,
              help="Where to write the estimate (an export folder; `dualhuman export verify` accepts it).")
@click.option("--temporal", "temporal", type=click.Path(file_okay=False, exists=True, path_type=Path), default=None,
              help="A run of `dualhuman train temporal-refiner`: refine each person's estimated motion with it.")
@click.option("--prior", "prior", type=click.Path(file_okay=False, exists=True, path_type=Path), default=None,
              help="A run of `dualhuman train reaction-prior`: then refine the reactor given the actor (test-time optimisation).")
@click.option("--camera", type=str, default=None, help="The view to estimate from (default: each sequence's first rendered view).")
@click.option("--prior-window", type=click.IntRange(min=2), default=64, show_default=True,
              help="Frames per window of the reaction prior's optimisation.")
@click.option("--prior-iterations", type=click.IntRange(min=1), default=None,
              help="Optimiser steps per window of the reaction prior (default: the prior run's).")
@click.option("--prior-lambda", type=click.FloatRange(min=0.0), default=None,
              help="Weight of the prior term (default: the prior run's lambda_prior). Choose it on a validation split: "
                   "see docs/guides/models.md.")
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True, help="Where to run the models.")
@click.option("--force", is_flag=True,
              help="Estimate again even when --out holds the estimate of the same runs, input and settings.")
@click.option("--progress/--no-progress", default=True, show_default=True, help="One line per sequence.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary (errors of every stage) as JSON.")
def estimate(run: Path, dataset: Path, out: Path, temporal: Path | None, prior: Path | None, camera: str | None,
             prior_window: int, prior_iterations: int | None, prior_lambda: float | None, device: str, force: bool,
             progress: bool, as_json: bool):  # fmt: skip
    """Estimate both people of every rendered sequence of DATASET with the pose estimator of RUN.

    Every rendered frame of one camera goes through the estimator, the people are linked over frames
    by the track of the previous frame's roots, turned from the camera to the world frame, and the
    frames that were not rendered are interpolated; then, when given, the temporal network (--temporal)
    and the reaction prior's test-time optimisation (--prior). The result is written as an export under
    --out: both people's joints, features and translation are estimated; their pose and shape are the
    input's, carried over (not estimated). Its sequence.json files and manifest say so, with the
    errors of every stage against DATASET's joints (MPJPE, PA-MPJPE, translation, mm). RUN may also be
    a run of the lifting baseline (from the render's 2D keypoints). Input is a rendered dataset
    export; a folder of images without ground truth is not supported. When --out already holds the
    estimate of the same runs (config and weights), input and settings, it is kept and its summary read
    back (--force estimates again).

    \b
    Examples:
      dualhuman estimate runs/estimator WS/export --out WS/estimated
      dualhuman estimate runs/estimator OUT --out EST \\
        --temporal runs/smooth --prior runs/prior
    """
    from rich.markup import escape

    from dualhuman_builder.models.estimate import estimate_export

    def say(text: str) -> None:
        console.print(escape(text), highlight=False, soft_wrap=True)

    summary = estimate_export(run, dataset, out, temporal_run=temporal, prior_run=prior, camera=camera, device=device,
                              prior_window=prior_window, prior_iterations=prior_iterations, prior_lambda=prior_lambda, progress=progress and not as_json,
                              say=say, force=force)  # fmt: skip
    if as_json:
        click.echo(json.dumps({k: v for k, v in summary.items() if k != "per_sequence"}, indent=2))
    elif not progress:
        done = "up to date" if summary["up_to_date"] else "estimated"
        console.print(f"{done}: {summary['sequences']} sequences in {escape(str(out))}", highlight=False, soft_wrap=True)

"""The two-person pose estimator of the Dual-Human paper on our renders: the full pipeline, the paper's
ablations, the 2D-lifting baseline, and speed.

For each training seed the script trains, on the rendered export's train split (`models.training.train`):
the pose estimator, the estimator without interaction attention (`interaction_attention=false`), the
temporal refinement network (`temporal-refiner`), the reaction prior (`reaction-prior`) and the lifting
baseline (`lifting-baseline`). Then `models.estimate.estimate_export` runs each pipeline over every
rendered sequence (one camera each): the full pipeline (estimator, temporal network, reaction prior), the
paper's Table 4 ablations (without interaction attention; without the reaction prior; without the
temporal network) and the lifting baseline alone. Figures on the test split's sequences, as mean ± std
over seeds: MPJPE (root-relative), PA-MPJPE and translation (pelvis) error in mm against the export's
joints, over every frame (unrendered ones interpolated, then refined) and over the rendered frames
only; the estimator's own figures before any refinement come from the full pipeline's first stage.
Speed, measured alone after every seed has finished (so `--jobs`, seeds in parallel processes, does not
change it): training images/s of a `--speed-steps` run of each model and inference images/s of the
estimator, at its training size on this machine; with `--device cuda`, also at 512x512 (training steps
and inference on the export's frames resized to 512). Every estimate is checked with `export verify`.
A finished training run in `--work` is kept, and so is an estimate of the same runs, export and settings
(`estimate_export` reads it back), so a stopped bench goes on where it stopped.

    dualhuman synth GT --takes 200 --path ground-truth --export GT/export --render   # a rendered synthetic export
    python benchmarks/bench_pose_estimator.py --export GT/export --seeds 3 --jobs 2  # the experiment
    python benchmarks/bench_pose_estimator.py --quick --out /tmp/pe.json             # a tiny check
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_file import Goal, Table, lookup, write_results

ROOT = Path(__file__).resolve().parents[1]
#: pipeline -> (estimator model, temporal network, reaction prior)
PIPELINES = {
    "full": ("estimator", True, True),
    "no_interaction_attention": ("estimator_no_ia", True, True),
    "no_reaction_prior": ("estimator", True, False),
    "no_temporal": ("estimator", False, True),
    "lifting_baseline": ("lifting", False, False),
}
#: --quick: tiny models and a few steps on a tiny rendered export, to check the script end to end
QUICK = {
    "estimator": {"size": 32, "backbone_width": 8, "backbone_blocks": [1, 1], "d_model": 32, "heads": 2, "layers": 1,
                  "ff": 64, "steps": 6},
    "temporal": {"window": 8, "hidden": 32, "res_hidden": 16, "blocks": 1, "steps": 4},
    "prior": {"window": 8, "latent_dim": 16, "layers": 1, "heads": 2, "ff": 32, "mapper_blocks": 1, "mapper_hidden": 16,
              "vae_steps": 4, "inn_steps": 2, "stats_batches": 2},
    "lifting": {"size": 16, "hidden": 64, "blocks": 1, "steps": 6},
}  # fmt: skip


def _mean_std(values: list[dict]) -> dict:
    """Nested dicts of numbers -> the same keys with ``{"mean", "std"}`` over the list (sample std)."""
    out = {}
    for k, v in values[0].items():
        if isinstance(v, dict):
            out[k] = _mean_std([x[k] for x in values])
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            arr = np.array([x[k] for x in values if x.get(k) is not None], dtype=np.float64)
            out[k] = {"mean": float(arr.mean()), "std": float(arr.std(ddof=1)) if len(arr) > 1 else 0.0}
    return out


def _test_errors(summary: dict, test_ids: set[str]) -> dict:
    """Per stage, the frame-weighted mean errors over the test sequences of an ``estimate_export`` summary."""
    per = [rec for sid, rec in summary["per_sequence"].items() if sid in test_ids]
    out = {}
    for stage in per[0]["errors"]:
        key = "rendered_frames" if stage.endswith("rendered") else None
        weights = [rec[key] if key else rec["rendered_frames"] + rec["filled_frames"] for rec in per]
        out[stage] = {m: float(np.average([rec["errors"][stage][m] for rec in per], weights=weights))
                      for m in per[0]["errors"][stage]}  # fmt: skip
    return out


def _inference_speed(run: Path, export: Path, device: str, size: int | None = None, batch: int = 8,
                     max_images: int = 64) -> float:  # fmt: skip
    """Images/s of the estimator's prediction (no track) on the export's test frames at ``size`` (default:
    the run's), in batches of ``batch``, after one warm-up batch (decoding and cropping not counted)."""
    from dualhuman_builder.models.images import ImageFrames
    from dualhuman_builder.models.pose_estimator import predict
    from dualhuman_builder.models.training import load_run

    _, config, module = load_run(run, device=device)
    ds = ImageFrames(export, "test", size=int(size or config["size"]))
    n = min(len(ds), max_images)
    batches = [{k: (v.to(device) if torch.is_tensor(v) else v) for k, v in ds.batch(np.arange(lo, min(n, lo + batch))).items()}
               for lo in range(0, n, batch)]  # fmt: skip
    with torch.no_grad():
        predict(module, batches[0], use_track=False)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t = time.perf_counter()
        for b in batches:
            predict(module, b, use_track=False)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
    return sum(len(b["seq_id"]) for b in batches) / (time.perf_counter() - t)


def _speed_512(export: Path, work: Path, config: dict, device: str, steps: int = 10) -> dict:
    """Training and inference images/s of the estimator at 512x512 (the paper's input size)."""
    from dualhuman_builder.models.training import train

    run = work / "speed-512"
    shutil.rmtree(run, ignore_errors=True)
    train("pose-estimator", export, run, config_overrides={**config, "size": 512, "steps": steps}, batch_size=8,
          device=device, progress=False)  # fmt: skip
    summary = json.loads((run / "summary.json").read_text())
    return {"train_images_per_s": summary.get("windows_per_s"), "inference_images_per_s": _inference_speed(run, export, device, 512)}


def _models(configs: dict) -> dict[str, tuple[str, dict]]:
    """Run key -> (registered model, config overrides) of everything a seed may train."""
    return {"estimator": ("pose-estimator", configs["estimator"]),
            "estimator_no_ia": ("pose-estimator", {**configs["estimator"], "interaction_attention": False}),
            "temporal": ("temporal-refiner", configs["temporal"]), "prior": ("reaction-prior", configs["prior"]),
            "lifting": ("lifting-baseline", configs["lifting"])}  # fmt: skip


def _train_speed(key: str, export: Path, work: Path, configs: dict, device: str, batch_size: int, steps: int) -> float:
    """Training items/s of run ``key``'s model: a run of ``steps`` steps (one phase each), alone on the
    machine after every seed has finished, so that ``--jobs`` does not change the figure."""
    from dualhuman_builder.models.training import train

    name, cfg = _models(configs)[key]
    run = work / f"speed-{key}"
    shutil.rmtree(run, ignore_errors=True)  # a kept run would not be trained again, nor timed
    train(name, export, run, config_overrides={**cfg, "steps": steps}, batch_size=batch_size, device=device,
          progress=False)  # fmt: skip
    return json.loads((run / "summary.json").read_text())["windows_per_s"]


def _seed(job: tuple) -> dict:
    """Train one seed's models (a finished run is kept) and run every pipeline over the export (an
    estimate of the same inputs is kept too: its ``seconds`` are then the reading's); a
    process of its own with ``--jobs``. Returns ``{"seed", "runs", "verify_problems"}``."""
    from dualhuman_builder.export.verify import verify_export
    from dualhuman_builder.models.estimate import estimate_export
    from dualhuman_builder.models.training import train

    seed, c = job
    if c["threads"] > 0:
        torch.set_num_threads(c["threads"])
    export, work, pipelines, test_ids = Path(c["export"]), Path(c["work"]), c["pipelines"], set(c["test_ids"])
    out: dict = {"seed": seed, "runs": {}, "verify_problems": 0}
    models, runs = _models(c["configs"]), {}
    wanted = set(c["needed"]) | ({"temporal"} if any(PIPELINES[p][1] for p in pipelines) else set()) \
        | ({"prior"} if any(PIPELINES[p][2] for p in pipelines) else set())  # fmt: skip
    if "prior" in wanted and c["prior_from"] is not None:
        runs["prior"] = Path(c["prior_from"]) / f"full-s{seed}"  # checked by main()
        wanted = wanted - {"prior"}
    for key in [k for k in models if k in wanted]:
        name, cfg = models[key]
        runs[key] = work / f"{key}-s{seed}"
        t = time.perf_counter()
        train(name, export, runs[key], config_overrides=cfg, steps_scale=c["steps_scale"], batch_size=c["batch_size"],
              seed=seed, device=c["device"], progress=False)  # fmt: skip
        summary = json.loads((runs[key] / "summary.json").read_text())
        out["runs"][f"{key}-s{seed}"] = {"train_s": summary.get("time_s", time.perf_counter() - t),  # the run's own: a finished run is kept
                                         "items_per_s": summary.get("windows_per_s"), "loader_share": summary.get("loader_share")}  # fmt: skip
    for p in pipelines:
        est, use_t, use_p = PIPELINES[p]
        t = time.perf_counter()
        s = estimate_export(runs[est], export, work / f"estimate-{p}-s{seed}", temporal_run=runs["temporal"] if use_t else None,
                            prior_run=runs["prior"] if use_p else None, camera=c["camera"], device=c["device"],
                            prior_window=c["prior_window"], prior_iterations=c["prior_iterations"],
                            prior_lambda=c["prior_lambda"], progress=False)  # fmt: skip
        out["verify_problems"] += len(verify_export(work / f"estimate-{p}-s{seed}"))
        errs = _test_errors(s, test_ids)
        errs["seconds"] = time.perf_counter() - t
        out["runs"][f"estimate-{p}-s{seed}"] = errs
        print(f"seed {seed} {p}: MPJPE {errs['final']['mpjpe_mm']:.1f} mm, PA-MPJPE {errs['final']['pa_mpjpe_mm']:.1f} mm, "
              f"translation {errs['final']['translation_mm']:.1f} mm", flush=True)  # fmt: skip
    return out


def _prior_from(run: Path, export: Path) -> Path:
    """A finished reaction-prior run to reuse, refused unless every sequence it trained on is in
    ``export``'s train split (its ``train`` or ``fit`` split of an export of the same sequences: the
    motion is the same whether or not an export carries renders), so it never saw a test sequence."""
    from dualhuman_builder.export.files import read_manifest
    from dualhuman_builder.models.data import split_ids

    cfg = json.loads((run / "config.json").read_text()) if (run / "config.json").is_file() else {}
    if cfg.get("model") != "reaction-prior" or not (run / "summary.json").is_file():
        sys.exit(f"--prior-from: {run} is not a finished reaction-prior run")
    theirs = Path(cfg["export"]["path"])
    split = cfg["export"].get("split", "train")
    ours, mine = read_manifest(export), read_manifest(theirs)
    train_ids = set(split_ids(export, ours, "train"))

    def motion(m: dict, sid: str):
        return m.get("files", {}).get(f"sequences/{sid}/motion.npz", {}).get("sha256")

    extra = [sid for sid in split_ids(theirs, mine, split) if sid not in train_ids or motion(mine, sid) != motion(ours, sid)]
    if extra:
        sys.exit(f"--prior-from: {run} trained on {len(extra)} sequences that are not in {export}'s train split "
                 f"with the same motion (e.g. {min(extra)})")
    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--export", type=Path, help="a rendered export (`dualhuman synth ... --path ground-truth --render`)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--pipelines", default=",".join(PIPELINES), help="comma-separated, of " + ", ".join(PIPELINES))
    ap.add_argument("--steps-scale", type=float, default=1.0)
    ap.add_argument("--batch-size", type=int, default=32)
    ap.add_argument("--camera", default=None, help="the view to estimate from (default: each sequence's first)")
    ap.add_argument("--prior-window", type=int, default=64)
    ap.add_argument("--prior-iterations", type=int, default=None)
    ap.add_argument("--prior-lambda", type=float, default=None,
                    help="the prior term's weight (default: the prior run's lambda_prior), e.g. the one "
                         "bench_reaction_prior.py --choose-lambda chose for the full model")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--set", action="append", default=[], metavar="MODEL.KEY=JSON",
                    help="config override of one model (estimator, temporal, prior, lifting), e.g. estimator.size=128")
    ap.add_argument("--prior-from", type=Path, default=None, metavar="DIR",
                    help="use the reaction-prior runs DIR/full-s<seed> (e.g. bench_reaction_prior.py's --work) instead of "
                         "training them; refused unless they trained only on this export's train sequences, same motion")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default; 1 with --jobs)")
    ap.add_argument("--jobs", type=int, default=1, help="seeds at once, each in its own process")
    ap.add_argument("--speed-steps", type=int, default=40,
                    help="training steps of each model's speed run, alone after the seeds (default 40)")
    ap.add_argument("--quick", action="store_true", help="a tiny rendered export, tiny models, a few steps, one seed")
    ap.add_argument("--work", type=Path, default=None, help="folder for the runs (default: a temporary one)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()

    from dualhuman_builder.export.files import read_manifest
    from dualhuman_builder.models.data import split_ids

    if args.threads > 0:
        torch.set_num_threads(args.threads)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-pose-estimator-"))
    configs: dict[str, dict] = {"estimator": {}, "temporal": {}, "prior": {}, "lifting": {}}
    export = args.export
    if args.quick:
        sys.path.insert(0, str(ROOT / "tests" / "models"))
        from tiny_render_export import make_tiny_render_export

        export = make_tiny_render_export(work, n_sequences=3, frames=16, views=2, size=48, every=2)
        configs = {k: dict(v) for k, v in QUICK.items()}
        args.seeds, args.prior_window, args.prior_iterations, args.batch_size, args.speed_steps = 1, 8, 3, 4, 4
    if export is None:
        ap.error("--export is required (or --quick)")
    for item in args.set:
        key, _, raw = item.partition("=")
        model, _, setting = key.partition(".")
        if model not in configs or not setting:
            ap.error(f"--set {item!r}: write MODEL.KEY=JSON with MODEL one of {', '.join(configs)}")
        configs[model][setting] = json.loads(raw)
    test_ids = set(split_ids(export, read_manifest(export), "test"))
    pipelines = [p for p in args.pipelines.split(",") if p]
    needed = {PIPELINES[p][0] for p in pipelines}
    figures: dict = {"pipelines": {}, "runs": {}, "verify_problems": 0}
    per_pipeline: dict[str, list] = {p: [] for p in pipelines}
    estimator_only: list[dict] = []
    if args.prior_from is not None and any(PIPELINES[p][2] for p in pipelines):
        for seed in range(args.seeds):
            _prior_from(args.prior_from / f"full-s{seed}", export)
    t0 = time.perf_counter()
    common = {"export": str(export), "work": str(work), "configs": configs, "pipelines": pipelines, "needed": sorted(needed),
              "prior_from": str(args.prior_from) if args.prior_from is not None else None, "test_ids": sorted(test_ids),
              "steps_scale": args.steps_scale, "batch_size": args.batch_size, "device": args.device, "camera": args.camera,
              "prior_window": args.prior_window, "prior_iterations": args.prior_iterations, "prior_lambda": args.prior_lambda,
              "threads": args.threads if args.jobs == 1 else max(1, args.threads)}  # fmt: skip
    jobs = [(seed, common) for seed in range(args.seeds)]
    if args.jobs == 1:
        done = [_seed(job) for job in jobs]
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            done = list(pool.map(_seed, jobs))  # one seed per process, on its own thread(s); the figures do not depend on it
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    for rec in done:
        figures["runs"].update(rec["runs"])
        figures["verify_problems"] += rec["verify_problems"]
        for p in pipelines:
            per_pipeline[p].append(rec["runs"][f"estimate-{p}-s{rec['seed']}"])
        if "full" in pipelines:
            errs = rec["runs"][f"estimate-full-s{rec['seed']}"]
            estimator_only.append({"rendered": errs["estimate_rendered"], "all_frames": errs["fill"]})
    for p in pipelines:
        figures["pipelines"][p] = _mean_std(per_pipeline[p])
    if estimator_only:
        figures["estimator_only"] = _mean_std(estimator_only)
    speed: dict = {"device": args.device, "train_steps": args.speed_steps}
    for key in ("estimator", "lifting", "temporal"):
        if any(f"{key}-s{s}" in figures["runs"] for s in range(args.seeds)):
            speed[f"{key}_train_items_per_s"] = _train_speed(key, export, work, configs, args.device, args.batch_size,
                                                             args.speed_steps)  # fmt: skip
    if "estimator" in needed:
        speed["estimator_inference_images_per_s"] = _inference_speed(work / "estimator-s0", export, args.device)
        speed["estimator_size"] = int(configs["estimator"].get("size", 64))
        if args.device.startswith("cuda"):
            speed["at_512"] = _speed_512(export, work, configs["estimator"], args.device)
    figures["speed"] = speed
    figures["seconds"] = time.perf_counter() - t0
    figures["test_sequences"] = len(test_ids)
    if "full" in pipelines:
        full = figures["pipelines"]["full"]["final"]
        figures["full_best"] = {p: {m: float(full[m]["mean"] <= figures["pipelines"][p]["final"][m]["mean"])
                                    for m in ("mpjpe_mm", "translation_mm")} for p in pipelines if p != "full"}  # fmt: skip
    goals = [Goal("verify_problems", "<=", 0, "", "every estimate passes `export verify`")]
    if "full" in pipelines:
        goals += [Goal(f"full_best.{p}.{m}", ">=", 1, "", f"full pipeline at least as good as {p} on {m}")
                  for p in figures["full_best"] for m in figures["full_best"][p]]  # fmt: skip
    metrics = ("mpjpe_mm", "pa_mpjpe_mm", "translation_mm")
    rows = [[p, *(f"pipelines.{p}.final.{m}.mean" for m in metrics), *(f"pipelines.{p}.final.{m}.std" for m in metrics)]
            for p in pipelines]  # fmt: skip
    if estimator_only:
        rows.append(["estimator alone (interpolated)", *(f"estimator_only.all_frames.{m}.mean" for m in metrics),
                     *(f"estimator_only.all_frames.{m}.std" for m in metrics)])  # fmt: skip
    tables = [Table("Test sequences, every frame (mm, mean and std over seeds)",
                    ["pipeline", "MPJPE", "PA-MPJPE", "translation", "MPJPE std", "PA-MPJPE std", "translation std"], rows)]
    speed_rows = [[label, f"speed.{key}"] for label, key in (
        ("estimator, training (images/s)", "estimator_train_items_per_s"),
        ("estimator, inference (images/s)", "estimator_inference_images_per_s"),
        ("temporal network, training (windows/s)", "temporal_train_items_per_s"),
        ("lifting baseline, training (frames/s)", "lifting_train_items_per_s"),
        ("estimator at 512x512, training (images/s)", "at_512.train_images_per_s"),
        ("estimator at 512x512, inference (images/s)", "at_512.inference_images_per_s")) if lookup(figures, f"speed.{key}") is not None]  # fmt: skip
    if speed_rows:
        tables.append(Table(f"Speed on {args.device}, at the estimator's training size ({speed.get('estimator_size')} px) "
                            "unless said", ["what", "rate"], speed_rows))  # fmt: skip
    notes = ("--quick: a tiny rendered export and tiny models; the figures check the script, they measure nothing."
             if args.quick else "")  # fmt: skip
    if args.prior_from is not None:
        figures["prior_runs"] = {f"s{seed}": str(args.prior_from / f"full-s{seed}") for seed in range(args.seeds)}
    path = write_results("pose_estimator", figures, params={**vars(args), "configs": configs}, goals=goals, tables=tables,
                         notes=notes, out=args.out)  # fmt: skip
    print(path)


if __name__ == "__main__":
    main()

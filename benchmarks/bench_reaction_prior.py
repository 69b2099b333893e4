"""The reaction prior of the Dual-Human paper on our data: the paper's refinement experiment with its
ablations, reaction generation from the actor alone, and training speed.

For each variant (the full model; the paper's Table 4 ablations: without the motion VAE, the INN
replaced by an MLP, without noise augmentation; and `features`, the full model on the paper's 269-dim
motion features instead of joint positions) and each training seed, the prior is trained on the
export's train split (`models.training.train`; the two generator ablations start from the full run's VAE
of the same seed and train only the generator, unless `--own-vae`), then every test sequence's reactor is corrupted by the
visibility-driven noise (`reaction_prior.noise`, the same draw for every variant and seed) and refined
with the prior (`reaction_prior.refine`: windows of 64, half overlap, lambda_prior 0.01). With
`--choose-lambda`, the prior trains on the `fit` split instead, each run refines the `validation` split
(people it never saw; `models.data.validation_subjects`) at each candidate weight, and each variant is
scored on the test split at the weight with its lowest validation MPJPE (mean over seeds). Figures, as
mean ± std over seeds: MPJPE (root-relative), PA-MPJPE and translation (pelvis) error of the reactor
before and after, in mm (`models.metrics`), and the weighted prior term's share of the objective at the
last step (how much the prior, rather than the observation, steers the result). Reaction generation: the reactor decoded from the prior's
mean given the clean actor, per test window: Fréchet distance of joint positions and diversity against
the held-out reactions, proxy penetration and proxy contact F1 against the ground truth. Speed:
training windows/s and the loader's share of a step, from the run's summary. A refined export is
written once with `refine_export` and checked with `export verify`.

    python benchmarks/bench_reaction_prior.py --export WS/export --seeds 3          # the experiment
    python benchmarks/bench_reaction_prior.py --export WS/export --choose-lambda 0.01,0.1,1,10,100,1000
    python benchmarks/bench_reaction_prior.py --export WS/export --vae-set vae_steps=2000  # another VAE schedule
    python benchmarks/bench_reaction_prior.py --quick --out /tmp/rp.json            # a tiny check
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_file import Goal, Table, write_results

ROOT = Path(__file__).resolve().parents[1]
VARIANTS = {
    "full": {},
    "no_vae": {"use_vae": False},
    "mlp": {"mapper": "mlp"},
    "no_noise": {"noise_augment": False},
    "features": {"representation": "features"},
}
#: The paper's Table 4 ablations, which the full model should beat; ``features`` is not one of them but
#: the full model on the paper's 269-dim features instead of joint positions, a candidate to compare.
ABLATIONS = ("no_vae", "mlp", "no_noise")
#: Variants that change only the generator: by default they start from the full run's VAE of the same seed
#: (``vae_from``), the VAE being independent of the generator and of the noise augmentation.
SHARES_VAE = ("mlp", "no_noise")
#: --quick: a tiny model and a few steps, to check the script end to end (figures mean nothing)
QUICK = {"window": 32, "latent_dim": 16, "layers": 1, "heads": 2, "ff": 32, "dropout": 0.0, "mapper_blocks": 2,
         "mapper_hidden": 32, "vae_steps": 20, "inn_steps": 10, "stats_batches": 4, "dct_coeffs": 4,
         "eval_refine_windows": 2, "eval_refine_iterations": 3}  # fmt: skip


def _test_sequences(export: Path, split: str) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """``(seq_id, actor joints, reactor joints)`` of the split, roles resolved as the training data does."""
    from dualhuman_builder.export.files import read_manifest
    from dualhuman_builder.models.data import actor_is_b, read_sequence, split_ids

    manifest = read_manifest(export)
    out = []
    for sid in split_ids(export, manifest, split):
        motion, text = read_sequence(export, sid)
        a, b = motion["a.joints"].astype(np.float32), motion["b.joints"].astype(np.float32)
        out.append((sid, b, a) if actor_is_b(text) else (sid, a, b))
    return out


def _dataset(export: Path, splits: tuple[str, ...] = ("train", "test")) -> dict:
    """What the figures were measured on: the splits' sizes and, for an export of `dualhuman synth`, the
    plan's arguments that shape the data (types, hold-outs, frame rate, seed) and the takes it lost."""
    from dualhuman_builder.export.files import read_manifest
    from dualhuman_builder.models.data import split_ids

    manifest = read_manifest(export)
    out = {split: len(split_ids(export, manifest, split)) for split in splits}
    synth = manifest.get("synth")
    if isinstance(synth, dict):
        a = synth.get("arguments", {})
        out["synth"] = {k: a.get(k) for k in ("takes", "seed", "types", "fps", "hold_out_actors", "hold_out_types",
                                               "long_share", "takes_per_day")}  # fmt: skip
        out["synth"]["failed"] = len(synth.get("failed") or {})
    return out


def _refinement(module, seqs, config: dict, window: int, iterations: int, lambda_prior: float, device: str) -> dict:
    from dualhuman_builder.models import metrics
    from dualhuman_builder.models.reaction_prior.refine import corrupt_sequence, refine_sequences
    from dualhuman_builder.models.visibility import joint_visibility

    truth, noisy, pairs = [], [], []
    for sid, actor, reactor in seqs:
        _, vis_b = joint_visibility(actor, reactor)
        n = corrupt_sequence(reactor, vis_b, config, 0, sid)  # seed 0: the same draw for every variant and seed
        truth.append(reactor), noisy.append(n), pairs.append((actor, n))
    terms: dict[str, float] = {}
    refined = [r for r, _ in refine_sequences(module, pairs, window, lambda_prior, iterations,
                                              float(config["refine_lr"]), device, terms)]  # fmt: skip
    t, n, r = (np.concatenate(x) for x in (truth, noisy, refined))

    def figs(p):
        return {"mpjpe_mm": metrics.mpjpe(p, t), "pa_mpjpe_mm": metrics.pa_mpjpe(p, t),
                "translation_mm": metrics.translation_error(p, t),
                "joint_error_mm": metrics.mpjpe(p, t, root=None)}  # fmt: skip

    before, after = figs(n), figs(r)
    return {"before": before, "after": after, "mpjpe_reduction": 1.0 - after["mpjpe_mm"] / before["mpjpe_mm"],
            "frames": len(t), "prior_share": terms.get("prior", 0.0) / max(1e-12, terms.get("data", 0.0) + terms.get("prior", 0.0))}  # fmt: skip


def _generation(module, seqs, window: int, device: str) -> dict:
    from dualhuman_builder.models import metrics
    from dualhuman_builder.models.reaction_prior.refine import window_starts
    from dualhuman_builder.models.reaction_prior.representation import canonical_pair, to_world

    wa, wr = [], []
    for _, actor, reactor in seqs:
        if len(actor) < window:
            continue
        for s in window_starts(len(actor), window):
            wa.append(actor[s : s + window]), wr.append(reactor[s : s + window])
    if len(wa) < 2:
        return {"windows": len(wa)}
    a, r = torch.from_numpy(np.stack(wa)).to(device), torch.from_numpy(np.stack(wr)).to(device)
    module.eval()
    with torch.no_grad():
        ca, _, origin, yaw = canonical_pair(a, r)
        pm, _ = module.react(*module.encode(ca))
        gen = to_world(module.decode(pm, window), origin, yaw).cpu().numpy()
    a, r = a.cpu().numpy(), r.cpu().numpy()
    pen_gen, pen_true = metrics.proxy_penetration(a, gen), metrics.proxy_penetration(a, r)
    contacts = metrics.proxy_contact_scores(a, gen, a, r)
    def safe(fn, *a, **k):  # FD needs more frames than coordinates, diversity more windows than pairs
        try:
            return fn(*a, **k)
        except metrics.MetricInputError:
            return None

    pairs = min(metrics.DIVERSITY_PAIRS, len(wa) - 1)
    return {"windows": len(wa), "fd_mm2": safe(metrics.joint_positions_fd, gen, r), "diversity_pairs": pairs,
            "diversity_mm": safe(metrics.joint_positions_diversity, gen, pairs),
            "diversity_truth_mm": safe(metrics.joint_positions_diversity, r, pairs),
            "mpjpe_mm": metrics.mpjpe(gen, r), "translation_mm": metrics.translation_error(gen, r),
            "penetration_mean_mm": pen_gen["mean_depth_mm"], "penetration_truth_mean_mm": pen_true["mean_depth_mm"],
            "contact_f1": contacts.get("f1")}  # fmt: skip


def _mean_std(values: list[dict]) -> dict:
    """Nested dicts of numbers -> the same keys with ``{"mean", "std"}`` over the list (sample std)."""
    out = {}
    for k, v in values[0].items():
        if isinstance(v, dict):
            out[k] = _mean_std([x[k] for x in values])
        elif isinstance(v, (int, float)) and v is not None:
            arr = np.array([x[k] for x in values if x.get(k) is not None], dtype=np.float64)
            out[k] = {"mean": float(arr.mean()), "std": float(arr.std(ddof=1)) if len(arr) > 1 else 0.0}
    return out


def _train(job: tuple) -> dict:
    """Train one ``(variant, seed)`` (a finished run is kept) and, with ``--choose-lambda``, refine the
    validation split at each candidate weight; a process of its own with ``--jobs``."""
    from dualhuman_builder.models.training import load_run, train

    name, seed, c = job
    shared = name in SHARES_VAE and c["share_vae"]  # the generator ablations train on the full run's VAE
    if c["threads"] > 0:
        torch.set_num_threads(c["threads"])
    export, run = Path(c["export"]), Path(c["work"]) / f"{name}-s{seed}"
    t = time.perf_counter()
    vae = c["vae_overrides"] if VARIANTS[name].get("use_vae", True) else {}  # the DCT code has no VAE to shape
    train("reaction-prior", export, run, config_overrides={**c["overrides"], **vae, **VARIANTS[name],
                                                          **({"vae_from": str(Path(c["work"]) / f"full-s{seed}")} if shared else {})},
          steps_scale=c["steps_scale"], batch_size=c["batch_size"], seed=seed, device=c["device"],
          progress=False, split=c["train_split"])  # fmt: skip
    summary = json.loads((run / "summary.json").read_text()) if (run / "summary.json").is_file() else {}
    rec = {"train_s": summary.get("time_s", time.perf_counter() - t),  # the run's own: a finished run is not retrained
           "windows_per_s": summary.get("windows_per_s"), "loader_share": summary.get("loader_share")}  # fmt: skip
    if c["lambdas"]:
        module = load_run(run, device=c["device"])[2]
        val = _test_sequences(export, "validation")
        rec["validation"] = {_lam_key(lam): _refinement(module, val, module.config, c["window"], c["iterations"], lam,
                                                     c["device"])["after"]["mpjpe_mm"] for lam in c["lambdas"]}  # fmt: skip
    return rec


def _score(job: tuple, seqs: list | None = None) -> dict:
    """Score one trained ``(variant, seed)`` on the test split at ``lambda_prior``: refinement,
    generation; a process of its own with ``--jobs``."""
    from dualhuman_builder.models.training import load_run

    name, seed, c, lam = job
    if c["threads"] > 0:
        torch.set_num_threads(c["threads"])
    seqs = seqs if seqs is not None else _test_sequences(Path(c["export"]), "test")
    module = load_run(Path(c["work"]) / f"{name}-s{seed}", device=c["device"])[2]
    t = time.perf_counter()
    refine = _refinement(module, seqs, module.config, c["window"], c["iterations"], lam, c["device"])
    rec = {"refine": refine, "refine_s": time.perf_counter() - t, "lambda_prior": lam,
           "generation": _generation(module, seqs, c["window"], c["device"])}  # fmt: skip
    print(f"{name} seed {seed}: MPJPE {refine['before']['mpjpe_mm']:.1f} -> {refine['after']['mpjpe_mm']:.1f} mm "
          f"at lambda_prior {lam:g}", flush=True)  # fmt: skip
    return rec


def _lam_key(lam: float) -> str:
    """A weight as a key of the results file, without the dot a figure's path would split at: 0.01 -> 0_01."""
    return f"{lam:g}".replace(".", "_")


def _choose_lambda(recs: dict, name: str, seeds: int, lambdas: list[float]) -> float:
    """The candidate weight with the lowest validation MPJPE after refinement, mean over seeds."""
    sweep = {lam: float(np.mean([recs[(name, s)]["validation"][_lam_key(lam)] for s in range(seeds)])) for lam in lambdas}
    return min(sweep, key=sweep.get)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--export", type=Path, help="a dataset export (e.g. of `dualhuman synth`, >= 500 sequences)")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated, of " + ", ".join(VARIANTS))
    ap.add_argument("--steps-scale", type=float, default=1.0)
    ap.add_argument("--batch-size", type=int, default=32)
    ap.add_argument("--iterations", type=int, default=100, help="refinement steps per window")
    ap.add_argument("--lambda-prior", type=float, default=0.01, help="refinement's prior weight (without --choose-lambda)")
    ap.add_argument("--choose-lambda", default="", metavar="L1,L2,...",
                    help="train on the `fit` split, refine the `validation` split at each weight, and score the test "
                         "split at each variant's best (mean over seeds)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=JSON", help="config override for every variant")
    ap.add_argument("--vae-set", action="append", default=[], metavar="KEY=JSON",
                    help="config override for the variants with the motion VAE only (its size, tokens, steps): the "
                         "ablation without it then keeps its runs")
    ap.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default; 1 with --jobs)")
    ap.add_argument("--jobs", type=int, default=1, help="trainings at once, each in its own process")
    ap.add_argument("--own-vae", action="store_true",
                    help="train the generator ablations' VAEs too, instead of starting them from the full run's")
    ap.add_argument("--quick", action="store_true", help="a tiny export, a tiny model, a few steps, one seed")
    ap.add_argument("--work", type=Path, default=None, help="folder for the runs (default: a temporary one)")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()

    from dualhuman_builder.export.verify import verify_export
    from dualhuman_builder.models.reaction_prior.refine import refine_export

    if args.threads > 0:
        torch.set_num_threads(args.threads)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-reaction-prior-"))
    overrides = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)}
    vae_overrides = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.vae_set)}
    export = args.export
    if args.quick:
        sys.path.insert(0, str(ROOT))
        from tests.models.tiny_export import make_tiny_export

        export = make_tiny_export(work, n_sequences=4, frames=80)
        overrides = {**QUICK, **overrides}
        args.seeds, args.iterations = 1, 5
    if export is None:
        ap.error("--export is required (or --quick)")
    window = int(overrides.get("window", 64))
    seqs = _test_sequences(export, "test")
    variants = [v for v in args.variants.split(",") if v]
    figures: dict = {"variants": {}, "runs": {}}
    t0 = time.perf_counter()
    jobs = [(name, seed) for name in variants for seed in range(args.seeds)]
    common = {"export": str(export), "work": str(work), "overrides": overrides, "vae_overrides": vae_overrides, "window": window,
              "steps_scale": args.steps_scale, "batch_size": args.batch_size, "device": args.device,
              "iterations": args.iterations, "lambda_prior": args.lambda_prior,
              "threads": args.threads if args.jobs == 1 else max(1, args.threads)}  # fmt: skip
    common["share_vae"] = "full" in variants and not args.own_vae
    lambdas = [float(x) for x in args.choose_lambda.split(",") if x.strip()]
    common.update(lambdas=lambdas, train_split="fit" if lambdas else "train")
    # first the runs that train a VAE (or none), then the ablations that take the full run's
    waves = [[j for j in jobs if not (common["share_vae"] and j[0] in SHARES_VAE)],
             [j for j in jobs if common["share_vae"] and j[0] in SHARES_VAE]]  # fmt: skip
    def run_waves(fn, waves) -> dict:
        if args.jobs == 1:
            return {j[:2]: fn(j, seqs) if fn is _score else fn(j) for wave in waves for j in wave}
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        out = {}
        with ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            for wave in waves:  # one training per process, each on its own thread(s); the figures do not depend on it
                out.update(zip((j[:2] for j in wave), pool.map(fn, wave)))
        return out

    trained = run_waves(_train, [[(n, s, common) for n, s in wave] for wave in waves])
    chosen = {n: _choose_lambda(trained, n, args.seeds, lambdas) if lambdas else args.lambda_prior for n in variants}
    scored = run_waves(_score, [[(n, s, common, chosen[n]) for n, s in jobs]])
    recs = {j: {**trained[j], **scored[j]} for j in jobs}
    for name in variants:
        per_seed = []
        for seed in range(args.seeds):
            rec = recs[(name, seed)]
            figures["runs"][f"{name}-s{seed}"] = rec
            per_seed.append({k: v for k, v in rec.items() if v is not None})
        figures["variants"][name] = _mean_std(per_seed)
        figures["variants"][name]["lambda_prior"] = chosen[name]
    if "full" in variants:
        full_run = work / "full-s0"
        t = time.perf_counter()
        summary = refine_export(full_run, export, work / "refined", window=window, lambda_prior=chosen["full"],
                                iterations=args.iterations, device=args.device, progress=False)  # fmt: skip
        figures["refine_export"] = {"seconds": time.perf_counter() - t, "sequences": summary["sequences"],
                                    "windows": summary["windows"],
                                    "verify_problems": len(verify_export(work / "refined"))}  # fmt: skip
        full = figures["variants"]["full"]["refine"]["after"]["mpjpe_mm"]["mean"]
        figures["beats"] = {n: float(full < figures["variants"][n]["refine"]["after"]["mpjpe_mm"]["mean"])
                            for n in variants if n in ABLATIONS}  # fmt: skip
    figures["seconds"] = time.perf_counter() - t0
    figures["test_sequences"] = len(seqs)
    figures["dataset"] = _dataset(export, ("train", "test", "fit", "validation") if lambdas else ("train", "test"))
    goals = [Goal("variants.full.refine.mpjpe_reduction.mean", ">=", 0.25, "", "refinement's MPJPE cut, full model")]
    goals += [Goal(f"beats.{n}", ">=", 1, "", f"full model refines better than {n}") for n in variants if n in ABLATIONS]
    goals.append(Goal("refine_export.verify_problems", "<=", 0, "", "refined export passes `export verify`"))
    if args.device.startswith("cuda"):
        goals.append(Goal("variants.full.loader_share.mean", "<=", 0.10, "", "loader share of a training step (GPU)"))
    def row(n: str, cells) -> list[str]:
        return [n, *(f"variants.{n}.{c}" for c in cells)]

    refine_cells = ("lambda_prior", "refine.before.mpjpe_mm", "refine.after.mpjpe_mm", "refine.mpjpe_reduction", "refine.after.pa_mpjpe_mm",
                    "refine.before.translation_mm", "refine.after.translation_mm", "refine.prior_share")  # fmt: skip
    gen_cells = ("generation.fd_mm2", "generation.diversity_mm", "generation.mpjpe_mm", "generation.penetration_mean_mm",
                 "generation.contact_f1")  # fmt: skip
    tables = [Table("Refinement of the corrupted test reactors (mm; mean ± std over seeds)",
                    ["variant", "λ_prior", "MPJPE before", "MPJPE after", "MPJPE cut", "PA-MPJPE after", "translation before",
                     "translation after", "prior's share of the objective"], [row(n, refine_cells) for n in variants]),
              Table("Reaction generation from the actor alone, test windows (mean ± std over seeds)",
                    ["variant", "FD (mm²)", "diversity (mm)", "MPJPE (mm)", "penetration (mm)", "contact F1"],
                    [row(n, gen_cells) for n in variants]),
              Table("Training", ["variant", "seconds", "windows/s", "loader share"],
                    [row(n, ("train_s", "windows_per_s", "loader_share")) for n in variants])]  # fmt: skip
    if lambdas:
        tables.insert(0, Table("λ_prior chosen on the validation split: MPJPE after refinement (mm; mean ± std over seeds)",
                               ["variant", *(f"λ = {lam:g}" for lam in lambdas)],
                               [row(n, [f"validation.{_lam_key(lam)}" for lam in lambdas]) for n in variants]))  # fmt: skip
    notes = ("--quick: tiny export and model; the figures check the script, they measure nothing."
             if args.quick else "")  # fmt: skip
    path = write_results(args.out.stem if args.out else "reaction_prior", figures,
                         params={**vars(args), "overrides": overrides, "vae_overrides": vae_overrides}, goals=goals,
                         tables=tables, notes=notes, out=args.out)  # fmt: skip
    print(path)


if __name__ == "__main__":
    main()

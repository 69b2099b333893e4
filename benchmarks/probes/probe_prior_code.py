"""Probe: how well the reaction prior's motion code can describe a reaction, by its kind, size and schedule.

    .venv/bin/python benchmarks/probes/probe_prior_code.py --export RP/export-r64 --work RP/codes --jobs 2

Refinement with the prior (``reaction_prior/refine.py``) optimises a window's code and gives back its
decoding, so no refined reaction is closer to the truth than the closest motion the code can decode
to. The reaction-prior benchmark found the "without motion VAE" ablation, a fixed low-frequency DCT of
each coordinate, refining better than the full model; this probe measures that floor for each code
without the generator: the motion VAE at several widths and training lengths (``--vae``), and the DCT
at several numbers of coefficients (``--dct``); a VAE item without ``@steps`` trains the model's default
schedule (``vae_steps``). Each VAE trains its ``vae`` phase only, on the ``fit``
split, seed 0 (``--set`` overrides the rest of the config, as the benchmark's ``--set`` does). Per code,
on the reactors of a split (``--split``, default ``validation``: people the codes never saw; ``fit``:
the training windows themselves):

- ``recon``: the clean reactor encoded and decoded (MPJPE, PA-MPJPE, translation error, mm);
- ``projection``: the reactor corrupted by the visibility-driven noise (the benchmark's draw), then
  refined with the prior term off (``lambda_prior = 0``), so the decoder alone pulls it back: what
  the code's shape of motion removes of the noise;
- ``code_size``: the numbers in a window's code.

Writes ``benchmarks/results/probe_prior_code.json`` (``--out`` elsewhere: the results take the file's name).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: results_file, bench_reaction_prior

from bench_reaction_prior import _refinement, _test_sequences  # noqa: E402
from dualhuman_builder.models.reaction_prior.spec import DEFAULTS  # noqa: E402
from results_file import Table, write_results  # noqa: E402

#: ``--vae`` items: ``<latent>x<layers>`` with the feed-forward width twice the latent (MLD's ratio is 4;
#: 2 is the CPU default's), optionally ``t<tokens>`` (``latent_tokens``, MLD's latent_size) and ``@<vae_steps>``.
DEFAULT_VAES = "64x2,64x2t4,64x2t8,128x2,64x2@6000"
DEFAULT_DCTS = "1,2,4,8,16"


def parse_vae(item: str) -> dict:
    """``"64x2t8@6000"`` -> the config overrides of that VAE (``latent_dim``, ``layers``, ``ff``, and
    ``latent_tokens`` and ``vae_steps`` where given)."""
    size, _, steps = item.partition("@")
    latent, _, rest = size.partition("x")
    layers, _, tokens = rest.partition("t")
    try:
        out = {"latent_dim": int(latent), "layers": int(layers), "ff": 2 * int(latent)}
        if tokens:
            out["latent_tokens"] = int(tokens)
        if steps:
            out["vae_steps"] = int(steps)
    except ValueError:
        raise SystemExit(f"--vae item {item!r} is not <latent>x<layers>[t<tokens>][@<steps>], e.g. 64x2t8@6000") from None
    return out


def _code_name(kind: str, item: str) -> str:
    return f"{kind}_{item.replace('@', '_')}"


def _train_and_score(job: tuple) -> dict:
    """Train one code (a VAE's ``vae`` phase; nothing for a DCT) and score it; a process of its own."""
    import torch

    from dualhuman_builder.models.reaction_prior.refine import refine_sequences
    from dualhuman_builder.models.training import load_run, train
    from dualhuman_builder.models import metrics

    name, overrides, c = job
    if c["threads"] > 0:
        torch.set_num_threads(c["threads"])
    run = Path(c["work"]) / name
    # the generator is not probed: one step of it, so the run completes
    train("reaction-prior", Path(c["export"]), run, config_overrides={**c["overrides"], **overrides, "inn_steps": 1},
          seed=0, progress=False, split="fit")  # fmt: skip
    summary = json.loads((run / "summary.json").read_text())
    module = load_run(run, device="cpu")[2]
    seqs = _test_sequences(Path(c["export"]), c["split"])
    window = int(module.config["window"])
    clean = refine_sequences(module, [(a, r) for _, a, r in seqs], window, 0.0, 0)  # encode, decode
    t = np.concatenate([r for _, _, r in seqs])
    rec = np.concatenate([x for x, _ in clean])
    proj = _refinement(module, seqs, module.config, window, c["iterations"], 0.0, "cpu")
    vae = summary.get("phases", {}).get("vae", {})
    out = {"code_size": int(module.code_dim),
           "recon": metrics.pose_errors(rec, t),
           "projection": {"before_mpjpe_mm": proj["before"]["mpjpe_mm"], "mpjpe_mm": proj["after"]["mpjpe_mm"],
                          "pa_mpjpe_mm": proj["after"]["pa_mpjpe_mm"], "translation_mm": proj["after"]["translation_mm"]},
           "vae_steps": vae.get("steps"), "vae_final_l1": (vae.get("final") or {}).get("l1"),
           "train_s": summary.get("time_s"), "windows_per_s": vae.get("windows_per_s"), "frames": len(t)}  # fmt: skip
    print(f"{name}: recon {out['recon']['mpjpe_mm']:.1f} mm, projection {proj['before']['mpjpe_mm']:.1f} -> "
          f"{out['projection']['mpjpe_mm']:.1f} mm", flush=True)  # fmt: skip
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--export", type=Path, required=True, help="a dataset export with a train split (fit/validation)")
    ap.add_argument("--work", type=Path, required=True, help="folder of the probe's runs (a finished run is kept)")
    ap.add_argument("--vae", default=DEFAULT_VAES,
                    help=f"VAEs: <latent>x<layers>[t<tokens>][@<vae_steps>], comma-separated (default {DEFAULT_VAES})")
    ap.add_argument("--dct", default=DEFAULT_DCTS, help=f"DCT codes: coefficients kept per coordinate (default {DEFAULT_DCTS})")
    ap.add_argument("--split", default="validation", choices=("validation", "fit"), help="the reactors scored")
    ap.add_argument("--iterations", type=int, default=100, help="refinement steps per window (the benchmark's)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=JSON", help="config override for every code")
    ap.add_argument("--jobs", type=int, default=1, help="codes at once, each in its own process on one thread")
    ap.add_argument("--out", type=Path, default=None, help="results file (default benchmarks/results/probe_prior_code.json)")
    args = ap.parse_args()

    overrides = {k: json.loads(v) for k, v in (s.split("=", 1) for s in args.set)}
    jobs = [(_code_name("vae", v), parse_vae(v)) for v in args.vae.split(",") if v]
    jobs += [(_code_name("dct", d), {"use_vae": False, "dct_coeffs": int(d)}) for d in args.dct.split(",") if d]
    given = [n for n, _ in jobs]  # the table's order
    # longest first, so the pool's processes end together
    jobs.sort(key=lambda j: -(j[1].get("latent_dim", 0) ** 2 * j[1].get("layers", 0) * j[1].get("vae_steps", DEFAULTS["vae_steps"])))
    c = {"export": str(args.export), "work": str(args.work), "overrides": overrides, "split": args.split,
         "iterations": args.iterations, "threads": 1 if args.jobs > 1 else 0}  # fmt: skip
    t0 = time.perf_counter()
    if args.jobs == 1:
        recs = {n: _train_and_score((n, o, c)) for n, o in jobs}
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            recs = dict(zip((n for n, _ in jobs), pool.map(_train_and_score, [(n, o, c) for n, o in jobs])))
    figures = {"codes": recs, "seconds": time.perf_counter() - t0}
    rows = [[n, f"codes.{n}.code_size", f"codes.{n}.vae_steps", f"codes.{n}.recon.mpjpe_mm", f"codes.{n}.recon.pa_mpjpe_mm",
             f"codes.{n}.recon.translation_mm", f"codes.{n}.projection.mpjpe_mm", f"codes.{n}.projection.pa_mpjpe_mm"]
            for n in given]  # fmt: skip
    name = (args.out.stem if args.out else "probe_prior_code")
    path = write_results(name, figures, params=vars(args), out=args.out, tables=[Table(
        f"What each code can describe, on the {args.split} split's reactors (mm)",
        ["code", "numbers", "VAE steps", "recon MPJPE", "recon PA-MPJPE", "recon translation",
         "projection MPJPE", "projection PA-MPJPE"], rows)])  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

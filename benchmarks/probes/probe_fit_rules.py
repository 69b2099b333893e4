"""Probe: what each of the window solver's rules costs in time and buys in accuracy, on one take.

    .venv/bin/python benchmarks/probes/probe_fit_rules.py --inputs HUG.npz --minutes 0.5
    .venv/bin/python benchmarks/probes/probe_fit_rules.py --inputs HUG.npz --runs 3 --rules contact_pass

The window solver carries rules grown to make it accurate enough on a CPU (docs/design/fit-collision.md):
the hands' pass, restarts of stuck frames, the energy refit, held settled frames, the contact pass.
Each fit here switches one of them off (a :class:`~dualhuman_builder.fit.config.FitConfig` field) and
fits the same frames as the product's fit (``default``) in the same run, in this process (torch on one
thread, the collision term's queries on its own; one short fit first, untimed), so the speed ratio to ``default`` is free of this
machine's drift between runs; runs go round the rules in turn (``--runs``, median). Each row has the
frame pairs per second, the ratio to ``default``, the joint error against the ground truth (mm, 22
joints of both actors, every frame), the deepest penetration left (mm) and the frames in collision
before the collision passes. Inputs: a take written by ``bench_fit.py --save-inputs`` (the generated
hug with six trackers per actor at their segment origins):

    .venv/bin/python benchmarks/bench_fit.py --minutes 1 --save-inputs HUG.npz --runs 0

Writes ``benchmarks/results/probe_fit_rules.json`` (``--out`` elsewhere).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: results_file, bench_fit

from bench_fit import first_frames, joint_error, load_inputs  # noqa: E402
from results_file import Table, write_results  # noqa: E402

#: rule -> (what switching it off means, the FitConfig fields that do it)
RULES = {
    "default": ("the product's fit, every rule on", {}),
    "contact_pass": ("no contact pass (surfaces a few mm apart stay apart)", {"contact_reach_m": 0.0}),
    "restart": ("no restart of stuck frames from their neighbours", {"collision_restart": False}),
    "energy_refit": ("no exact refit of a window bent out of shape", {"collision_energy_ratio": 0.0}),
    "hold_settled": ("every round moves the whole span, settled frames too", {"collision_hold_settled": False}),
    "hands_pass": ("relaxed hands: no hands' pass, no openings", {"hand_opening": False}),
}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n\n".join(__doc__.split("\n\n")[1:]))  # fmt: skip
    ap.add_argument("--inputs", required=True, help="a take written by bench_fit.py --save-inputs (.npz)")
    ap.add_argument("--minutes", type=float, default=0.5, help="fit the file's first MINUTES (default 0.5)")
    ap.add_argument("--runs", type=int, default=1, help="fits per rule, going round the rules in turn (median; default 1)")
    ap.add_argument("--rules", default=",".join(r for r in RULES if r != "default"),
                    help=f"comma-separated rules to switch off, each beside default (default: all of {', '.join(RULES)})")
    ap.add_argument("--out", type=Path, default=None, help="results file (default: benchmarks/results/probe_fit_rules.json)")
    args = ap.parse_args()
    rules = ["default"] + [r for r in args.rules.split(",") if r and r != "default"]
    if set(rules) - set(RULES):
        ap.error(f"--rules: unknown {sorted(set(rules) - set(RULES))}; choose from {', '.join(RULES)}")
    if args.runs < 1:
        ap.error("--runs: at least 1")

    import torch

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.fit.fitter import FitConfig, fit_actors

    inp, truth, fps = load_inputs(args.inputs)
    n = int(args.minutes * 60 * fps)
    inp = first_frames(inp, n)
    truth = [gt[:n] for gt in truth]
    T = len(inp[0].seg_rot)
    model = get_body_model()
    torch.set_num_threads(FitConfig().torch_threads)
    print(f"take: {T} frame pairs at {fps:g} fps from {args.inputs}; window solver, 1 process", flush=True)
    fit_actors(model, first_frames(inp, 60), fps, FitConfig(), workers=1)  # not timed: the first fit of a process builds caches
    rates: dict[str, list[float]] = {r: [] for r in rules}
    last: dict = {}
    for i in range(args.runs):
        for r in rules:
            res = fit_actors(model, inp, fps, FitConfig(**RULES[r][1]), workers=1)
            rates[r].append(res.summary["frame_pairs_per_s"])
            last[r] = res
            print(f"run {i} {r:13s} {rates[r][-1]:.2f} frame pairs/s", flush=True)
    base = statistics.median(rates["default"])
    figures = {"frame_pairs": T, "fps": fps}
    for r in rules:
        s, rate = last[r].summary, statistics.median(rates[r])
        figures[r] = {"switched_off": RULES[r][0], "fields": RULES[r][1], "pairs_per_s": rate, "runs_pairs_per_s": rates[r],
                      "x_default": rate / base, "mpjpe_mm": joint_error(last[r], truth),
                      "max_penetration_mm": s["max_penetration_after_mm"], "collision_frames": s["collision_frames"]}  # fmt: skip
        print(f"{r:13s} {rate:6.2f} frame pairs/s ({rate / base:.2f}x default), joint error {figures[r]['mpjpe_mm']:.2f} mm, "
              f"max penetration {s['max_penetration_after_mm']:.2f} mm", flush=True)  # fmt: skip
    cols = ["switched off", "frame pairs/s", "x default", "joint error (mm)", "max penetration (mm)"]
    rows = [[f"{r}: {RULES[r][0]}"] + [f"{r}.{k}" for k in ("pairs_per_s", "x_default", "mpjpe_mm", "max_penetration_mm")] for r in rules]
    path = write_results(args.out.stem if args.out else "probe_fit_rules", figures,
                         params={"inputs": Path(args.inputs).name, "minutes": args.minutes, "runs": args.runs, "rules": rules},
                         tables=[Table(f"The window solver's rules, each switched off, on {T} frame pairs of the hug (1 process)",
                                       cols, rows)],
                         out=args.out)  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

"""Probe: the run-to-run spread of the fit's accuracy columns on one take, over fresh recordings of it.

    .venv/bin/python benchmarks/probes/probe_fit_spread.py --keep TAKES                       # realistic high five, seed 11
    .venv/bin/python benchmarks/probes/probe_fit_spread.py --keep TAKES --type hug --preset ideal --recordings 3

Two recordings of one scene differ through the real transports' timing (``bench_fit_accuracy.py``
records in real time), and the fit's discrete decisions (a round undone, a frame restarted) turn a
fraction of a millimetre there into millimetres in its answer. So a change to the fit that moves an
accuracy table's row says little until it is set against this spread. Per recording (``--recordings``;
the first is the accuracy bench's own, ``TAKES/<type>-<seed>[-<preset>]/``, the others
``TAKES/r<i>/<type>-<seed>[-<preset>]/``, recorded in real time when missing) it fits the take once with each
``--solver`` and scores it as the accuracy bench does (trackers and the collision term on). Written per
solver: every recording's row, and the mean, standard deviation, minimum and maximum of each column;
the mean and the spread of each later solver's per-recording differences from the first's. The take
solver's two steps side by side, on the same recordings:

    .venv/bin/python benchmarks/probes/probe_fit_spread.py --keep TAKES --solver take:shared,take:runs,windows \
        --out benchmarks/results/probe_fit_spread_take_step.json

Writes ``benchmarks/results/probe_fit_spread.json`` (``--out`` elsewhere).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: results_file

from bench_fit_accuracy import recorded  # noqa: E402
from results_file import Table, write_results  # noqa: E402

#: column -> (label, the evaluate_take_fit key, scale)
COLUMNS = {"mpjpe_mm": ("MPJPE (mm)", "mpjpe_mm", 1.0), "pa_mpjpe_mm": ("PA-MPJPE (mm)", "pa_mpjpe_mm", 1.0),
           "root_mm": ("root (mm)", "root_mm", 1.0), "max_penetration_mm": ("max penetration (mm)", "max_penetration_mm", 1.0),
           "penetrating_share_pct": ("penetrating share (%)", "penetrating_share", 100.0),
           "foot_slide_mm": ("foot slide (mm)", "foot_slide_mm", 1.0), "contact_f1": ("contact F1", "contact_f1", 1.0)}  # fmt: skip


def recording(keep: Path, typ: str, seed: int, preset: str, fps: float, model, i: int):
    """Recording ``i`` of the take, ``(take path, scene)``: the accuracy bench's own in ``keep`` (``i`` 0)
    or another in ``keep/r<i>``, recorded first when missing (:func:`bench_fit_accuracy.recorded`)."""
    return recorded(typ, seed, fps, 1.0, keep if i == 0 else keep / f"r{i}", model, preset)


def spread(rows: list[dict]) -> dict:
    """Mean, standard deviation (ddof 1), minimum and maximum of each column over ``rows``."""
    a = {c: np.array([r[c] for r in rows], float) for c in COLUMNS}
    return {s: {c: float(f(v)) for c, v in a.items()}
            for s, f in (("mean", np.mean), ("std", lambda v: np.std(v, ddof=1) if len(v) > 1 else 0.0),
                         ("min", np.min), ("max", np.max))}  # fmt: skip


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n\n".join(__doc__.split("\n\n")[1:]))  # fmt: skip
    ap.add_argument("--keep", type=Path, required=True, help="folder of the kept recordings (the accuracy bench's --keep)")
    ap.add_argument("--type", default="high_five", help="scene type (default: high_five)")
    ap.add_argument("--seed", type=int, default=11, help="scene and device seed (default: 11)")
    ap.add_argument("--preset", default="realistic", choices=("ideal", "realistic"), help="device errors (default: realistic)")
    ap.add_argument("--recordings", type=int, default=5, help="recordings of the take (default: 5)")
    ap.add_argument("--solver", default="windows,take",
                    help="comma-separated solvers: windows, take, take:shared, take:runs (default: windows,take)")
    ap.add_argument("--fps", type=float, default=15.0, help="scene and fit frame rate (default: 15)")
    ap.add_argument("--out", type=Path, default=None, help="results file (default: benchmarks/results/probe_fit_spread.json)")
    args = ap.parse_args()
    solvers = [s for s in args.solver.split(",") if s]
    if args.recordings < 2:
        ap.error("--recordings: a spread needs at least 2")
    from dualhuman_builder.fit.config import solver_fields

    try:
        fields = {s: solver_fields(s) for s in solvers}
    except ValueError as e:
        ap.error(f"--solver: {e}")
    if not solvers:
        ap.error("--solver: name at least one")

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.evaluation.fit import evaluate_take_fit
    from dualhuman_builder.fit.fitter import FitConfig
    from dualhuman_builder.fit.process import process_take

    model = get_body_model()
    rows: dict[str, list[dict]] = {s: [] for s in solvers}
    for i in range(args.recordings):
        take, scene = recording(args.keep, args.type, args.seed, args.preset, args.fps, model, i)
        for s in solvers:
            tf = process_take(take, fps=args.fps, model=model, config=FitConfig(**fields[s]))
            ev = evaluate_take_fit(tf, scene, seed=args.seed, model=model, preset=args.preset)
            rows[s].append({c: float(ev[k]) * scale for c, (_, k, scale) in COLUMNS.items()})
            print(f"recording {i} {s:11s} " + "  ".join(f"{c} {v:.3g}" for c, v in rows[s][-1].items()), flush=True)
    figures: dict = {s: {"recordings": rows[s], **spread(rows[s])} for s in solvers}
    diffs = {}  # each later solver's rows minus the first's: "difference" with two, "difference <solver>" with more
    for other in solvers[1:]:
        diff = [{c: rb[c] - ra[c] for c in COLUMNS} for ra, rb in zip(rows[solvers[0]], rows[other])]
        diffs["difference" if len(solvers) == 2 else f"difference {other}"] = {"of": f"{other} - {solvers[0]}", "recordings": diff,
                                                                                **spread(diff)}  # fmt: skip
    figures.update(diffs)
    for s in figures:
        print(f"{s:11s} " + "  ".join(f"{c} {figures[s]['mean'][c]:.3g} ± {figures[s]['std'][c]:.2g}" for c in COLUMNS))
    groups = [*solvers, *diffs]
    cols = ["column"] + [f"{g} {stat}" for g in groups for stat in ("mean", "std")]
    table_rows = [[label] + [f"{g}.{stat}.{c}" for g in groups for stat in ("mean", "std")] for c, (label, _, _) in COLUMNS.items()]
    path = write_results(args.out.stem if args.out else "probe_fit_spread", figures,
                         params={"type": args.type, "seed": args.seed, "preset": args.preset, "recordings": args.recordings,
                                 "solvers": solvers, "fps": args.fps},
                         tables=[Table(f"Run-to-run spread over {args.recordings} recordings of one take "
                                       f"({args.type}, seed {args.seed}, {args.preset} devices)", cols, table_rows)],
                         out=args.out)  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

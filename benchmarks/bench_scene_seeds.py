"""Ground-truth scenes on many seeds: the share of seeds per scene type on which ``make_scene``
returns a scene that meets its quality contract (goal 100 %), how many draws of the variation each
took, and what broke in the draws it rejected and in any seed it gave up on.

- per type: seeds tried, passed (a scene returned, so its contract met), the pass rate, the share
  met on the seed's own draw, draws per seed (mean, largest), seconds per seed;
- every rejected draw with its contract failures, and every seed that raised ``SceneContractError``.

    .venv/bin/python benchmarks/bench_scene_seeds.py [--seeds 50] [--first-seed 0] [--fps 30] [--types hug,push]

Writes ``benchmarks/results/scene_seeds.json`` (``--out`` elsewhere). Each scene is a full
generation (8 to 120 s at 30 fps on a 2-core machine): the default run is several hours there.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from results_file import Goal, Table, write_results


def main() -> None:
    from dualhuman_builder.sim.scenes import MAX_DRAWS, SCENE_TYPES

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=50, help="seeds per scene type")
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--types", default=",".join(SCENE_TYPES))
    ap.add_argument("--max-draws", type=int, default=MAX_DRAWS, help="draws make_scene may take per seed")
    ap.add_argument("--out", type=Path, default=None, help="results file (default benchmarks/results/scene_seeds.json)")
    args = ap.parse_args()

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.sim.scenes import SceneContractError, SceneParams, contract_failures, make_scene

    model = get_body_model()
    types = args.types.split(",")
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    per_type = {}
    for kind in types:
        passed, first, draws, seconds, rejected, failed = 0, 0, [], [], [], []
        for seed in seeds:
            notes: list[str] = []
            t0 = time.perf_counter()
            try:
                sc = make_scene(SceneParams(type=kind, seed=seed, fps=args.fps), model=model, log=notes.append,
                                max_draws=args.max_draws)  # fmt: skip
            except SceneContractError as e:
                failed.append({"seed": seed, "error": e.message})
                status = "GAVE UP"
            else:
                assert contract_failures(sc.stats) == []
                passed += 1
                first += sc.stats["draws"] == 1
                draws.append(sc.stats["draws"])
                status = f"met on draw {sc.stats['draws']}"
            seconds.append(time.perf_counter() - t0)
            rejected += [{"seed": seed, "log": n} for n in notes if "breaks the quality contract" in n]
            print(f"{kind:12s} seed {seed:4d}: {status} ({seconds[-1]:.0f} s)", flush=True)
        per_type[kind] = {
            "seeds": len(seeds), "passed": passed, "pass_rate_pct": 100.0 * passed / len(seeds),
            "first_draw_pct": 100.0 * first / len(seeds),
            "draws_mean": sum(draws) / len(draws) if draws else None, "draws_max": max(draws, default=None),
            "seconds_mean": sum(seconds) / len(seconds), "rejected_draws": rejected, "failed_seeds": failed,
        }  # fmt: skip
    total = sum(v["passed"] for v in per_type.values())
    n = len(seeds) * len(types)
    figures = {"types": per_type, "overall": {"scenes": n, "passed": total, "pass_rate_pct": 100.0 * total / n}}
    print(f"overall: {total} of {n} seeds met the contract ({100.0 * total / n:.1f} %)")
    goals = [Goal("overall.pass_rate_pct", ">=", 100.0, "%",
                  f"seeds meeting the quality contract, all types, {args.fps:g} fps")]  # fmt: skip
    goals += [Goal(f"types.{k}.pass_rate_pct", ">=", 100.0, "%", f"{k}: seeds meeting the quality contract")
              for k in types]  # fmt: skip
    tables = [Table(f"scene quality contract over seeds {seeds[0]}-{seeds[-1]} at {args.fps:g} fps (at most "
                    f"{args.max_draws} draws each)",
                    ["scene type", "seeds", "met (%)", "met on the seed's own draw (%)", "draws, mean", "draws, most",
                     "seconds per seed"],
                    [[k, f"types.{k}.seeds", f"types.{k}.pass_rate_pct", f"types.{k}.first_draw_pct",
                      f"types.{k}.draws_mean", f"types.{k}.draws_max", f"types.{k}.seconds_mean"]
                     for k in types])]  # fmt: skip
    params = {"seeds": args.seeds, "first_seed": args.first_seed, "fps": args.fps, "types": types,
              "max_draws": args.max_draws}  # fmt: skip
    path = write_results("scene_seeds", figures, params=params, goals=goals, tables=tables, out=args.out)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

"""Fit speed: frame pairs per second, against anny's raw forward+backward at the same batch size,
and peak memory as the take grows.

Goal: 30 frame pairs/s (``GOAL_PAIRS_PER_S``) for the fit with the collision term (held contacts,
the product's fit) and without it, on the first ``--workers`` setting.

    .venv/bin/python benchmarks/bench_fit.py                      # 1-minute take, CPU
    .venv/bin/python benchmarks/bench_fit.py --minutes 10         # peak memory stays bounded?
    .venv/bin/python benchmarks/bench_fit.py --device cuda        # on a GPU
    .venv/bin/python benchmarks/bench_fit.py --minutes 10 --collision off --runs 1   # memory, quickly
    .venv/bin/python benchmarks/bench_fit.py --collision held     # the product's collision passes only

Inputs are the ground-truth segments of a generated hug (the scene type with the most contact),
looped to the requested length, with six trackers per actor at their segment origins: the fitter
does the same work as on a recorded take (sync and fuse excluded: the fit stage's own time).
Prints: fit frame pairs/s without the collision term, with it (contacts held through each pass,
the default: ``FitConfig.collision_hold_contacts``), and with it located at every evaluation
(``exact``, the baseline), median of --runs each, in this process; the held/exact ratio; anny
forward+backward bodies/s at batch 2 x window, the fit/anny ratios, and the process's peak RSS.
Under each fit, how unevenly it errs around the seams between its segments against elsewhere
(:func:`seam_jitter`: the RMS second difference of the joint error against the ground truth).
torch runs on ``--threads`` CPU threads (default ``FitConfig.torch_threads``, 1: fits that repeat
exactly) for the fits and anny's rate alike. The take's segments are fitted on ``--workers``
processes (this one included; ``auto``: the fit's default, one per CPU; a comma-separated list runs
each mode once per value and prints the ratios to the first). Peak RSS is this process's and the
largest worker process's (as it reports it).

    .venv/bin/python benchmarks/bench_fit.py --minutes 1 --collision held --workers 1,auto

``--solver windows,take`` fits each mode with the window solver (the default fit) and with the
whole take as one problem (``FitConfig.solver``, one process), side by side; ``take:shared`` and
``take:runs`` name the take solver's two steps (``FitConfig.take_step``). Each row has its joint
error against the ground truth (mm):

    .venv/bin/python benchmarks/bench_fit.py --inputs /tmp/hug1.npz --collision held \
        --solver windows,take:shared,take:runs --out benchmarks/results/fit_solvers.json

The take's inputs can be written once and read back (``--save-inputs FILE.npz``, ``--inputs
FILE.npz``), so that a machine without the scene generator's time to spare (a lent GPU) fits the
same frames:

    .venv/bin/python benchmarks/bench_fit.py --minutes 1 --save-inputs /tmp/hug1.npz --runs 0
    .venv/bin/python benchmarks/bench_fit.py --inputs /tmp/hug1.npz --device cuda --collision held

Writes ``benchmarks/results/fit.json`` (``fit_cuda.json`` with ``--device cuda``; ``--out``
elsewhere); a run with ``--runs 0`` measures nothing and writes no results.
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from results_file import Goal, Table, write_results  # noqa: E402

#: Frame pairs per second the fit must reach on this project's 2-CPU machine.
GOAL_PAIRS_PER_S = 30.0


#: the inputs' skeleton is anny's own (``ActorInput.skeleton_rms_m`` 0): the trackers sit at the segment
#: origins the suit's segments report, so the fit keeps their offsets as given instead of weighing them
#: with the capture protocol's sites (``fit/mounts.py``), which would put them centimetres from where they are
ANNY_SKELETON = 0.0


def inputs(model, minutes: float, fps: float, truth: list | None = None):
    """The benchmark take's ActorInputs (``T = minutes * 60 * fps`` frames); with a list ``truth``,
    each actor's ground-truth joints ``(T, 22, 3)`` (m) are appended to it."""
    from dualhuman_builder.body.mapping import MVN_SEGMENTS
    from dualhuman_builder.fit.fitter import ActorInput
    from dualhuman_builder.sim.groundtruth import segment_kinematics
    from dualhuman_builder.sim.scenes import SceneParams, make_scene

    sc = make_scene(SceneParams(type="hug", seed=0, fps=fps), model=model)
    T = int(minutes * 60 * fps)
    out = []
    tracked = [MVN_SEGMENTS.index(s) for s in ("Pelvis", "Head", "LeftHand", "RightHand", "LeftFoot", "RightFoot")]
    for track in sc.sequence.actors:
        sk = segment_kinematics(track)
        n = sk.num_frames
        idx = np.concatenate([np.arange(n), np.arange(n)[::-1]])  # ping-pong keeps the motion continuous
        idx = np.resize(idx, T)
        pos = np.asarray(sk.positions)[idx]
        if truth is not None:
            truth.append(track.joints()[idx])
        out.append(ActorInput(track.actor, {k: float(v) for k, v in zip(model.shape_names, track.shape)},
                              np.asarray(sk.orientations)[idx], pos[:, 0], np.ones(T, bool), pos[:, tracked],
                              np.ones((T, 6), bool), np.array(tracked), np.zeros((6, 3)),
                              pos[:, [MVN_SEGMENTS.index("LeftFoot"), MVN_SEGMENTS.index("RightFoot")]],
                              skeleton_rms_m=ANNY_SKELETON))  # fmt: skip
    return out


#: ActorInput's array fields; the (T, ...) ones are all but the trackers' segments and offsets
_ARRAYS = ("seg_rot", "pelvis", "valid", "trk_pos", "trk_valid", "trk_segment", "trk_offset", "ankles")
_PER_FRAME = tuple(f for f in _ARRAYS if f not in ("trk_segment", "trk_offset"))


def first_frames(inp: list, n: int) -> list:
    """The ActorInputs ``inp`` cut to their first ``n`` frames."""
    return [dataclasses.replace(a, **{f: getattr(a, f)[:n] for f in _PER_FRAME}) for a in inp]


def save_inputs(path: str, inp: list, truth: list, fps: float) -> None:
    """Write the benchmark take (``inputs``' ActorInputs and ground-truth joints) to ``path`` (.npz)."""
    arrays = {"fps": np.float64(fps), "actors": np.int64(len(inp))}
    for k, (a, gt) in enumerate(zip(inp, truth)):
        arrays[f"{k}_name"] = np.array(a.name)
        arrays[f"{k}_shape_names"] = np.array(list(a.shape))
        arrays[f"{k}_shape_values"] = np.array(list(a.shape.values()), np.float64)
        arrays[f"{k}_truth"] = gt
        for f in _ARRAYS:
            arrays[f"{k}_{f}"] = getattr(a, f)
    np.savez_compressed(path, **arrays)


def load_inputs(path: str) -> tuple[list, list, float]:
    """``(inputs, truth, fps)`` as :func:`save_inputs` wrote them."""
    from dualhuman_builder.fit.fitter import ActorInput

    with np.load(path) as z:
        inp, truth = [], []
        for k in range(int(z["actors"])):
            shape = {str(n): float(v) for n, v in zip(z[f"{k}_shape_names"], z[f"{k}_shape_values"])}
            inp.append(ActorInput(str(z[f"{k}_name"]), shape, **{f: z[f"{k}_{f}"] for f in _ARRAYS}, skeleton_rms_m=ANNY_SKELETON))
            truth.append(z[f"{k}_truth"])
        return inp, truth, float(z["fps"])


def seam_jitter(res, truth: list, cfg) -> tuple[float, float, int]:
    """``(at seams, elsewhere, seams)``: the RMS (mm/frame^2) of the second difference over frames of
    the joint error (fit minus ground truth, 22 joints of both actors), in the frames around the
    seams between segments (the 2 x overlap frames they share and overlap more on each side) and in
    the others. The ground truth's own motion cancels; what is left is how unevenly the fit errs,
    and a seam's cross-fade shows as a larger figure there."""
    from dualhuman_builder.fit.fitter import layout

    T, O = len(truth[0]), int(cfg.overlap)
    segments = layout(T, cfg) if cfg.solver == "windows" else [[]]  # the take solver has no seams
    near = np.zeros(T, bool)
    for seg in segments[1:]:
        s = seg[0][1]  # the later segment starts 2 x overlap frames before the earlier one ends
        near[max(s - O, 0) : min(s + 3 * O, T)] = True
    err = np.concatenate([tr.joints() - gt for tr, gt in zip(res.sequence.actors, truth)], axis=1)
    acc = np.linalg.norm(err[2:] - 2 * err[1:-1] + err[:-2], axis=-1) * 1000  # (T - 2, joints)
    at = near[1:-1]

    def rms(x):
        return float(np.sqrt(np.mean(x**2))) if x.size else float("nan")

    return rms(acc[at]), rms(acc[~at]), len(segments) - 1


def joint_error(res, truth: list) -> float:
    """Mean distance (mm) of the fitted joints (22, both actors, every frame) to the ground truth."""
    return float(np.mean([np.linalg.norm(tr.joints() - gt, axis=-1).mean() for tr, gt in zip(res.sequence.actors, truth)]) * 1000)


def anny_rate(model, batch: int, runs: int) -> float:
    dev = model.device
    pose = torch.zeros(batch, model.num_bones, 3, requires_grad=True, device=dev)
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)
    times = []
    for _ in range(runs):
        sync()
        t = time.perf_counter()
        model.forward(pose, None, torch.zeros(batch, 3, device=dev)).vertices.sum().backward()
        sync()
        times.append(time.perf_counter() - t)
    return batch / statistics.median(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=None,
                    help="take length (default 1; with --inputs: the file's first MINUTES, default all of it)")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--runs", type=int, default=3, help="fits per mode (median); 0: none (with --save-inputs)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--collision", choices=("all", "held", "exact", "off"), default="all",
                    help="fit without the collision term (off), with it and the contacts held through each pass "
                         "(held, the default fit), with them located at every evaluation (exact), or all three (default)")
    ap.add_argument("--threads", type=int, default=None,
                    help="torch CPU threads for the fit and for anny's raw rate (default: FitConfig.torch_threads, 1)")
    ap.add_argument("--workers", default="auto",
                    help="processes to fit the take's segments on, this one included: a number or auto (the fit's "
                         "default), or a comma-separated list to compare (default: auto)")
    ap.add_argument("--solver", default="windows",
                    help="the fit's solver: windows (the default fit), take (the whole take as one problem, one "
                         "process; take:shared or take:runs for its step, FitConfig.take_step), or a comma-separated "
                         "list to compare them in the same run (ratios to the first)")
    ap.add_argument("--save-inputs", metavar="FILE", help="write the take's inputs and ground truth to FILE (.npz)")
    ap.add_argument("--inputs", metavar="FILE", help="read the take from FILE (--save-inputs) instead of generating it; "
                    "--fps is then the file's")
    ap.add_argument("--out", type=Path, default=None,
                    help="results file (default benchmarks/results/fit.json, or fit_cuda.json on cuda)")
    args = ap.parse_args()
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.fit.config import solver_fields
    from dualhuman_builder.fit.fitter import FitConfig, fit_actors

    workers = [None if w.strip() == "auto" else int(w) for w in args.workers.split(",")]
    solvers = [x.strip() for x in args.solver.split(",")]
    try:
        fields = {sv: solver_fields(sv) for sv in solvers}
    except ValueError as e:
        ap.error(f"--solver: {e}")
    # (solver, workers, key): the take solver runs in one process whatever --workers says
    settings = [(sv, w, str(w or "auto") if sv == "windows" else sv) for sv in solvers for w in (workers if sv == "windows" else [1])]

    model = get_body_model(args.device)
    truth: list = []
    if args.inputs:
        inp, truth, args.fps = load_inputs(args.inputs)
        if args.minutes is not None:  # the file's first frames
            n = int(args.minutes * 60 * args.fps)
            inp = first_frames(inp, n)
            truth = [gt[:n] for gt in truth]
        args.minutes = len(inp[0].seg_rot) / args.fps / 60
    else:
        args.minutes = 1.0 if args.minutes is None else args.minutes
        inp = inputs(get_body_model(), args.minutes, args.fps, truth)
    if args.save_inputs:
        save_inputs(args.save_inputs, inp, truth, args.fps)
        print(f"inputs written to {args.save_inputs}")
    if args.runs <= 0:
        return
    T = len(inp[0].seg_rot)
    threads = FitConfig().torch_threads if args.threads is None else args.threads
    if threads > 0:
        torch.set_num_threads(threads)  # anny's raw rate below at the fit's setting
    print(f"take: {args.minutes:g} min at {args.fps:g} fps = {T} frame pairs; device {args.device}; torch threads {torch.get_num_threads()}")
    medians = {}
    fits = []
    worker_mb = 0
    modes = {"all": ("off", "held", "exact")}.get(args.collision, (args.collision,))
    names = {"off": "without collision term", "held": "with collision term, contacts held",
             "exact": "with collision term, contacts located at every evaluation"}
    base = settings[0][2]
    for mode in modes:
        for solver, w, key in settings:
            cfg = FitConfig(collision=mode != "off", collision_hold_contacts=mode == "held", device=args.device, torch_threads=threads,
                            **fields[solver])  # fmt: skip
            rates = []
            for _ in range(args.runs):
                res = fit_actors(model, inp, args.fps, cfg, workers=w)
                rates.append(res.summary["frame_pairs_per_s"])
            medians[mode, key] = statistics.median(rates)
            s = res.summary
            n = s["processes"]
            worker_mb = max(worker_mb, s.get("worker_peak_rss_mb") or 0)
            extra = (f", frames in collision {s['collision_frames']}, max penetration {s['max_penetration_after_mm']:.2f} mm, "
                     f"frames located exactly after a stall {len(s['collision_exact_frames'])}, windows fitted again exactly {len(s['collision_exact_windows'])}, "
                     f"seams fitted again {len(s['seams_fitted_again'])} of {s['segments'] - 1}") if mode != "off" else ""  # fmt: skip
            ratio = f", {medians[mode, key] / medians[mode, base]:.2f}x the first" if key != base else ""
            mpjpe = joint_error(res, truth)
            print(f"fit {names[mode]}, {solver} solver, {n} process{'es' if n > 1 else ''}: {medians[mode, key]:.1f} frame pairs/s "
                  f"(median of {args.runs}{extra}); joint error {mpjpe:.2f} mm{ratio}", flush=True)  # fmt: skip
            at, elsewhere, seams = seam_jitter(res, truth, cfg)
            fit = {"mode": mode, "solver": solver, "workers": w or "auto", "processes": n, "pairs_per_s": medians[mode, key],
                   "runs_pairs_per_s": rates, "x_first": medians[mode, key] / medians[mode, base], "mpjpe_mm": mpjpe,
                   "seam_jitter": {"at_seams": at, "elsewhere": elsewhere, "seams": seams},
                   "worker_peak_rss_mb": s.get("worker_peak_rss_mb")}  # fmt: skip
            if mode != "off":
                fit.update({"collision_frames": s["collision_frames"], "max_penetration_mm": s["max_penetration_after_mm"],
                            "exact_frames": len(s["collision_exact_frames"]),
                            "exact_windows": len(s["collision_exact_windows"]),
                            "seams_fitted_again": len(s["seams_fitted_again"]), "segments": s["segments"]})  # fmt: skip
            fits.append(fit)
            if seams:
                print(f"  joint error's frame-to-frame acceleration (RMS): {at:.2f} mm/frame^2 around the {seams} seams, "
                      f"{elsewhere:.2f} elsewhere", flush=True)  # fmt: skip
    for _, _, key in settings:
        if ("held", key) in medians and ("exact", key) in medians:
            print(f"held / exact ({key}): {medians['held', key] / medians['exact', key]:.2f}x")
    cfg = FitConfig()
    rate = anny_rate(model, 2 * cfg.window, args.runs + 2)
    print(f"anny forward+backward at batch {2 * cfg.window}: {rate:.0f} bodies/s = {rate / 2:.0f} frame pairs/s")
    print("ratio fit / anny raw: " + ", ".join(f"{v / (rate / 2):.3f} {m} ({key})" for (m, key), v in medians.items()))
    print(f"peak RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB this process"
          + (f", {worker_mb} MB the largest worker process (VmHWM)" if worker_mb else "")
          + (f"; peak GPU memory {torch.cuda.max_memory_allocated() / 2**20:.0f} MB (max_memory_allocated)"
             if model.device.type == "cuda" else ""))

    first = {m: medians[m, base] for m in modes}
    figures: dict = {
        "take": {"minutes": args.minutes, "fps": args.fps, "frame_pairs": T, "inputs": args.inputs or "generated hug, seed 0",
                 "device": args.device, "torch_threads": torch.get_num_threads()},
        "pairs_per_s": first,
        "fits": fits,
        "held_over_exact": {key: medians["held", key] / medians["exact", key] for _, _, key in settings
                            if ("held", key) in medians and ("exact", key) in medians},
        "anny": {"batch": 2 * cfg.window, "bodies_per_s": rate, "pairs_per_s": rate / 2},
        "fit_over_anny": {m: v / (rate / 2) for m, v in first.items()},
        "peak_rss_mb": {"this_process": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                        "largest_worker": worker_mb or None},
        "peak_gpu_mb": torch.cuda.max_memory_allocated() / 2**20 if model.device.type == "cuda" else None,
    }  # fmt: skip
    rows = [[f"{names[f['mode']]}, {f['solver']} solver" + (f", --workers {f['workers']}" if f["solver"] == "windows" else "")
             + f" ({f['processes']} process{'es' if f['processes'] > 1 else ''})",
             f"fits.{k}.pairs_per_s",
             f"fits.{k}.x_first", f"fits.{k}.mpjpe_mm", f"fits.{k}.max_penetration_mm" if f["mode"] != "off" else "",
             f"fits.{k}.seam_jitter.at_seams", f"fits.{k}.seam_jitter.elsewhere"] for k, f in enumerate(fits)]
    rows.append([f"anny forward+backward at batch {2 * cfg.window} (frame pairs/s)", "anny.pairs_per_s", "", "", "", "", ""])
    tables = [Table(f"{args.minutes:g}-minute hug, {T} frame pairs at {args.fps:g} fps, on {args.device} (median of "
                    f"{args.runs})", ["fit", "frame pairs/s", "x first setting", "joint error mm", "max penetration mm",
                                      "seam jitter at seams mm/frame²", "elsewhere"], rows),
              Table("ratios in the same run", ["ratio", "value"],
                    [[f"fit {m} / anny forward+backward", f"fit_over_anny.{m}"] for m in first]
                    + [[f"held / exact ({w} workers)", f"held_over_exact.{w}"] for w in figures["held_over_exact"]]
                    + [["peak RSS MB, this process", "peak_rss_mb.this_process"],
                       ["peak RSS MB, largest worker process", "peak_rss_mb.largest_worker"]])]  # fmt: skip
    goals = [Goal(f"pairs_per_s.{m}", ">=", GOAL_PAIRS_PER_S, "frame pairs/s", label=f"fit {names[m]}")
             for m in ("held", "off") if m in first]  # fmt: skip
    name = args.out.stem if args.out else ("fit_cuda" if model.device.type == "cuda" else "fit")
    path = write_results(name, figures, params={k: v for k, v in vars(args).items() if k != "out"}, goals=goals,
                         tables=tables, out=args.out,
                         notes="Sync and fuse excluded: the fit stage's own time. Seam jitter: the RMS "
                               "second difference over frames of the joint error against the ground truth, around "
                               "the seams between segments and elsewhere.")  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

"""Long takes through the whole path: does the fit's error grow over a 10-minute take?

A ``session`` scene (:mod:`dualhuman_builder.sim.session`: the six interactions chained with walks
and stands between them, 30 fps) goes through simulated devices -> take file -> sync -> fuse ->
fit, and the fit is scored against the scene per minute. Per take: MPJPE and root error over
the whole take, over its first and its last window (a minute; a third of the take when it is
shorter than three minutes), their ratio (goal: the last window's error at most 1.2x the
first's on the 10-minute take: no drift growth), the fit stage's time, and the peak resident
memory of the sync -> fuse -> fit call (this process and its fit workers, sampled every 0.2 s).

    .venv/bin/python benchmarks/bench_long_takes.py                    # 1 min in real time, 10 min in-process
    .venv/bin/python benchmarks/bench_long_takes.py --takes 60         # the 1-minute take only
    .venv/bin/python benchmarks/bench_long_takes.py --keep takes/      # keep the recordings, score them again later
    .venv/bin/python benchmarks/bench_long_takes.py --keep takes/ --reuse-scores   # gather kept scores only

Transports: a take up to ``--realtime-max`` seconds (default 60) is recorded in real time on the
loopback transports (:func:`~dualhuman_builder.evaluation.fit.record_simulated_take`, speed 1:
the same path as ``dualhuman capture --source sim://session?...``). A longer one is written
without sockets, faster than real time: the same simulated devices' wire datagrams (MVN UDP for
the two suits, the tracker bridge's datagrams for the twelve trackers, at the simulated host
receive times), fed to the same decoders and the same take writer the recorder uses; everything
after the transport (take file, sync, fuse, fit) is the same code. The two prop IMUs (Xbus, CAN),
which the fit does not use, are left out of that path. Scenes are cached in
``benchmarks/cache/long_takes/``. Writes ``benchmarks/results/long_takes.json``
(``long_takes_realistic.json`` with ``--preset realistic``; ``--out`` elsewhere).
"""

from __future__ import annotations

import argparse
import heapq
import json
import os
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from results_file import ROOT, Goal, Table, write_results  # noqa: E402

CACHE = ROOT / "benchmarks" / "cache" / "long_takes"
#: Last window's error over the first's, on the longest take.
GOAL_RATIO = 1.2
SOURCES = [("suits", "mvn+udp://127.0.0.1:9763", "mvn"), ("trackers", "vive+udp://127.0.0.1:8051", "vive")]


# ------------------------------------------------------------------ memory
def _rss_tree_mb(pid: int) -> float:
    """Resident memory (MB) of ``pid`` and its descendants, from /proc (0 where unreadable)."""
    total, todo, seen = 0.0, [pid], set()
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen.add(p)
        try:
            with open(f"/proc/{p}/status") as f:
                for line in f:
                    if line.startswith("VmRSS:"):
                        total += int(line.split()[1]) / 1024
            for task in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{task}/children") as f:
                    todo += [int(x) for x in f.read().split()]
        except (OSError, ValueError):
            continue
    return total


class PeakMemory:
    """Samples :func:`_rss_tree_mb` of this process every ``every_s`` seconds while in the ``with`` block."""

    def __init__(self, every_s: float = 0.2):
        self.every_s, self.peak_mb, self.start_mb = every_s, 0.0, 0.0
        self._stop = threading.Event()

    def __enter__(self):
        self.start_mb = self.peak_mb = _rss_tree_mb(os.getpid())
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def _run(self):
        while not self._stop.wait(self.every_s):
            self.peak_mb = max(self.peak_mb, _rss_tree_mb(os.getpid()))

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak_mb = max(self.peak_mb, _rss_tree_mb(os.getpid()))


# ------------------------------------------------------------------ scenes and takes
def session_scene(seed: int, duration: float, fps: float, model, log=print):
    """``(scene, scene_path, generation_s)``: the cached session scene, or a new one (then cached)."""
    from dualhuman_builder.sim.generate import generate_scene
    from dualhuman_builder.sim.scenes import Scene, SceneParams

    path = CACHE / f"session-{seed}-{duration:g}s-{fps:g}fps.scene.npz"
    if path.is_file():
        scene = Scene.load(path)
        return scene, path, scene.stats.get("generation_s")
    t0 = time.perf_counter()
    scene = generate_scene(SceneParams(type="session", seed=seed, duration=duration, fps=fps), model=model,
                       log=lambda m: log(f"  [{time.perf_counter() - t0:6.0f} s] {m}"))  # fmt: skip
    CACHE.mkdir(parents=True, exist_ok=True)
    scene.save(path)
    return scene, path, time.perf_counter() - t0


def write_take_in_process(scene, devices_seed: int, path: Path, log=print, preset: str = "ideal") -> dict:
    """Write the take of ``scene``'s simulated suits and trackers (device errors seeded
    ``devices_seed``, device error ``preset``) without sockets: each sample's wire datagrams, at
    its simulated host receive time, through the decoders and the take writer the recorder uses,
    one sample at a time (memory bounded by the studio's streams). Returns counts and seconds."""
    from dualhuman_builder.capture.log.writer import TakeWriter
    from dualhuman_builder.capture.recorder import rig_bindings
    from dualhuman_builder.capture.sources import RawPacket, make_decoder
    from dualhuman_builder.resources import RIGS_DIR
    from dualhuman_builder.rig import RigActor, load_rig
    from dualhuman_builder.sim.devices import mvn_packets, tracker_packets
    from dualhuman_builder.sim.studio import simulate_studio

    t0 = time.perf_counter()
    extra = {} if preset == "ideal" else {"preset": preset, "contacts": scene.distances}
    studio = simulate_studio(scene.sequence, seed=devices_seed, **extra)
    t_sim = time.perf_counter() - t0
    actors = [RigActor(a.name, "suits", a.character, dict(a.trackers)) for a in load_rig(RIGS_DIR / "sim.toml").actors]
    w = TakeWriter(path, take=path.stem, sources=SOURCES, bindings=rig_bindings(actors))
    decoders = [make_decoder(url) for _, url, _ in SOURCES]
    streams = [((f.host_time_ns, 0, f) for f in suit) for suit in studio.suits]
    streams += [((s.host_time_ns, 1, s) for s in tr) for tr in studio.trackers]
    n = [0, 0]
    for _, i, sample in heapq.merge(*streams, key=lambda x: (x[0], x[1])):
        if i == 0:
            packets = mvn_packets([sample], clock="host", stream="suits")
        else:
            packets = tracker_packets([sample], clock="host")
        for p in packets:
            raw = RawPacket(p.time_ns, p.data)
            w.add_raw(i, raw)
            for s in decoders[i].feed(raw):
                w.add_sample(i, s)
        n[i] += 1
    for i, dec in enumerate(decoders):
        for s in dec.finish():
            w.add_sample(i, s)
    w.close()
    log(f"  wrote {path.name}: {n[0]} suit frames, {n[1]} tracker samples, {path.stat().st_size / 1e6:.0f} MB "
        f"in {time.perf_counter() - t0:.0f} s (studio simulated in {t_sim:.0f} s)")  # fmt: skip
    return {"suit_frames": n[0], "tracker_samples": n[1], "mb": path.stat().st_size / 1e6,
            "seconds": time.perf_counter() - t0, "studio_s": t_sim}  # fmt: skip


# ------------------------------------------------------------------ scores
def per_frame_errors(tf, scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(times_s, joint_error, root_error)``: per fitted frame, the mean 22-joint position error
    and the pelvis-centre error (m) over both actors, against the scene (joints by forward
    kinematics only: no vertices, so a 10-minute take costs no mesh memory)."""
    from dualhuman_builder.evaluation.contacts import gt_frames

    gt = scene.sequence
    fit = tf.fit.sequence
    actors = fit.actors if hasattr(fit, "actors") else fit
    times = np.asarray(tf.sync.times_s, np.float64)
    idx = gt_frames(times, gt.fps, gt.num_frames)
    joint, root = [], []
    for k, track in enumerate(actors):
        g = gt.actors[k]
        joint.append(np.linalg.norm(track.joints() - g.joints()[idx], axis=-1).mean(1))
        root.append(np.linalg.norm(np.asarray(track.transl) - np.asarray(g.transl)[idx], axis=-1))
    return times, np.mean(joint, axis=0), np.mean(root, axis=0)


def scores(times: np.ndarray, joint: np.ndarray, root: np.ndarray, window_s: float) -> dict:
    """MPJPE and root error (mm) over the take, its first and last ``window_s``, and per minute."""
    end = times[-1]
    first, last = times < times[0] + window_s, times > end - window_s

    def mm(x, m):
        return float(1000 * x[m].mean())

    minutes = []
    for a in np.arange(times[0], end, 60.0):
        m = (times >= a) & (times < a + 60.0)
        if m.sum() > 10:
            minutes.append({"start_s": float(a), "mpjpe_mm": mm(joint, m), "root_mm": mm(root, m)})
    out = {"window_s": window_s, "mpjpe_mm": float(1000 * joint.mean()), "root_mm": float(1000 * root.mean()),
           "first": {"mpjpe_mm": mm(joint, first), "root_mm": mm(root, first)},
           "last": {"mpjpe_mm": mm(joint, last), "root_mm": mm(root, last)}, "per_minute": minutes}  # fmt: skip
    out["mpjpe_last_over_first"] = out["last"]["mpjpe_mm"] / out["first"]["mpjpe_mm"]
    out["root_last_over_first"] = out["last"]["root_mm"] / out["first"]["root_mm"]
    return out


def one_take(duration: float, args, model, folder: Path) -> dict:
    from dualhuman_builder.evaluation.fit import record_simulated_take
    from dualhuman_builder.fit.process import process_take
    from dualhuman_builder.sim.scenes import Scene, contract_failures
    from dualhuman_builder.sim.session import interactions

    label = f"{duration:g}s"
    tail = "" if args.preset == "ideal" else f"-{args.preset}"
    take_dir = folder / f"session-{args.seed}-{label}{tail}"
    take = take_dir / f"session-{args.seed}{tail}.mcap"
    kept = take_dir / f"scores-fit{args.fit_fps:g}fps.json"
    if args.reuse_scores and kept.is_file():
        print(f"{label}: scores kept in {kept}", flush=True)
        return json.loads(kept.read_text())
    row: dict = {"duration_s": duration}
    t0 = time.perf_counter()
    if duration <= args.realtime_max:
        row["transport"] = "loopback, real time (speed 1)"
        scene_file = take_dir / f"session-{args.seed}.scene.npz"
        if take.is_file() and scene_file.is_file():
            scene, row["recorded"] = Scene.load(scene_file), "kept"
        else:
            extra = {} if args.preset == "ideal" else {"preset": args.preset}
            take, scene = record_simulated_take("session", args.seed, take_dir, fps=args.fps, speed=1.0,
                                                duration=duration, model=model, **extra)  # fmt: skip
            row["record_s"] = time.perf_counter() - t0  # scene generation included
        row["generation_s"] = scene.stats.get("generation_s")
    else:
        row["transport"] = "in-process (no sockets): wire datagrams -> decoders -> take writer"
        scene, _, row["generation_s"] = session_scene(args.seed, duration, args.fps, model)
        if take.is_file():
            row["recorded"] = "kept"
        else:
            take_dir.mkdir(parents=True, exist_ok=True)
            row["write"] = write_take_in_process(scene, args.seed, take, preset=args.preset)
    meetings = interactions(scene)
    row["scene"] = {"frames": scene.sequence.num_frames, "fps": scene.sequence.fps, "meetings": len(meetings),
                    "types": {t: sum(m["type"] == t for m in meetings) for t in sorted({m["type"] for m in meetings})},
                    "contract_failures": contract_failures(scene.stats),
                    "distances_mb": sum(d.nbytes for d in scene.distances) / 1e6}  # fmt: skip
    print(f"{label}: {len(meetings)} meetings, scene generated in {row['generation_s'] or float('nan'):.0f} s; fitting "
          f"at {args.fit_fps:g} fps", flush=True)  # fmt: skip
    t1 = time.perf_counter()
    with PeakMemory() as mem:
        tf = process_take(take, fps=args.fit_fps, model=model,
                          progress=(lambda m: print(f"  {m}", flush=True)) if args.verbose else None)  # fmt: skip
    row["path_s"] = time.perf_counter() - t1
    row["fit_s"] = float(tf.fit.summary["fit_seconds"])
    row["peak_rss_mb"], row["rss_before_mb"] = mem.peak_mb, mem.start_mb
    times, joint, root = per_frame_errors(tf, scene)
    row["frames_fit"] = int(len(times))
    row["fit_pairs_per_s"] = len(times) / row["fit_s"]
    row.update(scores(times, joint, root, min(60.0, duration / 3)))
    print(f"{label}: MPJPE {row['mpjpe_mm']:.1f} mm (first {row['first']['mpjpe_mm']:.1f}, last "
          f"{row['last']['mpjpe_mm']:.1f}: x{row['mpjpe_last_over_first']:.2f}), root {row['root_mm']:.1f} mm (first "
          f"{row['first']['root_mm']:.1f}, last {row['last']['root_mm']:.1f}: x{row['root_last_over_first']:.2f}); "
          f"fit {row['fit_s']:.0f} s, sync+fuse+fit {row['path_s']:.0f} s, peak {row['peak_rss_mb']:.0f} MB",
          flush=True)  # fmt: skip
    kept.write_text(json.dumps(row, default=float))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--takes", nargs="+", type=float, default=[60.0, 600.0], help="take lengths (s)")
    ap.add_argument("--seed", type=int, default=3, help="scene and device seed (never tuned on)")
    ap.add_argument("--fps", type=float, default=30.0, help="scene frame rate")
    ap.add_argument("--preset", default="ideal", help="device error preset (ideal, realistic)")
    ap.add_argument("--fit-fps", type=float, default=15.0, help="sync and fit frame rate (divides the scene's)")
    ap.add_argument("--realtime-max", type=float, default=60.0,
                    help="takes up to this long (s) are recorded in real time on loopback; longer ones in-process")
    ap.add_argument("--keep", type=Path, default=None, help="keep the takes in this folder and score kept ones again")
    ap.add_argument("--reuse-scores", action="store_true",
                    help="with --keep: take the scores a run kept beside each take instead of fitting it again")
    ap.add_argument("--out", type=Path, default=None, help="results file (default benchmarks/results/long_takes.json)")
    ap.add_argument("--verbose", action="store_true", help="print the pipeline's progress")
    args = ap.parse_args()

    import tempfile

    from dualhuman_builder.body.model import get_body_model

    model = get_body_model()
    takes = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) if args.keep is None else args.keep
        for d in args.takes:
            takes[f"{d:g}s"] = one_take(d, args, model, folder)
    longest = f"{max(args.takes):g}s"
    goals = [Goal(f"takes.{longest}.mpjpe_last_over_first", "<=", GOAL_RATIO, "x",
                  label=f"MPJPE over the last minute / the first, {longest} take"),
             Goal(f"takes.{longest}.root_last_over_first", "<=", GOAL_RATIO, "x",
                  label=f"root error over the last minute / the first, {longest} take")]  # fmt: skip
    figures = (("MPJPE, whole take", "mm", "mpjpe_mm"), ("MPJPE, first window", "mm", "first.mpjpe_mm"),
               ("MPJPE, last window", "mm", "last.mpjpe_mm"), ("MPJPE last / first", "", "mpjpe_last_over_first"),
               ("root error, whole take", "mm", "root_mm"), ("root error, first window", "mm", "first.root_mm"),
               ("root error, last window", "mm", "last.root_mm"), ("root last / first", "", "root_last_over_first"),
               ("fit stage", "s", "fit_s"), ("sync + fuse + fit", "s", "path_s"),
               ("peak memory, sync + fuse + fit", "MB", "peak_rss_mb"), ("scene generation", "s", "generation_s"))
    rows = [[f"{lab} ({unit})" if unit else lab, *[f"takes.{k}.{path}" for k in takes]] for lab, unit, path in figures]
    table = Table(f"Session takes ({args.preset} devices, seed {args.seed}, scene {args.fps:g} fps, "
                  f"fit {args.fit_fps:g} fps)", ["figure", *takes], rows)  # fmt: skip
    params = {"takes": args.takes, "seed": args.seed, "preset": args.preset, "fps": args.fps, "fit_fps": args.fit_fps,
              "realtime_max": args.realtime_max, "keep": str(args.keep) if args.keep else None}  # fmt: skip
    name = "long_takes" if args.preset == "ideal" else f"long_takes_{args.preset}"
    path = write_results(name, {"takes": takes}, params=params, goals=goals, tables=[table], out=args.out,
                         notes="Window: the first and the last minute (a third of the take when shorter than three "
                               "minutes). Peak memory: resident set of the process and its fit workers during "
                               "sync -> fuse -> fit, sampled every 0.2 s.")  # fmt: skip
    print(f"\nwritten {path}")


if __name__ == "__main__":
    main()

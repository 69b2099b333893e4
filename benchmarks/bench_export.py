"""Export stage and training loaders: sequences/min of ``export_dataset``, windows/s of the loaders
against a bare ``numpy.load`` loop in the same run.

Data: ground-truth scenes (``--types``, seed 0, ``--fps``, ``--scene-seconds`` long; cached in
``--scene-cache``, default ``benchmarks/cache/``), their contacts from :func:`~dualhuman_builder.evaluation.contacts.contacts_for_scene`
(once per scene), cut into clips of ``--seconds`` at evenly spread start frames (clip ``k`` from
scene ``k mod types``); each clip's contacts are the scene's, sliced (events clipped to the clip).
Every timed run gets freshly built tracks, so the export pays the body model for the joints as
it would on a freshly loaded sequence (tracks cache them).

1. **Export** of ``--sequences`` clips into a fresh folder per run (median of ``--repeats``):
   (a) without renders; (b) with a real render folder per clip (``render_sequence``: ``--views``
   views, ``--size`` px, ``--spp`` spp, every ``--every``-th frame; rendered once, untimed) on the
   export's filesystem, so the export hashes and hard-links it; (c) the same render folders on
   another filesystem (``--other-fs``, default ``/dev/shm``), so the export hashes and copies them.
   Each also re-run into its last folder, nothing changed (the export is resumable: it re-hashes
   every file and skips the work). Figures: seconds per run, sequences/min, the export's size
   (files in the manifest plus the manifest), MB/s of it, and the bytes this process actually
   wrote (``wchar`` of ``/proc/self/io``: a hard link writes nothing).
2. **Loaders** over the train split of a separate export of ``--loader-sequences`` clips of
   ``--loader-seconds`` (contacts included, no renders; untimed), windows of ``--window`` rows with
   stride L/2, ``--batch`` per batch, ``--epochs`` full passes (the first reported apart, as
   warm-up; default DataLoader settings, so workers are forked anew every epoch and
   ``set_epoch`` reaches them): :class:`MotionWindows` on the folder (in order and shuffled, 0 and
   2 workers) and on the shards, :class:`ShardWindows` (0 and 2 workers) over ``write_shards``
   shards (about ``--shards`` of them), against the **baseline**: a bare loop that ``numpy.load``\\ s
   ``a.features`` and ``b.features`` of each motion.npz in turn, copies out the same windows and
   stacks them into batches, no torch. Ratios are to the baseline run in the same process.
   One row marked "(experiment)": the folder dataset with ``persistent_workers=True`` (its cache
   then survives epochs; ``set_epoch`` reaches it through shared memory).

``--profile`` also prints the top functions (cProfile, cumulative) of one export (a) run and one
shuffled 0-worker MotionWindows epoch. Writes ``benchmarks/results/export.json`` (``--out``
elsewhere). No goals: the figures back the export's and loaders' design (decision record 0024).

    .venv/bin/python benchmarks/bench_export.py [--sequences 8] [--seconds 3] [--repeats 3]
        [--loader-sequences 48] [--loader-seconds 8] [--epochs 4] [--scene-cache DIR] [--profile]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from results_file import Table, write_results  # noqa: E402

MB = 1e6


# ============================================================================ data
def load_scene(kind: str, fps: float, seconds: float | None, cache: Path | None):
    """The ground-truth scene ``kind`` (seed 0) at ``fps``, ``seconds`` long (None: natural);
    ``(scene, generation seconds)`` (0 when read from ``cache``)."""
    from dualhuman_builder.sim.scenes import Scene, SceneParams, make_scene

    tag = f"_{seconds:g}s" if seconds else ""
    path = cache / f"scene_{kind}_seed0_{fps:g}fps{tag}.npz" if cache else None
    if path is not None and path.is_file():
        return Scene.load(path), 0.0
    print(f"generating the {kind} scene at {fps:g} fps{f', {seconds:g} s' if seconds else ''} ...", flush=True)
    t0 = time.perf_counter()
    sc = make_scene(SceneParams(type=kind, seed=0, fps=fps, duration=seconds))
    gen = time.perf_counter() - t0
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        sc.save(path)
    return sc, gen


def fresh_clip(seq, start: int, frames: int):
    """Frames ``start .. start+frames-1`` of ``seq`` as a new InteractionSequence with new tracks
    (nothing cached: the export computes the joints itself)."""
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    sl = slice(start, start + frames)
    actors = [BodyTrack(pose=a.pose[sl], transl=a.transl[sl], shape=a.shape, fps=a.fps, bone_names=a.bone_names,
                        shape_names=a.shape_names, model=a.model, model_version=a.model_version, actor=a.actor)
              for a in seq.actors]  # fmt: skip
    return InteractionSequence(actors, take=seq.take, frame_range=(start, start + frames), labels=seq.labels,
                               text=seq.text, meta=seq.meta)  # fmt: skip


def slice_contacts(res, start: int, frames: int) -> dict:
    """A ContactResult's frames ``start .. start+frames-1`` as the export's contacts dict; events
    that overlap the clip are clipped to it (frame indices relative to the clip)."""
    stop = start + frames
    events = []
    for ev in res.events:
        lo, hi = max(int(ev["start"]), start), min(int(ev["end"]), stop)
        if lo < hi:
            e = {k: v for k, v in ev.items() if k not in ("start_s", "end_s")}
            events.append({**e, "start": lo - start, "end": hi - start})
    return {"labels": res.labels[:, start:stop], "distances": res.distances[:, start:stop],
            "frame_contact": res.frame_contact[start:stop], "events": events}  # fmt: skip


class Clips:
    """``count`` clips of ``frames`` frames from ``scenes`` (name -> (scene, contacts)), clip ``k``
    from scene ``k mod len(scenes)``, start frames spread evenly over each scene."""

    def __init__(self, scenes: dict, count: int, frames: int, prefix: str):
        names = list(scenes)
        per = math.ceil(count / len(names))
        self.specs = []  # (seq_id, scene name, start)
        for k in range(count):
            name = names[k % len(names)]
            T = scenes[name][0].sequence.num_frames
            if frames > T:
                raise SystemExit(f"clips of {frames} frames do not fit the {T}-frame {name} scene: "
                                 "lower --seconds/--loader-seconds or raise --scene-seconds")  # fmt: skip
            starts = np.linspace(0, T - frames, per).round().astype(int)
            self.specs.append((f"{prefix}{name}_{k:03d}", name, int(starts[k // len(names)])))
        self.scenes, self.frames = scenes, frames

    def sequence(self, i: int):
        sid, name, start = self.specs[i]
        return fresh_clip(self.scenes[name][0].sequence, start, self.frames)

    def items(self, render_dirs: dict | None = None) -> list:
        """Fresh ExportItems (new tracks every call)."""
        from dualhuman_builder.export.items import ExportItem

        out = []
        for i, (sid, name, start) in enumerate(self.specs):
            contacts = slice_contacts(self.scenes[name][1], start, self.frames)
            out.append(ExportItem(sid, self.sequence(i), contacts=contacts,
                                  render_dir=render_dirs.get(sid) if render_dirs else None))  # fmt: skip
        return out


def render_clips(clips: Clips, root: Path, args) -> tuple[dict, dict]:
    """One small render folder per clip under ``root`` (kept there: a folder with a
    ``render.json`` is reused); ``({seq_id: folder}, timing)``."""
    from dualhuman_builder.render.stage import render_sequence, stage_cameras

    dirs, images, reused, t0 = {}, 0, 0, time.perf_counter()
    for i, (sid, name, start) in enumerate(clips.specs):
        folder = root / f"{name}_{start}+{clips.frames}_{args.views}v{args.size}px{args.spp}spp{args.every}e"
        dirs[sid] = folder
        if (folder / "render.json").is_file():
            reused += 1
            continue
        seq = clips.sequence(i)
        cams = stage_cameras(seq, views=args.views, size=args.size)
        doc = render_sequence(seq, folder, cams, spp=args.spp, every=args.every, log=lambda _m: None)
        images += int(doc.get("images", len(doc["frames"]) * len(doc["views"])))
    secs = time.perf_counter() - t0
    files = [p for d in dirs.values() for p in d.rglob("*") if p.is_file() and ".progress" not in p.parts]
    return dirs, {"seconds": round(secs, 1), "images": images, "reused": reused, "files_per_sequence": len(files) / len(dirs),
                  "mb_per_sequence": sum(p.stat().st_size for p in files) / MB / len(dirs)}  # fmt: skip


# ============================================================================ export timing
def wchar() -> int:
    """Bytes this process has passed to write()/sendfile() so far (``/proc/self/io``), or -1."""
    try:
        for line in Path("/proc/self/io").read_text().splitlines():
            if line.startswith("wchar:"):
                return int(line.split()[1])
    except OSError:
        pass
    return -1


def export_size(out: Path, manifest: dict) -> int:
    return sum(int(r["bytes"]) for r in manifest["files"].values()) + (out / "manifest.json").stat().st_size


def timed_export(make_items, out: Path) -> tuple[float, float, int, dict, str]:
    """One ``export_dataset`` run: ``(seconds, CPU seconds (all threads), bytes written by this
    process, manifest, last progress line)``."""
    from dualhuman_builder.export.writer import export_dataset

    items = make_items()  # built outside the timed region
    lines: list[str] = []
    w0, c0, t0 = wchar(), time.process_time(), time.perf_counter()
    manifest = export_dataset(items, out, progress=lines.append)
    secs, cpu, w1 = time.perf_counter() - t0, time.process_time() - c0, wchar()
    return secs, cpu, (w1 - w0) if w0 >= 0 else -1, manifest, lines[-1]


def bench_export(label: str, make_items, root: Path, repeats: int, n: int) -> tuple[dict, Path]:
    """``repeats`` fresh exports into new folders, then ``repeats`` re-runs into the last one."""
    fresh, reruns, out = [], [], None
    manifest: dict = {}
    for r in range(repeats):
        out = root / f"{label}-{r}"
        secs, cpu, written, manifest, _ = timed_export(make_items, out)
        fresh.append((secs, written, cpu))
    size = export_size(out, manifest)
    for _ in range(repeats):
        secs, cpu, written, again, last = timed_export(make_items, out)
        if " 0 files written" not in last or again != manifest:
            raise SystemExit(f"{label}: the re-run changed the export ({last})")
        reruns.append((secs, written, cpu))
    s_fresh, s_rerun = statistics.median(x[0] for x in fresh), statistics.median(x[0] for x in reruns)
    res = {"sequences": n, "frames": manifest["counts"]["frames"], "export_mb": size / MB,
           "with_renders": manifest["counts"]["with_renders"],
           "fresh": {"seconds": s_fresh, "sequences_per_min": 60 * n / s_fresh, "mb_per_s": size / MB / s_fresh,
                     "written_mb": statistics.median(x[1] for x in fresh) / MB, "runs_s": [x[0] for x in fresh],
                     "cpu_s": statistics.median(x[2] for x in fresh)},
           "rerun": {"seconds": s_rerun, "sequences_per_min": 60 * n / s_rerun, "mb_per_s": size / MB / s_rerun,
                     "written_mb": statistics.median(x[1] for x in reruns) / MB, "runs_s": [x[0] for x in reruns],
                     "cpu_s": statistics.median(x[2] for x in reruns)}}  # fmt: skip
    return res, out


# ============================================================================ loader timing
def baseline_epoch(folder: Path, ids: list[str], L: int, stride: int, batch: int) -> int:
    """The bare loop: per sequence ``numpy.load`` its two feature arrays, copy out the windows,
    stack them ``batch`` at a time. Returns the number of windows."""
    n, wa, wb = 0, [], []
    for sid in ids:
        with np.load(folder / "sequences" / sid / "motion.npz", allow_pickle=False) as z:
            fa, fb = z["a.features"], z["b.features"]
        for s in range(0, len(fa) - L + 1, stride):
            wa.append(fa[s : s + L].copy())
            wb.append(fb[s : s + L].copy())
            if len(wa) == batch:
                np.stack(wa), np.stack(wb)
                n, wa, wb = n + len(wa), [], []
    if wa:
        np.stack(wa), np.stack(wb)
        n += len(wa)
    return n


def run_epochs(make_iter, epochs: int, set_epoch=None) -> dict:
    """Time ``epochs`` full passes of ``make_iter()`` (an iterable of batches, or the window count
    of a pass it has just made); first epoch apart. Returns windows/s figures and the seconds to
    the first batch (None for a plain count)."""
    rates, firsts, n = [], [], 0
    for e in range(epochs):
        if set_epoch is not None:
            set_epoch(e)
        t0 = time.perf_counter()
        it = make_iter()
        if isinstance(it, int):
            n, first = it, None
        else:
            n, first = 0, None
            for batch in it:
                if first is None:
                    first = time.perf_counter() - t0
                n += len(batch["a"])
        dt = time.perf_counter() - t0
        rates.append(n / dt)
        firsts.append(first)
    steady, firsts = rates[1:] or rates, [f for f in firsts[1:] or firsts if f is not None]
    return {"windows": n, "first_epoch_wps": rates[0], "wps": statistics.median(steady), "epochs_wps": rates,
            "first_batch_s": statistics.median(firsts) if firsts else None}  # fmt: skip


def bench_loaders(folder: Path, shard_dir: Path, args) -> dict:
    import torch
    from torch.utils.data import DataLoader

    from dualhuman_builder.export.loader import MotionWindows, ShardWindows
    from dualhuman_builder.export.shards import write_shards

    L, B = args.window, args.batch
    stride = max(L // 2, 1)
    ids = [s for s in (folder / "splits" / "train.txt").read_text().split() if s]
    m = json.loads((folder / "manifest.json").read_text())
    keep = set(ids)
    train_bytes = sum(r["bytes"] for k, r in m["files"].items() if k.startswith("sequences/") and k.split("/")[1] in keep)
    max_bytes = max(int(1.05 * train_bytes / max(args.shards, 1)) + 64 * 1024, 4 * 20 * 512)
    t0 = time.perf_counter()
    shards = write_shards(folder, shard_dir, max_bytes=max_bytes, split="train")
    shard_s = time.perf_counter() - t0

    out: dict = {"train_sequences": len(ids), "window": L, "stride": stride, "batch": B, "shards": len(shards),
                 "shard_mb": sum(p.stat().st_size for p in shards) / MB, "write_shards_s": shard_s}  # fmt: skip
    rows: dict = {}
    rows["baseline"] = run_epochs(lambda: baseline_epoch(folder, ids, L, stride, B), args.epochs)

    def map_style(source, workers: int, shuffle: bool, persistent: bool = False):
        ds = MotionWindows(source, window=L, stride=stride, split="train", normalize=args.normalize,
                           mirror_p=args.mirror_p)  # fmt: skip
        torch.manual_seed(0)
        if persistent:
            dl = DataLoader(ds, batch_size=B, shuffle=shuffle, num_workers=workers, persistent_workers=True)
            return run_epochs(lambda: dl, args.epochs, ds.set_epoch)
        return run_epochs(lambda: DataLoader(ds, batch_size=B, shuffle=shuffle, num_workers=workers), args.epochs,
                          ds.set_epoch)  # fmt: skip

    def streaming(workers: int):
        ds = ShardWindows(shards, window=L, stride=stride, normalize=args.normalize, mirror_p=args.mirror_p)
        return run_epochs(lambda: DataLoader(ds, batch_size=B, num_workers=workers), args.epochs, ds.set_epoch)

    rows["folder_0w_ordered"] = map_style(folder, 0, False)
    rows["folder_0w_shuffled"] = map_style(folder, 0, True)
    rows["folder_2w_shuffled"] = map_style(folder, 2, True)
    rows["folder_2w_persistent"] = map_style(folder, 2, True, persistent=True)
    rows["shards_in_memory_0w"] = map_style(shards, 0, True)
    rows["shards_in_memory_2w"] = map_style(shards, 2, True)
    rows["shard_windows_0w"] = streaming(0)
    rows["shard_windows_2w"] = streaming(2)
    base = rows["baseline"]["wps"]
    for key, r in rows.items():
        r["ratio"] = r["wps"] / base
        r["label"] = LOADER_ROWS[key]
    out["rows"] = rows
    return out


#: The loader rows: key in the results -> label.
LOADER_ROWS = {
    "baseline": "baseline: np.load + slice, no torch",
    "folder_0w_ordered": "MotionWindows folder, 0 workers, in order",
    "folder_0w_shuffled": "MotionWindows folder, 0 workers, shuffled",
    "folder_2w_shuffled": "MotionWindows folder, 2 workers, shuffled",
    "folder_2w_persistent": "  (experiment) same, persistent_workers=True",
    "shards_in_memory_0w": "MotionWindows shards (in memory), 0 workers, shuffled",
    "shards_in_memory_2w": "MotionWindows shards (in memory), 2 workers, shuffled",
    "shard_windows_0w": "ShardWindows, 0 workers",
    "shard_windows_2w": "ShardWindows, 2 workers",
}


def profile_top(fn, top: int) -> str:
    import cProfile
    import io
    import pstats

    pr = cProfile.Profile()
    pr.enable()
    fn()
    pr.disable()
    buf = io.StringIO()
    pstats.Stats(pr, stream=buf).sort_stats("cumulative").print_stats(top)
    return "\n".join(line for line in buf.getvalue().splitlines() if line.strip())


# ============================================================================ main
def fs_type(path: Path) -> str:
    """Filesystem type of ``path`` (longest matching mount point of ``/proc/mounts``)."""
    best, kind = "", "?"
    try:
        p = str(path.resolve())
        for line in Path("/proc/mounts").read_text().splitlines():
            parts = line.split()
            if len(parts) > 2 and (p == parts[1] or p.startswith(parts[1].rstrip("/") + "/")) and len(parts[1]) >= len(best):
                best, kind = parts[1], parts[2]
    except OSError:
        pass
    return kind


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--types", default="handshake,high_five,push", help="scene types the clips are cut from")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--scene-seconds", type=float, default=10.0,
                    help="scene length, padded with standing (0: each type's natural length)")  # fmt: skip
    ap.add_argument("--sequences", type=int, default=8, help="sequences per export run")
    ap.add_argument("--seconds", type=float, default=3.0, help="length of each exported sequence")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--every", type=int, default=5, help="render every n-th frame")
    ap.add_argument("--no-renders", action="store_true", help="skip the export runs with renders")
    ap.add_argument("--other-fs", type=Path, default=Path("/dev/shm"),
                    help="a folder on another filesystem for the render-copy runs ('' skips them)")  # fmt: skip
    ap.add_argument("--loader-sequences", type=int, default=48)
    ap.add_argument("--loader-seconds", type=float, default=8.0, help="length of each loader sequence")
    ap.add_argument("--window", type=int, default=60)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--epochs", type=int, default=4, help="full passes per loader (the first one reported apart)")
    ap.add_argument("--shards", type=int, default=4, help="about this many train shards")
    ap.add_argument("--normalize", action="store_true")
    ap.add_argument("--mirror-p", type=float, default=0.0)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--workdir", type=Path, default=None,
                    help="where the exports go (default: a temporary folder in the scene cache, else the temp folder)")
    ap.add_argument("--scene-cache", type=Path, default=REPO / "benchmarks" / "cache",
                    help="keep generated scenes (and the render folders) here ('' disables)")  # fmt: skip
    ap.add_argument("--out", "--json", type=Path, default=None,
                    help="results file (default benchmarks/results/export.json)")
    args = ap.parse_args(argv)
    cache = args.scene_cache if str(args.scene_cache) not in ("", ".") else None
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)

    from dualhuman_builder.evaluation.contacts import contacts_for_scene
    from dualhuman_builder.export.writer import export_dataset

    load0 = os.getloadavg()[0]
    scenes, prep = {}, {}
    for kind in args.types.split(","):
        sc, gen = load_scene(kind, args.fps, args.scene_seconds or None, cache)
        t0 = time.perf_counter()
        res, _ = contacts_for_scene(sc)
        scenes[kind] = (sc, res)
        prep[kind] = {"frames": sc.sequence.num_frames, "generation_s": round(gen, 1),
                      "contacts_s": round(time.perf_counter() - t0, 1)}  # fmt: skip
    frames = int(round(args.seconds * args.fps))
    loader_frames = int(round(args.loader_seconds * args.fps))
    clips = Clips(scenes, args.sequences, frames, "")
    result: dict = {"scenes": prep}

    # beside the cached render folders, so that (b) hard-links them
    workdir = Path(tempfile.mkdtemp(prefix="bench-export-", dir=args.workdir or cache))
    other = None
    try:
        if args.other_fs and str(args.other_fs) not in ("", ".") and args.other_fs.is_dir():
            if os.stat(args.other_fs).st_dev != os.stat(workdir).st_dev:
                other = Path(tempfile.mkdtemp(prefix="bench-export-", dir=args.other_fs))
        exports: dict = {}
        print(f"export: {args.sequences} sequences x {frames} frames at {args.fps:g} fps, median of {args.repeats} "
              f"runs, into {workdir} ({fs_type(workdir)}) ...", flush=True)  # fmt: skip
        exports["a"], _ = bench_export("a", clips.items, workdir, args.repeats, args.sequences)
        exports["a"]["label"] = "(a) no renders"
        if args.profile:
            print(profile_top(lambda: export_dataset(clips.items(), workdir / "profile-a"), 25))
        if not args.no_renders:
            render_root = cache / "renders" if cache else workdir / "renders"
            dirs, render_info = render_clips(clips, render_root, args)
            result["renders"] = {**render_info, "views": args.views, "size": args.size, "spp": args.spp,
                                 "every": args.every, "folder": str(render_root)}  # fmt: skip
            linked = os.stat(render_root).st_dev == os.stat(workdir).st_dev
            exports["b"], _ = bench_export("b", lambda: clips.items(dirs), workdir, args.repeats, args.sequences)
            exports["b"]["label"] = f"(b) renders, {'hard-linked' if linked else 'copied'} (same filesystem)"
            if other is not None:
                far = {}
                for sid, d in dirs.items():
                    far[sid] = other / "renders" / d.name
                    if not far[sid].exists():
                        shutil.copytree(d, far[sid])
                exports["c"], _ = bench_export("c", lambda: clips.items(far), workdir, args.repeats, args.sequences)
                exports["c"]["label"] = f"(c) renders, copied from {fs_type(other)}"
        for label in ("b", "c"):
            for p in workdir.glob(f"{label}-*"):
                shutil.rmtree(p)
        result["export"] = exports

        # loaders
        lclips = Clips(scenes, args.loader_sequences, loader_frames, "L")
        t0 = time.perf_counter()
        lout = workdir / "loader"
        export_dataset(lclips.items(), lout)
        result["loader_export_s"] = time.perf_counter() - t0
        print(f"loaders: {args.loader_sequences} sequences x {loader_frames} frames (export {result['loader_export_s']:.1f} s), "
              f"window {args.window}, batch {args.batch}, {args.epochs} epochs ...", flush=True)  # fmt: skip
        result["loaders"] = bench_loaders(lout, workdir / "shards", args)
        if args.profile:
            import torch
            from torch.utils.data import DataLoader

            from dualhuman_builder.export.loader import MotionWindows

            ds = MotionWindows(lout, window=args.window, split="train")
            torch.manual_seed(0)
            print(profile_top(lambda: [None for _ in DataLoader(ds, batch_size=args.batch, shuffle=True)], 25))
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
        if other is not None:
            shutil.rmtree(other, ignore_errors=True)

    # ------------------------------------------------------------------ table
    load1 = os.getloadavg()[0]
    print()
    print(f"bench_export: {os.cpu_count()} CPUs, load {load0:.2f} -> {load1:.2f}; exports on {fs_type(workdir)}")
    print("scenes: " + ", ".join(f"{k} {v['frames']} frames (contacts {v['contacts_s']} s"
                                 f"{', generated ' + str(v['generation_s']) + ' s' if v['generation_s'] else ''})"
                                 for k, v in prep.items()))  # fmt: skip
    if "renders" in result:
        r = result["renders"]
        print(f"renders (untimed): {r['views']} views, {r['size']} px, {r['spp']} spp, every {r['every']}th frame: "
              f"{r['images']} images in {r['seconds']} s ({r['reused']} folders reused); {r['files_per_sequence']:.0f} files, "
              f"{r['mb_per_sequence']:.2f} MB per sequence")  # fmt: skip
    head = f"{'export of ' + str(args.sequences) + ' x ' + str(frames) + ' frames':38s}{'run':>14s}{'s/run':>8s}" \
           f"{'CPU s':>7s}{'seq/min':>9s}{'size MB':>9s}{'MB/s':>8s}{'written MB':>12s}"
    print(head)
    print("-" * len(head))
    for e in result["export"].values():
        for kind, name in (("fresh", "fresh folder"), ("rerun", "re-run, same")):
            x = e[kind]
            print(f"{e['label'] if kind == 'fresh' else '':38s}{name:>14s}{x['seconds']:8.2f}{x['cpu_s']:7.2f}{x['sequences_per_min']:9.1f}"
                  f"{e['export_mb']:9.2f}{x['mb_per_s']:8.1f}{x['written_mb']:12.2f}")  # fmt: skip
    lo = result["loaders"]
    print(f"\nloaders: {lo['train_sequences']} train sequences, window {lo['window']}, stride {lo['stride']}, "
          f"batch {lo['batch']}, {lo['shards']} shards ({lo['shard_mb']:.1f} MB, written in {lo['write_shards_s']:.2f} s); "
          f"epochs after the first, median")  # fmt: skip
    head = f"{'loader (shuffled: DataLoader shuffle=True)':56s}{'windows':>8s}{'win/s':>10s}{'x base':>8s}{'1st epoch':>11s}{'1st batch s':>12s}"
    print(head)
    print("-" * len(head))
    for r in lo["rows"].values():
        fb = "" if r["first_batch_s"] is None else f"{r['first_batch_s']:.3f}"
        print(f"{r['label']:56s}{r['windows']:8d}{r['wps']:10.0f}{r['ratio']:8.3f}{r['first_epoch_wps']:11.0f}{fb:>12s}")
    result["load"] = {"before": load0, "after": load1, "exports_on": fs_type(workdir)}
    tables = [Table(f"export of {args.sequences} sequences x {frames} frames at {args.fps:g} fps (median of "
                    f"{args.repeats})", ["export", "sequences/min", "re-run, nothing changed: sequences/min",
                                         "size MB", "written MB"],
                    [[e["label"], f"export.{k}.fresh.sequences_per_min", f"export.{k}.rerun.sequences_per_min",
                      f"export.{k}.export_mb", f"export.{k}.fresh.written_mb"] for k, e in result["export"].items()]),
              Table(f"loaders over {lo['train_sequences']} train sequences, window {lo['window']}, stride {lo['stride']}, "
                    f"batch {lo['batch']} (epochs after the first, median)",
                    ["loader", "windows/s", "x bare numpy.load loop", "first epoch windows/s"],
                    [[r["label"].strip(), f"loaders.rows.{k}.wps", f"loaders.rows.{k}.ratio",
                      f"loaders.rows.{k}.first_epoch_wps"] for k, r in lo["rows"].items()])]  # fmt: skip
    params = {k: v for k, v in vars(args).items() if k not in ("out", "workdir", "scene_cache", "profile")}
    path = write_results("export", result, params=params, tables=tables, out=args.out)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

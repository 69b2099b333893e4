"""Render stage speed and memory: the full pipeline against a bare Mitsuba render loop, in the same
run.

Scene: the ``hug`` ground-truth scene (``make_scene(SceneParams(type="hug", seed=0, fps=15))``,
cached in ``benchmarks/cache/render_hug_seed0_15fps.npz``; ``--sequence`` loads another
InteractionSequence), ``--frames`` frames around its middle (the bodies in contact), a ring of
``--views`` cameras, ``--size`` square images, the default template (studio) and sample count.

* **bare**: a :class:`SequenceRenderer` scene built for the run; per frame ``set_frame`` (vertex
  positions and normals through ``mi.traverse``) and per view ``mi.render(scene, sensor=i)`` with
  the image fetched to the host. Bodies are evaluated beforehand (not timed). It is released
  before the pipeline run, so that each run has one scene alive (see :func:`compare`).
* **pipeline**: :func:`render_sequence` on the same frames: body evaluation, RGB, depth and mask
  pass, keypoints and visibility, PNG/EXR encoding on the thread pool, resume markers, the
  per-render files. Its figure is the ``images_per_s`` it records (renderer construction
  excluded, as for the bare loop).

Both after a warm-up (JIT compilation), run alternately (load from other processes hits both
alike); medians of ``--repeats`` runs; ratio = pipeline / bare (goal >= 0.8), by wall time and
by CPU time of the process (all threads; steadier when other processes share the machine). Then the memory check: ``--memory-frames`` frames (the sequence tiled) at
``--memory-size`` pixels, one view, full pipeline, resident set size sampled every 0.2 s (it
should stay flat: the growth from 10 % of the frames to the end is recorded).

    .venv/bin/python benchmarks/bench_render.py [--size 512] [--views 4] [--frames 2] [--repeats 3]
        [--variant llvm_ad_rgb] [--memory-frames 1000] [--memory-size 64] [--out PATH]

Goal: pipeline / bare >= 0.8 by wall time (``GOAL_RATIO``). Writes ``benchmarks/results/render.json``
(``render_cuda.json`` for a CUDA variant; ``--out`` elsewhere).
"""

from __future__ import annotations

import argparse
import gc
import platform
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from results_file import Goal, Table, write_results  # noqa: E402

CACHE = REPO / "benchmarks" / "cache" / "render_hug_seed0_15fps.npz"
#: Images per second the full pipeline must keep of the bare render loop's.
GOAL_RATIO = 0.8


def rss_mb() -> float:
    """Resident set size of this process in MiB (Linux /proc)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def load_sequence(path: Path | None):
    from dualhuman_builder.tracks import InteractionSequence

    if path is not None:
        return InteractionSequence.load(path)
    if CACHE.is_file():
        return InteractionSequence.load(CACHE)
    from dualhuman_builder.sim.scenes import SceneParams, make_scene

    print("generating the hug scene (once; cached in benchmarks/cache/) ...", flush=True)
    seq = make_scene(SceneParams(type="hug", seed=0, fps=15)).sequence
    CACHE.parent.mkdir(parents=True, exist_ok=True)
    seq.save(CACHE)
    return seq


def sub_sequence(seq, idx):
    """The frames ``idx`` of ``seq`` (tiled when ``idx`` repeats frames) as a new sequence."""
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    actors = [BodyTrack(pose=a.pose[idx], transl=a.transl[idx], shape=a.shape, fps=a.fps, bone_names=a.bone_names,
                        shape_names=a.shape_names, model=a.model, model_version=a.model_version, actor=a.actor)
              for a in seq.actors]  # fmt: skip
    return InteractionSequence(actors)


def bare_loop(renderer, verts) -> tuple[float, float]:
    """``(images/s, CPU seconds per image)`` of set_frame + mi.render per view (image fetched to
    the host), one pass."""
    import mitsuba as mi

    scene, sensors, spp = renderer.scene, renderer._sensors, renderer.spp
    t, c = time.perf_counter(), time.process_time()
    n = 0
    for f in range(len(verts[0])):
        renderer.set_frame(verts[0][f], verts[1][f])
        for k, s in enumerate(sensors):
            np.asarray(mi.render(scene, sensor=s, spp=spp, seed=f * len(sensors) + k))
            n += 1
    return n / (time.perf_counter() - t), (time.process_time() - c) / n


def compare(make, seq, verts, cams, spp, variant, repeats: int, workers: int | None = None) -> tuple[list, list, dict]:
    """Alternating runs of the bare loop and of render_sequence (so that load from other
    processes hits both alike), after a warm-up of each; returns both lists of
    ``(images/s, CPU seconds per image)``.

    One Mitsuba scene is alive during each timed run: the bare loop's renderer (``make()``) is
    built for its run, warmed on one frame and released before the pipeline builds its own. With a
    second scene resident every render is slower, which would be charged to whichever side runs
    second."""
    from dualhuman_builder.render.stage import render_sequence

    quiet = lambda s: None  # noqa: E731
    bare, full, doc = [], [], {}
    with tempfile.TemporaryDirectory(prefix="bench-render-") as tmp:
        render_sequence(sub_sequence(seq, [0]), Path(tmp) / "warm", cams, spp=spp, variant=variant, log=quiet)
        for r in range(repeats):
            gc.collect()  # the previous run's renderer is released before, not during, a timed run
            renderer = make()
            bare_loop(renderer, [v[:1] for v in verts])  # warm-up: a new scene's first render
            bare.append(bare_loop(renderer, verts))
            del renderer
            gc.collect()
            doc = render_sequence(seq, Path(tmp) / f"run{r}", cams, spp=spp, variant=variant, log=quiet, workers=workers)
            full.append((doc["images_per_s"], doc["cpu_seconds"] / doc["images"]))
    return bare, full, doc


def encode_ms(size: int, repeats: int = 5) -> dict:
    """Milliseconds to encode one view's files (sRGB PNG, depth EXR, mask PNG) at ``size``."""
    from dualhuman_builder.render.stage import write_depth_exr, write_mask_png, write_rgb_png

    rng = np.random.default_rng(0)
    rgb = rng.random((size, size, 3), dtype=np.float32) * 0.3 + 0.2  # noisy, like a 16 spp render
    depth = (2.0 + rng.random((size, size), dtype=np.float32)).astype(np.float32)
    mask = (rng.random((size, size)) > 0.8).astype(np.uint8)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, fn, arr, ext in (("rgb png", write_rgb_png, rgb, "png"), ("depth exr", write_depth_exr, depth, "exr"),
                                   ("mask png", write_mask_png, mask, "png")):  # fmt: skip
            ts = []
            for k in range(repeats):
                t = time.perf_counter()
                fn(Path(tmp) / f"{k}.{ext}", arr)
                ts.append(time.perf_counter() - t)
            out[name] = round(statistics.median(ts) * 1e3, 2)
    return out


def breakdown(renderer, seq, repeats: int = 3) -> dict:
    """Median milliseconds per image of each step the pipeline's main thread runs in order: body
    evaluation (per frame, divided by the views), ``set_frame``, the RGB render (image fetched),
    the depth/mask pass, the keypoint annotation of both actors. The encoders run on the pool."""
    from dualhuman_builder.render.annotations import annotate_view
    from dualhuman_builder.render.stage import body_device

    cams, dev = renderer.cameras, body_device(renderer.variant)
    steps: dict[str, list] = {"body": [], "set_frame": [], "rgb": [], "depth_mask": [], "annotate": []}
    for _ in range(repeats):
        for f in range(seq.num_frames):
            t = time.perf_counter()
            bodies = [a.compute(frames=np.array([f]), device=dev) for a in seq.actors]
            steps["body"].append((time.perf_counter() - t) / len(cams))
            t = time.perf_counter()
            renderer.set_frame(bodies[0]["vertices"][0], bodies[1]["vertices"][0])
            steps["set_frame"].append((time.perf_counter() - t) / len(cams))
            pj = np.stack([b["joints"][0] for b in bodies])
            pc = np.stack([b["coco"][0] for b in bodies])
            for i, cam in enumerate(cams):
                t = time.perf_counter()
                renderer.render_rgb(i, seed=i)
                t1 = time.perf_counter()
                depth, mask = renderer.render_depth_mask(i)
                t2 = time.perf_counter()
                annotate_view(cam, pj, depth, mask)
                annotate_view(cam, pc, depth, mask)
                t3 = time.perf_counter()
                steps["rgb"].append(t1 - t)
                steps["depth_mask"].append(t2 - t1)
                steps["annotate"].append(t3 - t2)
    return {k: round(statistics.median(v) * 1e3, 2) for k, v in steps.items()} | {"body_device": dev}


def profile_pipeline(seq, cams, spp, variant, workers) -> None:
    """cProfile of one render_sequence run (the main thread: rendering, annotation, waiting for the
    encoders), top functions by own time."""
    import cProfile
    import pstats

    from dualhuman_builder.render.stage import render_sequence

    with tempfile.TemporaryDirectory(prefix="bench-render-prof-") as tmp:
        prof = cProfile.Profile()
        prof.enable()
        render_sequence(seq, Path(tmp) / "p", cams, spp=spp, variant=variant, log=lambda s: None, workers=workers)
        prof.disable()
    pstats.Stats(prof).sort_stats("tottime").print_stats(18)


def diagnose(seq, cams, spp, variant, workers, repeats: int) -> None:
    """Pipeline images/s as is, with a 0.5 ms GIL switch interval (threads waiting for the GIL
    get it sooner), and with the PNG/EXR writers replaced by no-ops (what encoding costs the
    main thread): medians of ``repeats``."""
    from dualhuman_builder.render import stage

    def run():
        with tempfile.TemporaryDirectory(prefix="bench-render-diag-") as tmp:
            return [stage.render_sequence(seq, Path(tmp) / f"d{r}", cams, spp=spp, variant=variant, log=lambda s: None,
                                          workers=workers)["images_per_s"] for r in range(repeats)]  # fmt: skip

    print(f"diagnose, pipeline images/s: as is {statistics.median(run()):.2f}", end="", flush=True)
    old = sys.getswitchinterval()
    sys.setswitchinterval(0.0005)
    try:
        print(f", switch interval 0.5 ms {statistics.median(run()):.2f}", end="", flush=True)
    finally:
        sys.setswitchinterval(old)
    saved = stage.write_rgb_png, stage.write_depth_exr, stage.write_mask_png
    stage.write_rgb_png = stage.write_depth_exr = stage.write_mask_png = lambda *a, **k: None
    try:
        print(f", writers skipped {statistics.median(run()):.2f}")
    finally:
        stage.write_rgb_png, stage.write_depth_exr, stage.write_mask_png = saved
    # where one pipeline run's main thread goes: each step timed inside render_sequence
    from dualhuman_builder.render.renderer import SequenceRenderer
    from dualhuman_builder.tracks import BodyTrack

    times: dict[str, list] = {}
    targets = [(SequenceRenderer, n) for n in ("set_frame", "render_rgb", "render_depth_mask")]
    targets += [(BodyTrack, "compute"), (stage, "annotate_view"), (stage, "_write_npz")]
    originals = [(obj, name, getattr(obj, name)) for obj, name in targets]

    def timed(name, fn):
        def wrapper(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                times.setdefault(name, []).append(time.perf_counter() - t)
        return wrapper

    for obj, name, fn in originals:
        setattr(obj, name, timed(name, fn))
    try:
        with tempfile.TemporaryDirectory(prefix="bench-render-diag-") as tmp:
            t = time.perf_counter()
            doc = stage.render_sequence(seq, Path(tmp) / "i", cams, spp=spp, variant=variant, log=lambda s: None,
                                        workers=workers)  # fmt: skip
            wall = time.perf_counter() - t
    finally:
        for obj, name, fn in originals:
            setattr(obj, name, fn)
    n = doc["images"]
    print(f"instrumented run: {doc['images_per_s']:.2f} images/s ({1e3 * doc['seconds'] / n:.1f} ms/image; "
          f"{wall:.2f} s with the scene build)")
    for name, ts in times.items():
        print(f"  {name:18s} calls {len(ts):4d}  total ms/image {1e3 * sum(ts) / n:6.2f}  first {1e3 * ts[0]:8.1f} ms  "
              f"median {1e3 * statistics.median(ts):7.2f} ms")


def memory_check(seq, frames: int, size: int, spp: int, variant) -> dict:
    """RSS over a ``frames``-frame render (the sequence tiled), one view of ``size`` pixels."""
    from dualhuman_builder.render.stage import render_sequence, stage_cameras

    idx = np.arange(frames) % seq.num_frames
    long = sub_sequence(seq, idx)
    cams = stage_cameras(long, views=1, size=size, frames=np.arange(min(frames, seq.num_frames)))
    samples, steps, stop = [], [], threading.Event()

    def sampler():
        while not stop.is_set():
            samples.append(rss_mb())
            stop.wait(0.2)

    def log(line):
        if "images (" in line:
            steps.append((line.split(" images")[0].split()[-1], round(rss_mb(), 1)))

    before = rss_mb()
    th = threading.Thread(target=sampler, daemon=True)
    th.start()
    t = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-render-mem-") as tmp:
        doc = render_sequence(long, Path(tmp) / "long", cams, spp=spp, variant=variant, log=log)
    stop.set()
    th.join()
    return {"frames": frames, "size": size, "spp": spp, "seconds": round(time.perf_counter() - t, 1),
            "images_per_s": doc["images_per_s"], "rss_before_mb": round(before, 1),
            "rss_at_10pct_mb": steps[0][1] if steps else None, "rss_end_mb": steps[-1][1] if steps else None,
            "rss_max_mb": round(max(samples), 1), "rss_steps_mb": steps}  # fmt: skip


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--spp", type=int, default=None, help="samples per pixel (default: the renderer's default, 16)")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--frames", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--variant", default=None, help="Mitsuba variant (default: the best that renders here)")
    ap.add_argument("--sequence", type=Path, default=None, help="an InteractionSequence .npz instead of the hug scene")
    ap.add_argument("--memory-frames", type=int, default=1000, help="0 skips the memory check")
    ap.add_argument("--memory-size", type=int, default=64)
    ap.add_argument("--workers", type=int, default=None, help="encoder threads (default: the pipeline's, min(8, CPUs))")
    ap.add_argument("--diagnose", action="store_true",
                    help="also time each main-thread step alone and inside the pipeline, and the pipeline with a 0.5 ms "
                         "GIL switch interval and with the file encoders skipped")
    ap.add_argument("--profile", action="store_true", help="also print where one pipeline run's main thread spends its time")
    ap.add_argument("--out", "--json", type=Path, default=None,
                    help="results file (default benchmarks/results/render.json, or render_cuda.json on CUDA)")
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(1)  # the body model is a small part; leave the cores to the renderer

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.render.renderer import DEFAULT_SPP, SequenceRenderer, body_model_uvs
    from dualhuman_builder.render.stage import stage_cameras

    spp = args.spp or DEFAULT_SPP
    seq = load_sequence(args.sequence)
    mid = seq.num_frames // 2
    idx = np.clip(mid + np.arange(args.frames) - args.frames // 2, 0, seq.num_frames - 1)
    sub = sub_sequence(seq, idx)
    cams = stage_cameras(sub, views=args.views, size=args.size)
    model = get_body_model()
    uv = body_model_uvs(model)

    def make():
        return SequenceRenderer(model.faces, model.num_vertices, cams, spp=spp, variant=args.variant, uv=uv[0], face_uv=uv[1])

    t = time.perf_counter()
    renderer = make()
    build_s = time.perf_counter() - t
    variant = renderer.variant
    print(f"{variant} (Mitsuba {renderer.mitsuba_version}), {platform.machine()}, {args.size}x{args.size}, {spp} spp, "
          f"{args.views} views x {args.frames} frames, template {renderer.template.name}, median of {args.repeats}")  # fmt: skip
    print(f"scene build (once per sequence): {build_s:.2f} s")
    del renderer  # one scene alive at a time (see compare)
    gc.collect()
    res = [a.compute(frames=np.arange(sub.num_frames)) for a in sub.actors]
    bare_runs, full_runs, doc = compare(make, sub, [res[0]["vertices"], res[1]["vertices"]], cams, spp, args.variant,
                                        args.repeats, args.workers)  # fmt: skip
    bare, full = statistics.median(r[0] for r in bare_runs), statistics.median(r[0] for r in full_runs)
    bare_cpu, full_cpu = statistics.median(r[1] for r in bare_runs), statistics.median(r[1] for r in full_runs)
    enc = encode_ms(args.size)
    if args.profile:
        profile_pipeline(sub, cams, spp, args.variant, args.workers)
    steps = {}
    if args.diagnose:  # the steps alone (a renderer of its own, released after), then inside the pipeline
        renderer = make()
        steps = breakdown(renderer, sub)
        del renderer
        gc.collect()
        diagnose(sub, cams, spp, args.variant, args.workers, args.repeats)
    ratio = full / bare
    ratio_cpu = bare_cpu / full_cpu
    rows = [("bare mi.render loop (set_frame + render)", bare, bare_cpu), ("full pipeline (render_sequence)", full, full_cpu)]
    print(f"{'':44s}{'images/s':>10s}{'ms/image':>10s}{'CPU ms/image':>14s}")
    for name, rate, cpu in rows:
        print(f"{name:44s}{rate:10.2f}{1000 / rate:10.1f}{1000 * cpu:14.1f}")
    print(f"pipeline / bare: {ratio:.3f} by wall time, {ratio_cpu:.3f} by CPU time (goal >= {GOAL_RATIO:g})")
    print(f"  runs (images/s): bare {[round(x[0], 3) for x in bare_runs]}, pipeline {[round(x[0], 3) for x in full_runs]}")
    print("encoding one view on one thread, ms: " + ", ".join(f"{k} {v}" for k, v in enc.items()))
    if steps:
        print("main thread per image, steps alone, ms: " + ", ".join(f"{k} {v}" for k, v in steps.items()))
    result = {"variant": variant, "mitsuba": doc.get("mitsuba"), "size": args.size, "spp": spp, "views": args.views,
              "frames": args.frames, "repeats": args.repeats, "template": doc.get("template"), "scene_build_s": round(build_s, 2),
              "bare_images_per_s": round(bare, 3), "pipeline_images_per_s": round(full, 3), "ratio": round(ratio, 3),
              "bare_cpu_ms_per_image": round(1000 * bare_cpu, 1), "pipeline_cpu_ms_per_image": round(1000 * full_cpu, 1),
              "ratio_cpu": round(ratio_cpu, 3), "bare_runs": bare_runs, "pipeline_runs": full_runs,
              "encode_ms": enc, "main_thread_ms": steps}  # fmt: skip
    if args.memory_frames:
        mem = memory_check(seq, args.memory_frames, args.memory_size, spp, args.variant)
        print(f"memory over {mem['frames']} frames at {mem['size']}x{mem['size']}, 1 view ({mem['seconds']} s, "
              f"{mem['images_per_s']} images/s): RSS before {mem['rss_before_mb']} MiB, at 10 % {mem['rss_at_10pct_mb']}, "
              f"end {mem['rss_end_mb']}, max {mem['rss_max_mb']}")  # fmt: skip
        print("  RSS at each 10 %: " + ", ".join(f"{n}: {r}" for n, r in mem["rss_steps_mb"]))
        if mem["rss_at_10pct_mb"] is not None and mem["rss_end_mb"] is not None:
            mem["rss_growth_mb"] = round(mem["rss_end_mb"] - mem["rss_at_10pct_mb"], 1)
        result["memory"] = mem
    result["bare_runs"] = [{"images_per_s": r[0], "cpu_s_per_image": r[1]} for r in bare_runs]
    result["pipeline_runs"] = [{"images_per_s": r[0], "cpu_s_per_image": r[1]} for r in full_runs]
    tables = [Table(f"{variant}, {args.size}x{args.size}, {spp} spp, {args.views} views x {args.frames} frames "
                    f"(median of {args.repeats}, run alternately)", ["render", "images/s", "CPU ms/image"],
                    [["bare Mitsuba loop", "bare_images_per_s", "bare_cpu_ms_per_image"],
                     ["full pipeline", "pipeline_images_per_s", "pipeline_cpu_ms_per_image"],
                     ["pipeline / bare (by wall time; by CPU time)", "ratio", "ratio_cpu"]])]  # fmt: skip
    if "memory" in result:
        tables.append(Table(f"memory over {args.memory_frames} frames, {args.memory_size}x{args.memory_size}, one view, "
                            "full pipeline", ["RSS", "MiB"],
                            [["before", "memory.rss_before_mb"], ["at 10 % of the frames", "memory.rss_at_10pct_mb"],
                             ["at the end", "memory.rss_end_mb"], ["growth from 10 % to the end", "memory.rss_growth_mb"],
                             ["max", "memory.rss_max_mb"]]))  # fmt: skip
    name = "render_cuda" if variant.startswith("cuda") else "render"
    params = {k: v for k, v in vars(args).items() if k not in ("out", "diagnose", "profile")}
    path = write_results(name, result, params=params, tables=tables, out=args.out,
                         goals=[Goal("ratio", ">=", GOAL_RATIO, "x", label="pipeline / bare loop, images/s by wall time")],
                         notes="The bare loop's scene is built for its run and released before the pipeline's, so one "
                               "Mitsuba scene is alive during each timed run. Building the scene is excluded from both.")  # fmt: skip
    print(f"wrote {path}")


if __name__ == "__main__":
    main()

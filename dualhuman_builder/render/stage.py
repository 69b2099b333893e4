"""Rendering a sequence to files, resumably, with or without a workspace.

:func:`render_sequence` renders an :class:`~dualhuman_builder.tracks.InteractionSequence` from a
list of cameras into a folder; :func:`run_render` is the ``render`` workspace stage of a take (it
needs the take's ``fit`` stage: ``bodies.npz``).

Output layout (one folder per render; the contact sheet, ``render/sheet.py``, reads it)::

    cameras.json                         save_cameras(): every camera's K, R, t (OpenCV,
                                         world-to-camera, metres), size, clip planes, plus
                                         "variant", "spp", "size" [w, h], "template"
    render.json                          variant (+ requested, fallback note), spp, template,
                                         frames [indices], views [names], seconds, cpu_seconds
                                         (all threads), images_per_s (this run), frames_rendered,
                                         frames_resumed, size
    views/<camera name>/rgb/<frame:05d>.png     8-bit sRGB
    views/<camera name>/depth/<frame:05d>.exr   channel "Z", float32 camera z (m), inf = nothing
    views/<camera name>/mask/<frame:05d>.png    8-bit, 0 background, 1 actor a, 2 actor b
    keypoints.npz                        joints (views, frames, 2, 22, 3) = u, v, visible;
                                         coco (views, frames, 2, 17, 3); frames (N,) int64;
                                         views (names); joint_names; coco_names
    visibility.json                      visible rates per actor x joint, per view (annotations)

``<frame>`` is the frame's index in the sequence (with ``every``/``max_frames`` only some
frames are rendered: ``frames`` lists them).

Pipeline: per frame the two meshes are moved once (``set_frame``), then each view is rendered
(RGB, then depth + mask) while a thread pool encodes the previous images (PNG, EXR); keypoints
and visibility are computed on the main thread. Bodies are evaluated in chunks of frames, so
memory stays flat however long the sequence.

Resume: a frame is complete when all its images are written; then a marker with its keypoints
is written to ``<out>/.progress/<frame:05d>.npz`` (atomically, after the images). A later call
with the same sequence, cameras, template and spp renders only the frames without a marker
(different settings start afresh; a finished render removes its markers unless asked to keep
them). A full disk (``ENOSPC``) stops with a :class:`RenderError` saying how many frames are
complete; re-running resumes. The workspace stage keeps its partial output in
``WS/scratch/render/<take>/<key>`` (the stage runner's staging folder is new on every run; ``key``
hashes the parameters and the fit result), hard-links the finished files into the stage's
staging folder, which the runner publishes in place of the previous render, and deletes the
scratch folder once the stage is recorded done.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from dualhuman_builder.fit.stage import BODIES, FIT, fitted_bodies, load_bodies
from dualhuman_builder.render.annotations import VISIBILITY_TOLERANCE_M, annotate_view, visibility_statistics
from dualhuman_builder.render.cameras import Camera, CameraError, load_cameras, ring_cameras, save_cameras
from dualhuman_builder.render.renderer import DEFAULT_SPP, RenderError, SequenceRenderer, body_model_uvs, linear_to_srgb8
from dualhuman_builder.render.template import load_template
from dualhuman_builder.workspace.runner import Stage

STAGE_VERSION = "1"
RENDER = Stage("render", per="take",
               artifacts=("cameras.json", "render.json", "keypoints.npz", "visibility.json", "views/{view}/rgb/{frame}.png",
                          "views/{view}/depth/{frame}.exr", "views/{view}/mask/{frame}.png"),
               reads=("fit",), command="dualhuman render {ws} --take {take}")  # fmt: skip
PROGRESS_DIR = ".progress"
#: Frames whose bodies are evaluated at once (memory: ~0.3 MB per frame and actor).
BODY_CHUNK = 32


# --------------------------------------------------------------------------------------------- files
def _atomic(path: Path, write: Callable[[Path], None], before_write=None) -> None:
    if before_write is not None:
        before_write(path)
    tmp = path.with_name(f".tmp-{path.name}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_rgb_png(path: Path, rgb_linear: np.ndarray, before_write=None) -> None:
    """8-bit sRGB PNG of linear RGB ``(H, W, 3)``."""
    from PIL import Image

    img = Image.fromarray(linear_to_srgb8(rgb_linear), "RGB")
    _atomic(Path(path), lambda p: img.save(p, format="PNG", compress_level=1), before_write)


def write_mask_png(path: Path, mask: np.ndarray, before_write=None) -> None:
    """8-bit grey PNG of an instance mask ``(H, W)`` (values 0, 1, 2)."""
    from PIL import Image

    img = Image.fromarray(np.ascontiguousarray(mask, dtype=np.uint8), "L")
    _atomic(Path(path), lambda p: img.save(p, format="PNG", compress_level=1), before_write)


def write_depth_exr(path: Path, depth: np.ndarray, before_write=None) -> None:
    """EXR with one float32 channel ``Z`` (camera z, metres; inf where nothing is hit)."""
    import OpenEXR

    z = np.ascontiguousarray(depth, dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    _atomic(Path(path), lambda p: OpenEXR.File(header, {"Z": z}).write(str(p)), before_write)


def read_depth_exr(path: str | Path) -> np.ndarray:
    """The ``Z`` channel ``(H, W)`` float32 of a depth EXR written by :func:`write_depth_exr`."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        return np.array(f.channels()["Z"].pixels, dtype=np.float32)


def _write_npz(path: Path, before_write=None, **arrays) -> None:
    def w(p):
        with open(p, "wb") as f:
            np.savez(f, **arrays)

    _atomic(path, w, before_write)


def _write_text(path: Path, text: str, before_write=None) -> None:
    _atomic(path, lambda p: p.write_text(text), before_write)


# --------------------------------------------------------------------------------------------- cameras
def ring_target(seq, frames: Sequence[int] | None = None, samples: int = 50) -> np.ndarray:
    """Where a ring looks: the pair's mean pelvis position (world metres) over up to ``samples``
    of ``frames``; its height is the mean pelvis height, between floor and chest."""
    idx = np.arange(seq.num_frames) if frames is None else np.asarray(frames, dtype=np.int64)
    if len(idx) == 0:
        raise RenderError("the sequence has no frames to frame a camera ring on")
    idx = idx[np.linspace(0, len(idx) - 1, min(samples, len(idx))).round().astype(int)]
    pelvis = np.concatenate([a.compute(frames=idx)["joints"][:, 0] for a in seq.actors])
    return pelvis.mean(axis=0)


def stage_cameras(seq, views: int = 8, size=512, radius_m: float = 3.0, height_m: float = 1.4, fov_deg: float = 50.0,
                  jitter_seed: int | None = None, rig_file=None, frames=None) -> list[Camera]:  # fmt: skip
    """The cameras of a render: those of ``rig_file`` when given (JSON, see
    :func:`.cameras.load_cameras`; entries without a size get ``size``), else a ring of ``views``
    around :func:`ring_target` of ``frames``."""
    w, h = (int(size), int(size)) if np.isscalar(size) else (int(size[0]), int(size[1]))
    if rig_file is not None:
        return load_cameras(rig_file, size=(w, h))
    if int(views) < 1:
        raise CameraError(f"a camera ring needs at least one view, got {views}")
    return ring_cameras(int(views), radius_m, height_m, fov_deg, target=ring_target(seq, frames), size=(w, h),
                        jitter_seed=jitter_seed)  # fmt: skip


# --------------------------------------------------------------------------------------------- rendering
def _sequence_digest(seq) -> str:
    h = hashlib.sha256()
    for a in seq.actors:
        for arr in (a.pose, a.transl, a.shape):
            h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()


def _frame_name(f: int) -> str:
    return f"{int(f):05d}"


def select_frames(num_frames: int, every: int = 1, max_frames: int | None = None) -> np.ndarray:
    """Frame indices rendered: ``0, every, 2 every, ...`` below ``num_frames``, at most ``max_frames``."""
    if int(every) < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    if max_frames is not None and int(max_frames) < 1:
        raise ValueError(f"max_frames must be >= 1 or None, got {max_frames}")
    idx = np.arange(0, int(num_frames), int(every), dtype=np.int64)
    return idx if max_frames is None else idx[: int(max_frames)]


def render_sequence(seq, out_dir: str | Path, cameras: Sequence[Camera], *, template="studio", spp: int = DEFAULT_SPP,
                    variant: str | None = None, every: int = 1, max_frames: int | None = None,
                    log: Callable[[str], None] = print, before_write: Callable[[Path], None] | None = None,
                    workers: int | None = None, keep_progress: bool = False,
                    tolerance_m: float = VISIBILITY_TOLERANCE_M) -> dict:  # fmt: skip
    """Render ``seq`` (an InteractionSequence) seen by ``cameras`` into ``out_dir`` (layout in the
    module docstring), resuming a previous partial render of the same settings there.

    ``every``/``max_frames``: frame stride and cap; ``before_write(path)``: called before every
    file is written (a quota check, or a test's simulated full disk: it may raise ``OSError``);
    ``workers``: encoder threads (default min(8, CPUs), at least 2); ``keep_progress``: keep the
    per-frame markers in ``out_dir/.progress``. Returns the ``render.json`` dict.
    """
    from dualhuman_builder.body.joints import COCO17, JOINT22_NAMES
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.tracks import InteractionSequence

    if not isinstance(seq, InteractionSequence):
        raise RenderError(f"render_sequence needs an InteractionSequence of two fitted bodies, got {type(seq).__name__}")
    if seq.num_frames == 0:
        raise RenderError("the sequence has no frames: there are no fitted bodies to render")
    frames = select_frames(seq.num_frames, every, max_frames)
    cameras = list(cameras)
    if not cameras:
        raise ValueError("render_sequence needs at least one camera")
    tpl = load_template(template)
    out = Path(out_dir)
    progress = out / PROGRESS_DIR
    progress.mkdir(parents=True, exist_ok=True)
    config = {"sequence": _sequence_digest(seq), "cameras": [c.as_dict() for c in cameras], "spp": int(spp),
              "template": tpl.raw, "tolerance_m": tolerance_m}  # fmt: skip
    key = hashlib.sha256(json.dumps(config, sort_keys=True, default=str).encode()).hexdigest()
    cfg_file = progress / "config.json"
    if cfg_file.is_file() and json.loads(cfg_file.read_text()).get("key") != key:
        log("render: settings changed since the partial render in this folder; starting afresh")
        shutil.rmtree(progress)
        progress.mkdir()
    if not cfg_file.is_file():
        try:
            _write_text(cfg_file, json.dumps({"key": key}), before_write)
        except OSError as e:
            _raise_disk_full(e, out, 0, len(frames))
    done = {int(p.stem) for p in progress.glob("[0-9]*.npz")}
    todo = [int(f) for f in frames if int(f) not in done]
    resumed = len(frames) - len(todo)
    if resumed:
        log(f"render: {resumed} of {len(frames)} frames already complete, rendering {len(todo)}")

    info_file = progress / "renderer.json"
    t0, c0 = time.perf_counter(), time.process_time()
    n_images = 0
    if todo:
        model = get_body_model()
        uvs = body_model_uvs(model)
        renderer = SequenceRenderer(model.faces, model.num_vertices, cameras, template=tpl, spp=spp, variant=variant,
                                    uv=uvs[0] if uvs else None, face_uv=uvs[1] if uvs else None, log=log)  # fmt: skip
        info = renderer.describe()
        log(f"render: {len(todo)} frames x {len(cameras)} views with {info['variant']} at {spp} spp, template {tpl.name}")
        try:
            _write_text(info_file, json.dumps(info), before_write)
            for c in cameras:
                for kind in ("rgb", "depth", "mask"):
                    (out / "views" / c.name / kind).mkdir(parents=True, exist_ok=True)
            t0, c0 = time.perf_counter(), time.process_time()
            n_images = _render_frames(renderer, seq, todo, out, progress, before_write, workers, log, tolerance_m)
        except OSError as e:
            complete = len({int(p.stem) for p in progress.glob("[0-9]*.npz")} & {int(f) for f in frames})
            _raise_disk_full(e, out, complete, len(frames))
    else:
        info = json.loads(info_file.read_text()) if info_file.is_file() else {"variant": None}
    seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - c0

    # ---- per-render files, from the frame markers
    joints = np.empty((len(cameras), len(frames), 2, len(JOINT22_NAMES), 3), np.float32)
    coco = np.empty((len(cameras), len(frames), 2, len(COCO17), 3), np.float32)
    for n, f in enumerate(frames):
        with np.load(progress / f"{_frame_name(f)}.npz") as z:
            joints[:, n], coco[:, n] = z["joints"], z["coco"]
    names = [c.name for c in cameras]
    try:
        _write_npz(out / "keypoints.npz", before_write, joints=joints, coco=coco, frames=frames, views=np.array(names),
                   joint_names=np.array(JOINT22_NAMES), coco_names=np.array(COCO17))  # fmt: skip
        stats = visibility_statistics(joints, coco, names, JOINT22_NAMES, COCO17,
                                      [a.actor or f"actor{k}" for k, a in enumerate(seq.actors)], tolerance_m)  # fmt: skip
        _write_text(out / "visibility.json", json.dumps(stats, indent=1), before_write)
        sizes = {(c.width, c.height) for c in cameras}
        size = list(next(iter(sizes))) if len(sizes) == 1 else None
        doc = {**{k: info.get(k) for k in ("variant", "variant_requested", "variant_note", "mitsuba", "uv_texture")},
               "spp": int(spp), "template": tpl.name, "size": size, "frames": frames.tolist(), "views": names,
               "seconds": round(seconds, 3), "cpu_seconds": round(cpu_seconds, 3),
               "images_per_s": round(n_images / seconds, 3) if n_images else None,
               "frames_rendered": len(todo), "frames_resumed": resumed, "images": n_images,
               "visible_rate": {"joints": stats["joints"]["overall"], "coco": stats["coco"]["overall"]}}  # fmt: skip
        save_path = out / "cameras.json"
        _atomic(save_path, lambda p: save_cameras(p, cameras, variant=doc["variant"], spp=int(spp), size=size,
                                                  template=tpl.name), before_write)  # fmt: skip
        _write_text(out / "render.json", json.dumps(doc, indent=1), before_write)
    except OSError as e:
        _raise_disk_full(e, out, len(frames), len(frames))
    if not keep_progress:
        shutil.rmtree(progress, ignore_errors=True)
    if n_images:
        log(f"render: {n_images} images in {seconds:.1f} s ({n_images / seconds:.2f} images/s, {doc['variant']})")
    return doc


def _raise_disk_full(e: OSError, out: Path, complete: int, total: int):
    """Re-raise a full disk as a RenderError saying what is kept; other OSErrors unchanged."""
    if e.errno != errno.ENOSPC:
        raise e
    raise RenderError(f"disk full while writing {e.filename or out}: {complete} of {total} frames are complete in {out}",
                      fix="free some space and run the render again: it resumes after the last complete frame") from e  # fmt: skip


def body_device(variant: str) -> str:
    """Where the body model runs during a render: ``"cuda"`` when Mitsuba renders on the GPU
    (``cuda_*`` variants) and torch sees one, else ``"cpu"``."""
    if not str(variant).startswith("cuda"):
        return "cpu"
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def _render_frames(renderer: SequenceRenderer, seq, todo: list[int], out: Path, progress: Path, before_write,
                   workers: int | None, log, tolerance_m: float) -> int:  # fmt: skip
    """Render ``todo`` frames; returns the number of images rendered. Raises the first write error."""
    cameras = renderer.cameras
    total = len(todo) * len(cameras)
    workers = workers or max(2, min(8, os.cpu_count() or 2))
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="render-encode")
    pending: deque = deque()
    n_images, next_report = 0, 0.1
    device = body_device(renderer.variant)
    t0 = time.perf_counter()

    def finish(item):
        f, futures, kj, kc = item
        for fut in futures:
            fut.result()  # re-raises a writer's exception (e.g. ENOSPC)
        _write_npz(progress / f"{_frame_name(f)}.npz", before_write, joints=kj, coco=kc)

    try:
        for start in range(0, len(todo), BODY_CHUNK):
            chunk = todo[start : start + BODY_CHUNK]
            bodies = [a.compute(frames=np.asarray(chunk), device=device) for a in seq.actors]
            for n, f in enumerate(chunk):
                renderer.set_frame(bodies[0]["vertices"][n], bodies[1]["vertices"][n])
                pj = np.stack([b["joints"][n] for b in bodies])
                pc = np.stack([b["coco"][n] for b in bodies])
                kj = np.empty((len(cameras), 2, pj.shape[1], 3), np.float32)
                kc = np.empty((len(cameras), 2, pc.shape[1], 3), np.float32)
                futures = []
                for i, cam in enumerate(cameras):
                    rgb = renderer.render_rgb(i, seed=f * len(cameras) + i)[..., :3]
                    depth, mask = renderer.render_depth_mask(i)
                    base = out / "views" / cam.name
                    name = _frame_name(f)
                    futures += [pool.submit(write_rgb_png, base / "rgb" / f"{name}.png", rgb, before_write),
                                pool.submit(write_depth_exr, base / "depth" / f"{name}.exr", depth, before_write),
                                pool.submit(write_mask_png, base / "mask" / f"{name}.png", mask, before_write)]  # fmt: skip
                    kj[i] = annotate_view(cam, pj, depth, mask, tolerance_m=tolerance_m)
                    kc[i] = annotate_view(cam, pc, depth, mask, tolerance_m=tolerance_m)
                    n_images += 1
                    if n_images >= next_report * total:
                        rate = n_images / (time.perf_counter() - t0)
                        log(f"render: {n_images}/{total} images ({100 * n_images / total:.0f} %), {rate:.2f} images/s")
                        next_report = (int(10 * n_images / total) + 1) / 10
                pending.append((f, futures, kj, kc))
                while len(pending) > 1:  # the previous frame's files are written while this one renders
                    finish(pending.popleft())
            del bodies
        while pending:
            finish(pending.popleft())
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return n_images


# --------------------------------------------------------------------------------------------- workspace stage
def _file_sha(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _link_tree(src: Path, out) -> None:
    """Hard-link (or copy, across file systems) every file under ``src`` except hidden ones into
    the stage output ``out``."""
    for p in sorted(src.rglob("*")):
        rel = p.relative_to(src)
        if not p.is_file() or any(part.startswith(".") for part in rel.parts):
            continue
        dest = out.path(rel.as_posix())
        try:
            os.link(p, dest)
        except OSError:
            shutil.copy2(p, dest)


def run_render(ws, take: str, views: int = 8, size=512, spp: int = DEFAULT_SPP, radius_m: float = 3.0,
               height_m: float = 1.4, fov_deg: float = 50.0, jitter_seed: int | None = None, rig_file=None,
               template: str = "studio", every: int = 1, max_frames: int | None = None, variant: str | None = None,
               force: bool = False, log: Callable[[str], None] = print,
               before_write: Callable[[Path], None] | None = None):  # fmt: skip
    """The ``render`` stage of ``take``: the fitted pair (fit stage's ``bodies.npz``) seen by a
    ring of ``views`` cameras (``radius_m`` around the pair, ``height_m`` above the floor,
    ``fov_deg`` horizontal, ``size`` pixels square or ``(w, h)``, jittered with ``jitter_seed``),
    or the cameras of ``rig_file`` instead. Artifacts follow :func:`render_sequence`'s layout.
    Resumable after a crash or a full disk (module docstring). Returns the StageResult."""
    fitted_bodies(ws, take)  # a clear error when the fit is not done
    rec = FIT.record(ws, take)
    tpl = load_template(template)
    size = [int(size), int(size)] if np.isscalar(size) else [int(size[0]), int(size[1])]
    params = {"views": int(views), "size": size, "spp": int(spp), "radius_m": float(radius_m), "height_m": float(height_m),
              "fov_deg": float(fov_deg), "jitter_seed": jitter_seed, "template": tpl.name,
              "template_sha256": hashlib.sha256(json.dumps(tpl.raw, sort_keys=True).encode()).hexdigest(),
              "rig_file": str(rig_file) if rig_file else None,
              "rig_sha256": _file_sha(rig_file) if rig_file and Path(rig_file).is_file() else None,
              "every": int(every), "max_frames": max_frames, "variant": variant}  # fmt: skip
    upstream = {"fit": rec["params_hash"], "bodies": rec["artifacts"][BODIES]["sha256"]}
    key = hashlib.sha256(json.dumps([params, upstream], sort_keys=True, default=str).encode()).hexdigest()[:16]
    scratch_root = ws.root / "scratch" / "render" / take
    scratch = scratch_root / key
    if scratch_root.is_dir():  # partial renders of other settings cannot be resumed: drop them
        for old in scratch_root.iterdir():
            if old.name != key:
                shutil.rmtree(old, ignore_errors=True)

    def compute(out):
        seq = load_bodies(ws, take)
        if seq.num_frames == 0:
            raise RenderError(f"the fit result of take {take!r} has no frames: there are no fitted bodies to render")
        frames = select_frames(seq.num_frames, every, max_frames)
        cams = stage_cameras(seq, views, size, radius_m, height_m, fov_deg, jitter_seed, rig_file, frames)
        summary = render_sequence(seq, scratch, cams, template=tpl, spp=spp, variant=variant, every=every,
                                  max_frames=max_frames, log=log, before_write=before_write, keep_progress=True)  # fmt: skip
        _link_tree(scratch, out)
        return {k: summary[k] for k in ("variant", "spp", "template", "size", "views", "seconds", "images_per_s",
                                        "frames_rendered", "frames_resumed", "visible_rate")} | {"frames": len(summary["frames"])}  # fmt: skip

    res = ws.run_stage(RENDER, compute, take=take, params=params, depends_on=[("fit", None)], version=STAGE_VERSION,
                       force=force)  # fmt: skip
    shutil.rmtree(scratch, ignore_errors=True)
    if scratch_root.is_dir() and not any(scratch_root.iterdir()):
        scratch_root.rmdir()
    return res


__all__ = ["PROGRESS_DIR", "body_device", "read_depth_exr", "render_sequence", "ring_target", "run_render", "select_frames",
           "stage_cameras", "write_depth_exr", "write_mask_png", "write_rgb_png"]

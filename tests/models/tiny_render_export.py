"""A real, tiny rendered dataset export for the image-model tests: the pairs of :mod:`tiny_export`
rendered by the toolkit's own Mitsuba render stage (a jittered camera ring, a few pixels wide, a few
samples per pixel) and written by the toolkit's export writer, so that the image dataset, the
estimator and `export verify` see exactly the layout a fitted export with renders has: ``cameras.json``,
``renders/views/<cam>/{rgb,depth,mask}/``, ``renders/keypoints.npz`` and ``renders/targets.npz``.

The last sequence is in the test split, the others in train. Built once per process per arguments
(about 3 s per sequence on one CPU core) under a temporary folder, and copied for every caller. From
a test outside ``tests/models``: ``sys.path.insert(0, str(Path(__file__).parents[1] / "models"))``
and ``from tiny_render_export import make_tiny_render_export`` (one module, so one build).
"""

from __future__ import annotations

import atexit
import shutil
import sys
import tempfile
from pathlib import Path

if str(Path(__file__).parent) not in sys.path:  # importable from any test folder, as one module
    sys.path.insert(0, str(Path(__file__).parent))

FPS = 20.0
_CACHE: dict[tuple, Path] = {}
_TMP: list[Path] = []


def _tmp() -> Path:
    if not _TMP:
        _TMP.append(Path(tempfile.mkdtemp(prefix="tiny-render-export-")))
        atexit.register(shutil.rmtree, _TMP[0], True)
    return _TMP[0]


def build_tiny_render_export(n_sequences: int = 2, frames: int = 12, views: int = 2, size: int = 48, every: int = 3,
                             spp: int = 2, seed: int = 0) -> Path:  # fmt: skip
    """The cached export folder itself (do not modify it: :func:`make_tiny_render_export` gives a copy)."""
    key = (int(n_sequences), int(frames), int(views), int(size), int(every), int(spp), int(seed))
    if key in _CACHE:
        return _CACHE[key]
    from tiny_export import _sequence

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.export.writer import export_dataset
    from dualhuman_builder.render.stage import render_sequence, select_frames, stage_cameras

    model = get_body_model()
    base = _tmp() / "-".join(map(str, key))
    items = []
    for k in range(key[0]):
        it = _sequence(model, key[1], k, key[6])
        frames_idx = select_frames(it.sequence.num_frames, key[4])
        cams = stage_cameras(it.sequence, views=key[2], size=key[3], frames=frames_idx, jitter_seed=key[6] * 100 + k)
        render_dir = base / "renders" / it.seq_id
        render_sequence(it.sequence, render_dir, cams, spp=key[5], every=key[4], log=lambda _m: None)
        it.render_dir = render_dir
        items.append(it)
    splits = {it.seq_id: ("test" if k == len(items) - 1 and len(items) > 1 else "train") for k, it in enumerate(items)}
    out = base / "export"
    export_dataset(items, out, seed=key[6], splits=splits, expect=("motion", "text", "renders"))
    _CACHE[key] = out
    return out


def make_tiny_render_export(root: str | Path, n_sequences: int = 2, frames: int = 12, views: int = 2, size: int = 48,
                            every: int = 3, spp: int = 2, seed: int = 0) -> Path:  # fmt: skip
    """A copy, under ``root/tiny-render-export``, of a real export of ``n_sequences`` two-person
    sequences of ``frames`` frames at 20 fps, each rendered from ``views`` ring cameras at ``size``
    x ``size`` pixels on every ``every``-th frame (default: 2 sequences, 4 rendered frames, 2 views,
    48 px; one in train, the last in test). `dualhuman export verify` accepts it."""
    src = build_tiny_render_export(n_sequences, frames, views, size, every, spp, seed)
    dest = Path(root) / "tiny-render-export"
    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(src, dest)
    return dest

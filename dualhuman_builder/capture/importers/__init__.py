"""Importers of recorded files: ``.mvnx`` (Xsens MVN XML export, :mod:`.mvnx`) and ``.bvh``
(:mod:`.bvh`), each read into a :class:`~dualhuman_builder.tracks.SkeletonTrack` in our
conventions; :func:`import_file` makes a workspace take of one (``dualhuman import WS FILE``).

A take made by :func:`import_file` holds, under ``WS/takes/<take>/``:

* the file itself, copied byte for byte;
* ``skeleton.npz`` — the :class:`SkeletonTrack` (versioned container, :mod:`dualhuman_builder.fileio`);
* for MVNX, ``mvnx_extras.npz`` (kind ``MvnxExtras``, version 1) — the other per-frame arrays as
  ``frame.<element>``, ``frame_index`` and ``epoch_ms``, each calibration pose as
  ``calibration.<type>.orientations`` / ``.positions``, and in its metadata the subject
  attributes, segments with their points, sensors, joints, ergonomic joints and foot contacts.

All three are registered with the take (SHA-256, sizes), with sample counts and metadata (source
format, fps, segment count, subject label, calibration poses, the host-clock note).
"""

from __future__ import annotations

import datetime as _dt
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from dualhuman_builder.capture.importers.bvh import read_bvh
from dualhuman_builder.capture.importers.mvnx import MvnxFile, read_mvnx
from dualhuman_builder.errors import FormatError, WorkspaceError
from dualhuman_builder.fileio import atomic_path, save_npz
from dualhuman_builder.tracks import SkeletonTrack

__all__ = ["FORMATS", "ImportResult", "MvnxFile", "import_file", "read_bvh", "read_mvnx", "safe_take_name"]

#: File suffix -> format name.
FORMATS = {".mvnx": "mvnx", ".bvh": "bvh"}
MVNX_EXTRAS_VERSION = 1


@dataclass(frozen=True)
class ImportResult:
    """What :func:`import_file` made: the ``take`` name, the ``source`` copy, ``track_path``
    (``skeleton.npz``), ``extras_path`` (``mvnx_extras.npz`` or None), the ``track``, the
    ``calibration_poses`` found, the ``subject`` label, the extra per-frame ``arrays``, ``notes``
    (units chosen, clocks) and the catalog's ``record`` of the take."""

    take: str
    format: str
    source: Path
    track_path: Path
    extras_path: Path | None
    track: SkeletonTrack
    calibration_poses: tuple[str, ...]
    subject: str
    arrays: tuple[str, ...]
    notes: tuple[str, ...]
    record: Any

    @property
    def frames(self) -> int:
        return self.track.num_frames

    @property
    def fps(self) -> float:
        return self.track.fps

    @property
    def segments(self) -> int:
        return len(self.track.segment_names)

    @property
    def duration_s(self) -> float:
        return _duration(self.track)


def safe_take_name(stem: str) -> str:
    """A take name from a file stem: characters other than letters, digits, ``-``, ``.`` and
    ``_`` become ``_``; no leading ``.``/``_``; at most 128 characters; ``import`` if nothing is left."""
    name = re.sub(r"[^A-Za-z0-9._-]+", "_", stem).lstrip("._")[:128]
    return name or "import"


def _duration(track: SkeletonTrack) -> float:
    if track.num_frames == 0:
        return 0.0
    if track.fps > 0:
        return track.num_frames / track.fps
    return float(track.device_time_ns[-1] - track.device_time_ns[0]) / 1e9


def _mvnx_extras(mf: MvnxFile) -> tuple[dict, dict]:
    arrays = {f"frame.{k}": v for k, v in mf.arrays.items()}
    arrays["frame_index"] = mf.frame_index
    arrays["epoch_ms"] = mf.epoch_ms
    for kind, pose in mf.calibration.items():
        arrays[f"calibration.{kind}.orientations"] = pose.orientations
        arrays[f"calibration.{kind}.positions"] = pose.positions
    meta = {"subject": mf.subject, "mvnx_version": mf.version, "mvn_version": mf.mvn_version, "mvn_build": mf.mvn_build,
            "comment": mf.comment,
            "segments": [{"label": s.label, "id": s.id, "points": {k: v.tolist() for k, v in s.points.items()}}
                         for s in mf.segments],
            "sensors": list(mf.sensors), "joints": [[j.label, j.connector1, j.connector2] for j in mf.joints],
            "ergonomic_joints": list(mf.ergonomic_joints), "foot_contacts": list(mf.foot_contacts),
            "calibration_poses": list(mf.calibration)}  # fmt: skip
    return arrays, meta


def import_file(ws, path: str | Path, *, take: str | None = None, actor: str | None = None, scale: float | None = None,
                up: str = "y", progress: Callable[[str], None] | None = None) -> ImportResult:  # fmt: skip
    """Import ``path`` (``.mvnx`` or ``.bvh``) into workspace ``ws`` as take ``take`` (default: the
    file stem made safe, :func:`safe_take_name`) with ``actor`` (a registered actor) in slot 0.

    ``scale`` / ``up`` apply to BVH (see :func:`~.bvh.read_bvh`). The file is read completely
    before anything is written; a bad file raises :class:`FormatError` and leaves the workspace
    unchanged, as does an existing take name or an unknown actor (:class:`WorkspaceError`).
    ``progress(message)`` is called while reading.
    """
    path = Path(path)
    if not path.is_file():
        raise FormatError("no such file", path=path, fix="check the path")
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise FormatError(f"unknown file type {path.suffix!r}", path=path,
                          fix=f"import one of: {', '.join(FORMATS)} (Xsens MVN XML export, Biovision BVH)")  # fmt: skip
    name = take or safe_take_name(path.stem)
    folder = ws.take_dir(name)  # checks the name
    if name in ws.takes():
        raise WorkspaceError(f"take {name!r} already exists", path=ws.root, fix="choose another name with --take NAME")
    if actor is not None:
        ws.actor(actor)  # raises if unknown

    notes: list[str] = []
    extras = None
    start_time = None
    meta: dict[str, Any] = {"source_format": fmt, "source_file": path.name}
    if fmt == "mvnx":
        cb = None
        if progress is not None:
            def cb(frames: int, done: int, total: int) -> None:
                progress(f"reading {path.name}: {done / max(total, 1):.0%} ({frames:,} frames)")
        mf = read_mvnx(path, progress=cb)
        track = mf.track
        calibration, subject = tuple(mf.calibration), mf.label
        arrays = tuple(mf.arrays)
        extras = _mvnx_extras(mf)
        if mf.num_frames and mf.epoch_ms[0] > 0:
            try:
                start_time = _dt.datetime.fromtimestamp(int(mf.epoch_ms[0]) / 1000.0, _dt.timezone.utc).isoformat()
            except (ValueError, OverflowError, OSError):  # a wall clock beyond the calendar: no start time
                notes.append(f"the first frame's wall clock (ms={int(mf.epoch_ms[0])}) is not a date; no start time")
        meta.update({"mvn_version": mf.mvn_version, "rec_date": mf.subject.get("recDate", "")})
        notes.append(track.meta["host_time"])
    else:
        if progress is not None:
            progress(f"reading {path.name}")
        track = read_bvh(path, scale=scale, up=up)
        calibration, subject, arrays = (), "", ()
        meta.update({"units": track.meta["units"], "scale": track.meta["scale"], "up": up})
        notes += [track.meta["scale_note"], track.meta["host_time"]]
    if track.meta.get("invalid_orientations") or track.meta.get("invalid_positions"):
        notes.append(f"{track.meta['invalid_orientations']} orientations and {track.meta['invalid_positions']} "
                     "positions were not valid and are marked invalid")  # fmt: skip
    track.actor = actor or ""
    meta.update({"fps": track.fps, "segment_count": len(track.segment_names), "subject_label": subject,
                 "calibration_poses": list(calibration), "arrays": list(arrays), "notes": notes})  # fmt: skip

    written: list[Path] = []
    existed = folder.exists()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        source = folder / path.name
        if source.resolve() != path.resolve():
            with atomic_path(source) as tmp:
                shutil.copyfile(path, tmp)
            written.append(source)
        track_path = track.save(folder / "skeleton.npz")
        written.append(track_path)
        extras_path = None
        if extras is not None:
            extras_path = save_npz(folder / "mvnx_extras.npz", "MvnxExtras", MVNX_EXTRAS_VERSION, *extras)
            written.append(extras_path)
        counts = {"skeleton": track.num_frames}
        if fmt == "mvnx":
            counts["calibration"] = len(calibration)
        files = [source, track_path] + ([extras_path] if extras_path is not None else [])
        record = ws.add_take(name, actors=[actor] if actor else [], files=files, start_time=start_time,
                             duration_s=_duration(track), sample_counts=counts, meta=meta)  # fmt: skip
    except BaseException:
        for p in written:
            p.unlink(missing_ok=True)
        if not existed and folder.exists() and not any(folder.iterdir()):
            folder.rmdir()
        raise
    return ImportResult(take=name, format=fmt, source=source, track_path=track_path, extras_path=extras_path,
                        track=track, calibration_poses=calibration, subject=subject, arrays=arrays,
                        notes=tuple(notes), record=record)  # fmt: skip

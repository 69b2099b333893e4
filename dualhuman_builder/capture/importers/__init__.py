"""Importers of recorded files: ``.mvnx`` (Xsens MVN XML export, :mod:`.mvnx`) and ``.bvh``
(:mod:`.bvh`), each read into a :class:`~dualhuman_builder.tracks.SkeletonTrack` in our
conventions; :func:`import_file` makes a workspace take of one (``dualhuman import WS FILE``),
:func:`import_files` one take of several MVNX files, one per actor (MVN exports one subject per file).

A take made by :func:`import_file` holds, under ``WS/takes/<take>/``:

* the file itself, copied byte for byte;
* ``skeleton.npz`` — the :class:`SkeletonTrack` (versioned container, :mod:`dualhuman_builder.fileio`);
* for MVNX, ``mvnx_extras.npz`` (kind ``MvnxExtras``, version 1) — the other per-frame arrays as
  ``frame.<element>``, ``frame_index`` and ``epoch_ms``, each calibration pose as
  ``calibration.<type>.orientations`` / ``.positions``, and in its metadata the subject
  attributes, segments with their points, sensors, joints, ergonomic joints and foot contacts.

All three are registered with the take (SHA-256, sizes), with sample counts and metadata (source
format, fps, segment count, subject label, calibration poses, the host-clock note). An MVNX take's
metadata also lists its ``suits`` (skeleton file, actor, subject label, MVN suit configuration), which
the sync stage reads as suit streams (:func:`dualhuman_builder.sync.stage.imported_suits`), and its
``flags``: ``no trackers`` (a file holds the suit alone), ``upper body`` (MVN recorded without leg
sensors: its legs are a fixed pose), ``unmeasured segments``, ``unknown configuration``
(:func:`suit_flags`); the sync and fit reports carry them on.
"""

from __future__ import annotations

import datetime as _dt
import re
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from dualhuman_builder.capture.importers.bvh import read_bvh
from dualhuman_builder.capture.importers.mvnx import LEG_SEGMENTS, MvnxFile, read_mvnx, unmeasured_segments
from dualhuman_builder.errors import FormatError, WorkspaceError
from dualhuman_builder.fileio import atomic_path, save_npz
from dualhuman_builder.tracks import SkeletonTrack

__all__ = ["FLAG_NO_TRACKERS", "FLAG_UNKNOWN_CONFIGURATION", "FLAG_UNMEASURED", "FLAG_UPPER_BODY", "FORMATS",
           "ImportResult", "MvnxFile", "flag_notes", "import_file", "import_files", "read_bvh", "read_mvnx",
           "safe_take_name", "suit_flags"]

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


#: Flags of an imported take (its catalog ``meta["flags"]``, carried into the sync and fit reports): the file
#: holds the suit alone, so nothing drift-free holds its positions ...
FLAG_NO_TRACKERS = "no trackers"
#: ... MVN recorded without leg sensors (its legs are a fixed pose, not the actor's) ...
FLAG_UPPER_BODY = "upper body"
#: ... other segments no sensor measured (:data:`~.mvnx.CONFIGURATIONS`) ...
FLAG_UNMEASURED = "unmeasured segments"
#: ... or a configuration this toolkit does not know (read as a full body).
FLAG_UNKNOWN_CONFIGURATION = "unknown configuration"


def suit_flags(configuration: str) -> dict[str, Any]:
    """The catalog metadata of an MVNX take recorded in suit ``configuration``: ``suit_configuration``,
    ``unmeasured_segments`` (:func:`~.mvnx.unmeasured_segments`; empty for a full body or an unknown
    configuration) and ``flags`` (:data:`FLAG_NO_TRACKERS` always, then :data:`FLAG_UPPER_BODY`,
    :data:`FLAG_UNMEASURED` or :data:`FLAG_UNKNOWN_CONFIGURATION` as they apply)."""
    segments = unmeasured_segments(configuration)
    flags = [FLAG_NO_TRACKERS]
    if segments is None:
        flags.append(FLAG_UNKNOWN_CONFIGURATION)
    elif set(LEG_SEGMENTS) <= set(segments) and not set(segments) & {"T8", "Head"}:  # legs only, torso measured
        flags.append(FLAG_UPPER_BODY)
    elif segments:
        flags.append(FLAG_UNMEASURED)
    return {"suit_configuration": configuration, "unmeasured_segments": list(segments or ()), "flags": flags}


def flag_notes(meta: dict) -> list[str]:
    """One sentence per flag of an imported take's metadata (:func:`suit_flags`), for people."""
    out = []
    for flag in meta.get("flags", ()):
        if flag == FLAG_NO_TRACKERS:
            out.append("no trackers: the file holds the suit alone; the fit uses the suit's own positions, drift included")
        elif flag == FLAG_UPPER_BODY:
            out.append(f"upper body: recorded in MVN's {meta.get('suit_configuration')!r} configuration, without leg "
                       "sensors; the legs are MVN's fixed pose, not the actor's, and not to be trusted (weight 0 in "
                       "the fit's input)")  # fmt: skip
        elif flag == FLAG_UNMEASURED:
            out.append(f"unmeasured segments: no sensor measured {', '.join(meta.get('unmeasured_segments', ()))} in "
                       f"MVN's {meta.get('suit_configuration')!r} configuration; not to be trusted (weight 0 in the "
                       "fit's input)")  # fmt: skip
        elif flag == FLAG_UNKNOWN_CONFIGURATION and not meta.get("suit_configuration"):
            out.append("unknown configuration: the file names no suit configuration; read as a full body")
        elif flag == FLAG_UNKNOWN_CONFIGURATION:
            out.append(f"unknown configuration: suit configuration {meta.get('suit_configuration')!r} is not one "
                       "MVN names; read as a full body")  # fmt: skip
    return out


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
    ``progress(message)`` is called while reading. An MVNX take's catalog metadata holds its
    ``suits`` (what sync reads), ``suit_configuration``, ``unmeasured_segments`` and ``flags``
    (:func:`suit_flags`).
    """
    return import_files(ws, [path], take=take, actors=[actor], scale=scale, up=up, progress=progress)[0]


def import_files(ws, paths: Sequence[str | Path], *, take: str | None = None, actors: Sequence[str | None] = (),
                 scale: float | None = None, up: str = "y",
                 progress: Callable[[str], None] | None = None) -> list[ImportResult]:  # fmt: skip
    """Import the files of one recording into workspace ``ws`` as one take: one ``.mvnx`` or ``.bvh``
    file (:func:`import_file`), or several ``.mvnx`` files, one per actor (MVN exports one subject per
    file), whose suits the take holds in order, ``actors[i]`` (registered actors, or None) wearing the
    suit of ``paths[i]``. Returns one :class:`ImportResult` per file, all of the one take.

    A take of several files keeps each file's skeleton and extras as ``skeleton.<i>.npz`` and
    ``mvnx_extras.<i>.npz`` (one file: ``skeleton.npz``, ``mvnx_extras.npz``); its metadata is the first
    file's, with every file in ``suits`` and the ``flags`` of all. Every file is read before anything is
    written; a bad one raises :class:`FormatError` and leaves the workspace unchanged."""
    paths = [Path(p) for p in paths]
    if not paths:
        raise FormatError("no file to import", fix="name the file(s) to import")
    if len(actors) > len(paths):
        raise WorkspaceError(f"{len(actors)} actors for {len(paths)} files", fix="name one actor per file, in order")
    actors = list(actors) + [None] * (len(paths) - len(actors))
    named = [a for a in actors if a]
    if len(set(named)) != len(named):
        raise WorkspaceError(f"an actor wears two suits: {named}", fix="name each actor once")
    fmts = []
    for path in paths:
        if not path.is_file():
            raise FormatError("no such file", path=path, fix="check the path")
        fmt = FORMATS.get(path.suffix.lower())
        if fmt is None:
            raise FormatError(f"unknown file type {path.suffix!r}", path=path,
                              fix=f"import one of: {', '.join(FORMATS)} (Xsens MVN XML export, Biovision BVH)")  # fmt: skip
        fmts.append(fmt)
    many = len(paths) > 1
    if many and set(fmts) != {"mvnx"}:
        raise FormatError("only MVNX files make one take together (one per actor)", path=paths[fmts.index("bvh")],
                          fix="import a BVH file on its own")  # fmt: skip
    if many and len({p.name for p in paths}) != len(paths):
        raise FormatError("two files of one take have the same name", path=paths[0], fix="rename one of them")
    name = take or safe_take_name(paths[0].stem)
    folder = ws.take_dir(name)  # checks the name
    if name in ws.takes():
        raise WorkspaceError(f"take {name!r} already exists", path=ws.root, fix="choose another name with --take NAME")
    for a in named:
        ws.actor(a)  # raises if unknown

    reads = [_read(path, fmt, actor, scale, up, progress) for path, fmt, actor in zip(paths, fmts, actors)]
    meta = dict(reads[0].meta)
    if fmts[0] == "mvnx":  # what sync reads of the take: one suit per skeleton file
        meta["suits"] = [{"skeleton": _suffixed("skeleton.npz", i, many), "actor": actor or "", "file": r.path.name,
                          "subject_label": r.subject, "suit_configuration": r.meta["suit_configuration"],
                          "unmeasured_segments": r.meta["unmeasured_segments"], "flags": r.meta["flags"]}
                         for i, (r, actor) in enumerate(zip(reads, actors))]  # fmt: skip
        meta["flags"] = list(dict.fromkeys(f for r in reads for f in r.meta["flags"]))
        if many:
            meta["source_files"] = [p.name for p in paths]

    written: list[Path] = []
    existed = folder.exists()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        files, counts, parts = [], {}, []
        for i, r in enumerate(reads):
            source = folder / r.path.name
            if source.resolve() != r.path.resolve():
                with atomic_path(source) as tmp:
                    shutil.copyfile(r.path, tmp)
                written.append(source)
            track_path = r.track.save(folder / _suffixed("skeleton.npz", i, many))
            written.append(track_path)
            extras_path = None
            if r.extras is not None:
                extras_path = save_npz(folder / _suffixed("mvnx_extras.npz", i, many), "MvnxExtras", MVNX_EXTRAS_VERSION,
                                       *r.extras)  # fmt: skip
                written.append(extras_path)
            counts[_suffixed("skeleton", i, many)] = r.track.num_frames
            if r.fmt == "mvnx":
                counts[_suffixed("calibration", i, many)] = len(r.calibration)
            files += [source, track_path] + ([extras_path] if extras_path is not None else [])
            parts.append((source, track_path, extras_path))
        record = ws.add_take(name, actors=named, files=files, start_time=reads[0].start_time,
                             duration_s=max(_duration(r.track) for r in reads), sample_counts=counts, meta=meta)  # fmt: skip
    except BaseException:
        for p in written:
            p.unlink(missing_ok=True)
        if not existed and folder.exists() and not any(folder.iterdir()):
            folder.rmdir()
        raise
    return [ImportResult(take=name, format=r.fmt, source=source, track_path=track_path, extras_path=extras_path,
                         track=r.track, calibration_poses=r.calibration, subject=r.subject, arrays=r.arrays,
                         notes=tuple(r.notes), record=record)
            for r, (source, track_path, extras_path) in zip(reads, parts)]  # fmt: skip


def _suffixed(name: str, i: int, many: bool) -> str:
    """``skeleton.npz`` -> ``skeleton.<i>.npz`` (``skeleton`` -> ``skeleton.<i>``) for file ``i`` of a take of
    several; unchanged for one."""
    if not many:
        return name
    stem, dot, ext = name.partition(".")
    return f"{stem}.{i}{dot}{ext}"


@dataclass
class _Read:
    """One file read for :func:`import_files`: the track and what goes with it into the take."""

    path: Path
    fmt: str
    track: SkeletonTrack
    calibration: tuple[str, ...]
    subject: str
    arrays: tuple[str, ...]
    extras: tuple[dict, dict] | None
    start_time: str | None
    meta: dict
    notes: list[str]


def _read(path: Path, fmt: str, actor: str | None, scale: float | None, up: str,
          progress: Callable[[str], None] | None) -> _Read:  # fmt: skip
    """Read one file completely (nothing is written)."""
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
        meta.update({"mvn_version": mf.mvn_version, "rec_date": mf.subject.get("recDate", ""),
                     **suit_flags(mf.configuration)})  # fmt: skip
        notes.append(track.meta["host_time"])
        notes.extend(flag_notes(meta))
    else:
        if progress is not None:
            progress(f"reading {path.name}")
        track = read_bvh(path, scale=scale, up=up)
        calibration, subject, arrays = (), "", ()
        meta.update({"units": track.meta["units"], "scale": track.meta["scale"], "up": up, "flags": [FLAG_NO_TRACKERS]})
        notes += [track.meta["scale_note"], track.meta["host_time"]]
    if track.meta.get("invalid_orientations") or track.meta.get("invalid_positions"):
        notes.append(f"{track.meta['invalid_orientations']} orientations and {track.meta['invalid_positions']} "
                     "positions were not valid and are marked invalid")  # fmt: skip
    track.actor = actor or ""
    meta.update({"fps": track.fps, "segment_count": len(track.segment_names), "subject_label": subject,
                 "calibration_poses": list(calibration), "arrays": list(arrays), "notes": notes})  # fmt: skip
    return _Read(path, fmt, track, calibration, subject, arrays, extras, start_time, meta, notes)

"""The dataset export: a documented folder layout with a manifest and a schema (``dualhuman export``).

Layout
------

::

    OUT/
      manifest.json        written LAST: format, format_version, toolkit_version, body_model (name,
                           version, bone/phenotype names, vertex count), fps, units, axes, split
                           settings, counts, per sequence what it has (motion, contacts, text, cameras,
                           renders + views, keypoints) and its split, the sequences left out with the
                           reason (skipped) or exported without some stage (incomplete), and the
                           sha256 + size of every other file in the export
      schema.json          every array: file, name, shape (symbolic dims: T frames, J bones,
                           P phenotype values, V vertices, ...), dtype, units, meaning; the 269
                           motion-feature slices (export/features.py FEATURE_SCHEMA)
      README.md            this dataset card, generated from the manifest
      labels.json          the interaction vocabulary (export/vocabulary.toml + the project's own):
                           {version, size K, labels: [{index, name, description, one_sided, sources}]}
      splits/train.txt     sequence ids, one per line, sorted (seeded split, 3:1 by default;
      splits/test.txt        optionally subject-disjoint: no subject in both)
      stats/mean.npy       (269,) float32 feature mean over the train split, both persons
      stats/std.npy        (269,) float32 feature std, one value per feature group (feature_stats)
      sequences/<seq_id>/
        sequence.json      seq_id, subjects, roles, take, frame_range, frames, fps, has, meta, and the
                           sha256 of this folder's files (written last in the folder)
        motion.npz         per person p in {a, b}: p.pose (T, J, 3) float32 rotation vectors (rad),
                           p.transl (T, 3) float32 m, p.shape (P,) float32 anny phenotype in [0, 1],
                           p.joints (T, 22, 3) float32 m (HumanML3D joint order, world frame),
                           p.features (T-1, 269) float32 (export/features.py)
        contacts.npz       labels_packed (2, T, ceil(V/8)) uint8 (np.packbits of the (2, T, V) bool
                           labels along V, big bit order), num_vertices () int64 = V,
                           distances (2, T, V) float16 signed distance to the other body (m,
                           negative inside, NaN beyond the contact band, -inf deeper than it),
                           frame_contact (T,) bool
        contact_events.json  region-level events [{region_a, region_b, start, end (exclusive),
                           contact_frames, peak_vertices, min_distance_m (null: deeper than the
                           band), ...}]
        text.json          {"labels": [...], "multi_hot": [K ints 0/1 over labels.json], "symmetric":
                           true | false | null, "texts": [...], "roles": ["actor" | "reactor", the
                           other] for persons a, b | null, "annotations": [{annotator, annotated_at,
                           sequence}]}, UTF-8
        cameras.json       the render's cameras (OpenCV K, world-to-camera R | t, metres)
        renders/           the render folder (hard-linked when on the same filesystem):
                           render.json, keypoints.npz, visibility.json,
                           views/<cam>/rgb/<frame:05d>.png, views/<cam>/depth/<frame:05d>.exr,
                           views/<cam>/mask/<frame:05d>.png (0 background, 1 person a, 2 person b)

World frame: right-handed, +Y up, metres, floor y = 0; a body at identity faces +Z with its left
towards +X. Person ``a`` is actor 0 of the interaction, ``b`` actor 1. Loading never unpickles:
every ``.npz`` is read with ``allow_pickle=False`` (:func:`load_motion`, :func:`load_contacts`).

Writing is crash-safe and resumable: every file is written to a temporary name and renamed
(``os.replace``); a file whose bytes would not change is not rewritten (the ``.npz`` files are
byte-deterministic); a sequence whose ``sequence.json`` records the same inputs and whose files
still match their sha256 is skipped without recomputation; ``manifest.json`` comes last, so a
folder without it is an unfinished export that re-running completes. Sequences are validated
before anything is written: duplicate ids, ids that are not safe folder names and text that is
not valid UTF-8 are errors; a sequence without motion, or whose motion holds NaN, is skipped
with its reason in the manifest (an error with ``strict=True``).
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import re
import shutil
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from dualhuman_builder import __version__
from dualhuman_builder.export.features import FEATURE_DIM, FEATURE_SCHEMA, feature_stats, motion_features
from dualhuman_builder.labels import Vocabulary, load_vocabulary
from dualhuman_builder.fileio import atomic_open, remove_partials, sha256_file
from dualhuman_builder.tracks import InteractionSequence

FORMAT = "dualhuman-export"
FORMAT_VERSION = 1
PERSONS = ("a", "b")
STAGES = ("motion", "contacts", "text", "renders")
SEQ_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,127}$")
MANIFEST = "manifest.json"
SEQUENCE_JSON = "sequence.json"
LABELS_JSON = "labels.json"
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)
#: Folders the export owns: files in them that the manifest does not list are removed on export
#: and reported by verify.
OWN_FOLDERS = ("sequences", "splits", "stats")


# ============================================================================ input
@dataclass(eq=False)
class ExportItem:
    """One sequence to export.

    ``seq_id``: folder name, ``[A-Za-z0-9][A-Za-z0-9_-]*`` (no dots: WebDataset keys end at the
    first dot), at most 128 characters. ``sequence``: the fitted pair, or None when the fit stage
    is missing (the item is then skipped). ``subjects``: the two performers' names (default: the
    tracks' ``actor`` names); ``labels``, ``texts``: interaction labels and descriptions (default:
    the sequence's own), ``str`` or UTF-8 ``bytes``; labels must be in the export's vocabulary.
    ``roles``: optional two role names (``("actor", "reactor")`` or the reverse for a one-sided
    interaction); ``symmetric``: True / False / None (None: derived from the labels' vocabulary
    entries); ``annotations``: who annotated when (``[{annotator, annotated_at, sequence}]``).
    ``contacts``: None, or a dict (or a ``ContactResult``) with ``labels (2, T, V)`` bool,
    ``distances (2, T, V)`` float16 metres, ``frame_contact (T,)`` bool, ``events`` list of dicts.
    ``render_dir``: None or a render folder (``cameras.json``, ``keypoints.npz``,
    ``visibility.json``, ``views/<cam>/{rgb,depth,mask}/``); hidden files in it are not copied.
    ``meta``: JSON-serialisable extras stored in ``sequence.json``.
    """

    seq_id: str
    sequence: InteractionSequence | None
    subjects: tuple[str, str] | None = None
    labels: list[str] = field(default_factory=list)
    texts: list[str | bytes] = field(default_factory=list)
    roles: tuple[str, str] | None = None
    symmetric: bool | None = None
    annotations: list[dict[str, Any]] = field(default_factory=list)
    contacts: Mapping[str, Any] | Any | None = None
    render_dir: str | Path | None = None
    meta: dict[str, Any] = field(default_factory=dict)


@dataclass
class _Prepared:
    item: ExportItem
    subjects: tuple[str, str]
    labels: list[str]
    texts: list[str]
    roles: list[str] | None
    symmetric: bool | None
    multi_hot: list[int]
    contacts: dict[str, Any] | None
    render_files: list[tuple[str, Path]]  # (relative path in the sequence folder, source)
    problem: str | None  # reason to skip, found before computing anything


# ============================================================================ helpers
def check_seq_id(seq_id) -> str:
    """``seq_id`` if it is a safe folder and WebDataset key name, else ValueError."""
    if not isinstance(seq_id, str) or not SEQ_ID_RE.match(seq_id):
        raise ValueError(
            f"invalid seq_id {seq_id!r}: use 1-128 characters from A-Z a-z 0-9 _ - (starting with a letter or "
            "digit; no dots, slashes or spaces)"
        )
    return seq_id


def json_clean(obj, what: str = "value"):
    """``obj`` as plain JSON data: numpy scalars/arrays to Python, tuples to lists, Paths to str,
    non-finite floats to None. ValueError naming ``what`` for anything else."""
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, (int, np.integer)) and not isinstance(obj, np.bool_):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (float, np.floating)):
        val = float(obj)
        return val if math.isfinite(val) else None
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.ndarray):
        return json_clean(obj.tolist(), what)
    if isinstance(obj, Mapping):
        return {str(k): json_clean(v, f"{what}[{k!r}]") for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_clean(v, f"{what}[{i}]") for i, v in enumerate(obj)]
    raise ValueError(f"{what} holds a {type(obj).__name__}, which is not JSON-serialisable")


def json_bytes(obj) -> bytes:
    """Deterministic, strict (no NaN) UTF-8 JSON with a trailing newline."""
    return (json.dumps(obj, indent=1, ensure_ascii=False, allow_nan=False) + "\n").encode("utf-8")


def npz_bytes(arrays: Mapping[str, np.ndarray], compress: bool = True) -> bytes:
    """A ``.npz`` of ``arrays`` as bytes, deterministic (fixed zip timestamps), never pickled."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED) as zf:
        for name, a in arrays.items():
            a = np.asarray(a)  # write_array stores C order itself; 0-d arrays stay 0-d
            if a.dtype == object:
                raise ValueError(f"array {name!r} has dtype object, which cannot be saved without pickle")
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_TIME)
            info.compress_type = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, a, allow_pickle=False)
    return buf.getvalue()


def npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.asarray(a), allow_pickle=False)
    return buf.getvalue()


def read_npz(source: str | Path | bytes, keys: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """The arrays of a ``.npz`` file (or its bytes), read with ``allow_pickle=False``: all of them,
    or only ``keys`` (the others are not decompressed). ValueError when it is not a readable
    ``.npz``, holds object arrays, or lacks one of ``keys``."""
    where = "npz bytes" if isinstance(source, (bytes, bytearray)) else str(source)
    try:
        with np.load(io.BytesIO(source) if isinstance(source, (bytes, bytearray)) else source, allow_pickle=False) as z:
            return {name: z[name] for name in (z.files if keys is None else keys)}
    except Exception as e:  # noqa: BLE001 - untrusted bytes: zipfile, zlib, and numpy's header parser (SyntaxError, TokenError) all raise
        raise ValueError(f"{where}: not a readable .npz without pickled objects ({e})") from e


def load_motion(path: str | Path, keys: Iterable[str] | None = None) -> dict[str, np.ndarray]:
    """``motion.npz`` of a sequence: ``{"a.pose", "a.transl", "a.shape", "a.joints", "a.features", "b.*"}``
    (or only ``keys``, in their order)."""
    return read_npz(path, keys)


def load_contacts(path: str | Path) -> dict[str, np.ndarray]:
    """``contacts.npz`` with the labels unpacked: ``labels (2, T, V)`` bool, ``distances (2, T, V)``
    float16 m, ``frame_contact (T,)`` bool."""
    z = read_npz(path)
    try:
        labels = np.unpackbits(z["labels_packed"], axis=2, count=int(z["num_vertices"])).astype(bool)
        return {"labels": labels, "distances": z["distances"], "frame_contact": z["frame_contact"]}
    except KeyError as e:
        raise ValueError(f"{path}: contacts.npz lacks {e}") from None


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _file_matches(path: Path, size: int, sha: str) -> bool:
    try:
        return path.is_file() and path.stat().st_size == size and sha256_file(path) == sha
    except OSError:
        return False


def _put_bytes(path: Path, data: bytes) -> tuple[dict, bool]:
    """Write ``data`` to ``path`` atomically unless the file already holds exactly these bytes.
    Returns ``({"sha256", "bytes"}, written)``."""
    rec = {"sha256": _sha(data), "bytes": len(data)}
    if _file_matches(path, rec["bytes"], rec["sha256"]):
        return rec, False
    with atomic_open(path, "wb") as f:
        f.write(data)
    return rec, True


def _put_copy(src: Path, dest: Path) -> tuple[dict, bool]:
    """Hard-link (same filesystem) or copy ``src`` to ``dest`` atomically, unless ``dest`` already
    is ``src`` or holds the same bytes."""
    sha = sha256_file(src)
    rec = {"sha256": sha, "bytes": src.stat().st_size}
    if dest.is_file():
        try:
            if os.path.samefile(src, dest) or _file_matches(dest, rec["bytes"], sha):
                return rec, False
        except OSError:
            pass
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".{dest.name}.{os.getpid()}.link.partial")
    tmp.unlink(missing_ok=True)
    try:
        try:
            os.link(src, tmp)
        except OSError:  # another filesystem, or links not allowed: copy
            shutil.copyfile(src, tmp)
        os.replace(tmp, dest)
    finally:
        tmp.unlink(missing_ok=True)
    return rec, True


def _decode_texts(seq_id: str, values, what: str) -> list[str]:
    out = []
    for i, t in enumerate(values or ()):
        if isinstance(t, (bytes, bytearray)):
            try:
                t = bytes(t).decode("utf-8")
            except UnicodeDecodeError as e:
                raise ValueError(
                    f"sequence {seq_id!r}: {what}[{i}] is not valid UTF-8 ({e.reason} at byte {e.start}: "
                    f"{bytes(t)[max(0, e.start - 8) : e.start + 8]!r})"
                ) from None
        elif not isinstance(t, str):
            raise ValueError(f"sequence {seq_id!r}: {what}[{i}] must be str or UTF-8 bytes, got {type(t).__name__}")
        try:
            t.encode("utf-8")
        except UnicodeEncodeError as e:
            raise ValueError(
                f"sequence {seq_id!r}: {what}[{i}] is not valid UTF-8 text ({e.reason} at character {e.start}; "
                "undecodable bytes smuggled in as surrogates?)"
            ) from None
        out.append(t)
    return out


def _check_contacts(seq_id: str, contacts, T: int) -> dict[str, Any]:
    get = contacts.get if isinstance(contacts, Mapping) else lambda k, d=None: getattr(contacts, k, d)
    missing = [k for k in ("labels", "distances", "frame_contact") if get(k) is None]
    if missing:
        raise ValueError(f"sequence {seq_id!r}: contacts lack {missing} (need labels, distances, frame_contact, events)")
    labels = np.asarray(get("labels"))
    if labels.ndim != 3 or labels.shape[0] != 2 or labels.shape[1] != T:
        raise ValueError(f"sequence {seq_id!r}: contacts labels must have shape (2, {T}, V), got {labels.shape}")
    if labels.dtype != bool:
        if not np.isin(labels, (0, 1)).all():
            raise ValueError(f"sequence {seq_id!r}: contacts labels must be boolean, got values other than 0/1")
        labels = labels.astype(bool)
    distances = np.asarray(get("distances"))
    if distances.shape != labels.shape:
        raise ValueError(f"sequence {seq_id!r}: contacts distances have shape {distances.shape}, labels {labels.shape}")
    frame = np.asarray(get("frame_contact"))
    if frame.shape != (T,):
        raise ValueError(f"sequence {seq_id!r}: contacts frame_contact must have shape ({T},), got {frame.shape}")
    events = get("events", None) or []
    if not isinstance(events, (list, tuple)) or not all(isinstance(e, Mapping) for e in events):
        raise ValueError(f"sequence {seq_id!r}: contacts events must be a list of dicts")
    return {"labels": labels, "distances": distances.astype(np.float16), "frame_contact": frame.astype(bool),
            "events": json_clean(list(events), f"sequence {seq_id!r} contact events")}  # fmt: skip


def _render_files(seq_id: str, render_dir) -> list[tuple[str, Path]]:
    root = Path(render_dir)
    if not root.is_dir():
        raise ValueError(f"sequence {seq_id!r}: render_dir {root} is not a folder")
    files = []
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root)
        if any(part.startswith(".") for part in rel.parts) or not p.is_file():
            continue  # resume markers (.progress/), partial writes, folders
        name = rel.as_posix()
        files.append(("cameras.json" if name == "cameras.json" else f"renders/{name}", p))
    return files


def _prepare(item: ExportItem, vocabulary: Vocabulary) -> _Prepared:
    if not isinstance(item, ExportItem):
        raise ValueError(f"export items must be ExportItem, got {type(item).__name__}")
    sid = item.seq_id
    seq = item.sequence
    if seq is not None and not isinstance(seq, InteractionSequence):
        raise ValueError(f"sequence {sid!r}: sequence must be an InteractionSequence or None, got {type(seq).__name__}")
    subjects = item.subjects
    if subjects is None:
        subjects = tuple(a.actor for a in seq.actors) if seq is not None else ("", "")
    if isinstance(subjects, str) or len(subjects) != 2 or not all(isinstance(s, str) for s in subjects):
        raise ValueError(f"sequence {sid!r}: subjects must be two names, got {subjects!r}")
    labels = _decode_texts(sid, item.labels or (seq.labels if seq is not None else ()), "labels")
    texts = _decode_texts(sid, item.texts or (seq.text if seq is not None else ()), "texts")
    roles = None
    if item.roles is not None:
        roles = _decode_texts(sid, item.roles, "roles")
        if len(roles) != 2:
            raise ValueError(f"sequence {sid!r}: roles must name two roles, got {len(roles)}")
    try:
        labels = vocabulary.check(labels)
    except ValueError as e:
        raise ValueError(f"sequence {sid!r}: {e}") from None
    if item.symmetric is not None and not isinstance(item.symmetric, bool):
        raise ValueError(f"sequence {sid!r}: symmetric must be True, False or None, got {item.symmetric!r}")
    symmetric = item.symmetric if item.symmetric is not None else vocabulary.symmetric(labels)
    json_clean(item.annotations, f"sequence {sid!r} annotations")
    json_clean(item.meta, f"sequence {sid!r} meta")
    if seq is not None:
        json_clean(seq.meta, f"sequence {sid!r} sequence.meta")
    problem = None
    contacts = None
    if seq is None:
        problem = "no motion: the fit stage has not produced this sequence"
    else:
        if seq.num_frames < 2:
            problem = f"only {seq.num_frames} frame (motion features need at least 2)"
        for name, track in zip(PERSONS, seq.actors):
            for arr in ("pose", "transl", "shape"):
                a = np.asarray(getattr(track, arr))
                if problem is None and not np.isfinite(a).all():
                    bad = np.argwhere(~np.isfinite(a))[0]
                    problem = f"person {name} {arr} holds NaN or inf (first at index {tuple(int(i) for i in bad)})"
        if item.contacts is not None:
            contacts = _check_contacts(sid, item.contacts, seq.num_frames)
    files = _render_files(sid, item.render_dir) if item.render_dir is not None else []
    return _Prepared(item, (str(subjects[0]), str(subjects[1])), labels, texts, roles, symmetric,
                     vocabulary.multi_hot(labels).tolist(), contacts, files, problem)  # fmt: skip


def _fingerprint(p: _Prepared, fps: float) -> str:
    """Hash of everything a sequence folder is computed from (and the toolkit version)."""
    h = hashlib.sha256()

    def add(x):
        h.update(x if isinstance(x, bytes) else json.dumps(x, sort_keys=True, default=str).encode())
        h.update(b"\0")

    seq = p.item.sequence
    add([FORMAT_VERSION, __version__, fps, p.subjects, p.labels, p.multi_hot, p.symmetric, p.item.annotations, p.texts,
         p.roles, json_clean(p.item.meta),
         json_clean(seq.meta), seq.take, list(seq.frame_range)])  # fmt: skip
    for track in seq.actors:
        add([track.model, track.model_version, list(track.bone_names), list(track.shape_names)])
        for arr in (track.pose, track.transl, track.shape):
            add(np.ascontiguousarray(arr).tobytes())
    if p.contacts is not None:
        for k in ("labels", "distances", "frame_contact"):
            add(np.ascontiguousarray(p.contacts[k]).tobytes())
        add(p.contacts["events"])
    for rel, src in p.render_files:
        st = src.stat()
        add([rel, st.st_size, st.st_mtime_ns, st.st_ino])
    return h.hexdigest()


# ============================================================================ schema
def build_schema(body_model: Mapping[str, Any]) -> dict[str, Any]:
    """The machine-readable description of every array in the export (``schema.json``).

    ``dims``: sizes of the symbolic dimensions (``T`` is per sequence, in the manifest; ``T-1`` is
    the number of feature rows; ``C``/``R`` are a render's cameras and rendered frames).
    ``arrays``: ``{file, name, shape, dtype, units, meaning, stage}``; ``file`` holds ``{seq_id}``.
    """
    J, P, V = int(body_model["num_bones"]), int(body_model["num_shape_params"]), int(body_model["num_vertices"])
    motion = "sequences/{seq_id}/motion.npz"
    contacts = "sequences/{seq_id}/contacts.npz"
    keypoints = "sequences/{seq_id}/renders/keypoints.npz"
    arrays = []
    for p, who in zip(PERSONS, ("actor 0", "actor 1")):
        arrays += [
            {"file": motion, "name": f"{p}.pose", "shape": ["T", "J", 3], "dtype": "float32", "units": "rad",
             "meaning": f"{who}: per-frame rotation vector of each anny bone (anny local-ref parameterisation in "
                        "Y-up world-aligned axes; bone 0 = root = global orientation)", "stage": "motion"},
            {"file": motion, "name": f"{p}.transl", "shape": ["T", 3], "dtype": "float32", "units": "m",
             "meaning": f"{who}: world position of the root bone head (pelvis centre)", "stage": "motion"},
            {"file": motion, "name": f"{p}.shape", "shape": ["P"], "dtype": "float32", "units": "1",
             "meaning": f"{who}: anny phenotype values in [0, 1], order body_model.shape_names", "stage": "motion"},
            {"file": motion, "name": f"{p}.joints", "shape": ["T", 22, 3], "dtype": "float32", "units": "m",
             "meaning": f"{who}: the 22 HumanML3D joints (anny bone heads), world frame", "stage": "motion"},
            {"file": motion, "name": f"{p}.features", "shape": ["T-1", FEATURE_DIM], "dtype": "float32",
             "units": "see fields", "meaning": f"{who}: 269-dim motion features of {p}.joints (HumanML3D 263 + "
             "initial facing and translation); row t describes frame t and the step t -> t+1",
             "fields": FEATURE_SCHEMA, "stage": "motion"},
        ]  # fmt: skip
    arrays += [
        {"file": contacts, "name": "labels_packed", "shape": [2, "T", "V8"], "dtype": "uint8", "units": "bits",
         "meaning": "per-vertex contact labels (2, T, V) bool of actor 0 / actor 1, np.packbits along V (big bit "
                    "order); unpack with np.unpackbits(x, axis=2, count=num_vertices)", "stage": "contacts"},
        {"file": contacts, "name": "num_vertices", "shape": [], "dtype": "int64", "units": "1",
         "meaning": "V, the vertex count the labels were packed from", "stage": "contacts"},
        {"file": contacts, "name": "distances", "shape": [2, "T", "V"], "dtype": "float16", "units": "m",
         "meaning": "signed distance of each vertex to the other body (negative inside); NaN beyond the contact "
                    "band, -inf inside deeper than it", "stage": "contacts"},
        {"file": contacts, "name": "frame_contact", "shape": ["T"], "dtype": "bool", "units": "1",
         "meaning": "any vertex of either actor in contact on the frame", "stage": "contacts"},
        {"file": keypoints, "name": "joints", "shape": ["C", "R", 2, 22, 3], "dtype": "float32", "units": "px, px, 0/1",
         "meaning": "per camera, rendered frame and actor: the 22 joints projected (u, v) and visible flag",
         "stage": "keypoints"},
        {"file": keypoints, "name": "coco", "shape": ["C", "R", 2, 17, 3], "dtype": "float32", "units": "px, px, 0/1",
         "meaning": "the same for the 17 COCO keypoints regressed from the vertices", "stage": "keypoints"},
        {"file": keypoints, "name": "frames", "shape": ["R"], "dtype": "int64", "units": "frame",
         "meaning": "the sequence frame index of each rendered frame", "stage": "keypoints"},
        {"file": keypoints, "name": "views", "shape": ["C"], "dtype": "str", "units": "",
         "meaning": "camera names (views/<name>/ and cameras.json)", "stage": "keypoints"},
    ]  # fmt: skip
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "dims": {"J": J, "P": P, "V": V, "V8": (V + 7) // 8,
                 "T": "frames of the sequence (manifest sequences.<id>.frames)", "T-1": "feature rows: T - 1",
                 "C": "cameras of the render", "R": "rendered frames"},  # fmt: skip
        "arrays": arrays,
        "json": {
            "sequences/{seq_id}/text.json": {"labels": "list[str] (names in labels.json)", "multi_hot": "list[int] (K)",
                                             "symmetric": "bool | null", "texts": "list[str]",
                                             "roles": "[str, str] | null (person a's, person b's)",
                                             "annotations": "list of {annotator, annotated_at, sequence}"},
            "labels.json": "{version, size, labels: [{index, name, description, one_sided, sources}]}",
            "sequences/{seq_id}/contact_events.json": "list of {region_a, region_b, start, end (exclusive), "
            "contact_frames, peak_vertices, min_distance_m (null: deeper than the band), start_s, end_s}",
            "sequences/{seq_id}/cameras.json": "{convention, cameras: [{name, width, height, K, R, t, ...}], ...}",
        },
    }


# ============================================================================ splits
def make_splits(subjects: Mapping[str, tuple[str, str]], split_ratio: float = 0.75, subject_disjoint: bool = False,
                seed: int = 0) -> tuple[list[str], list[str]]:  # fmt: skip
    """Seeded train/test split of sequence ids; returns sorted ``(train, test)``.

    ``subjects``: seq_id -> its two subject names. About ``split_ratio`` of the sequences go to
    train (at least one to each side when there are two or more and ``split_ratio < 1``).
    ``subject_disjoint``: sequences are grouped by shared subjects (connected components) and whole
    groups are assigned, so no subject appears in both splits; ValueError when that is impossible
    (one group) or a sequence has an unnamed subject.
    """
    if not (isinstance(split_ratio, (int, float)) and 0.0 < float(split_ratio) <= 1.0):
        raise ValueError(f"split_ratio must be in (0, 1], got {split_ratio!r}")
    ids = sorted(subjects)
    n = len(ids)
    if n == 0:
        return [], []
    rng = np.random.default_rng(seed)
    if split_ratio >= 1.0:
        return ids, []
    target = min(max(round(split_ratio * n), 1), n - 1) if n >= 2 else n
    if not subject_disjoint:
        order = [ids[i] for i in rng.permutation(n)]
        return sorted(order[:target]), sorted(order[target:])
    unnamed = [s for s in ids if not all(subjects[s])]
    if unnamed:
        raise ValueError(f"subject-disjoint split needs both subjects named; sequences {unnamed[:5]} have an empty name")
    parent: dict[str, str] = {}

    def find(x):
        while parent.setdefault(x, x) != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for s in ids:
        a, b = subjects[s]
        parent[find(a)] = find(b)
    groups: dict[str, list[str]] = {}
    for s in ids:
        groups.setdefault(find(subjects[s][0]), []).append(s)
    comps = sorted(groups.values())
    if len(comps) < 2:
        names = sorted({x for s in ids for x in subjects[s]})
        raise ValueError(
            f"a subject-disjoint split is impossible: all {n} sequences are linked through shared subjects "
            f"{names[:10]} (need at least two groups of sequences with no subject in common)"
        )
    train: list[str] = []
    test: list[str] = []
    for i in rng.permutation(len(comps)):
        comp = comps[i]
        if abs(len(train) + len(comp) - target) < abs(len(train) - target) or not train:
            train += comp
        else:
            test += comp
    if not test:  # the first group took everything it could; move the smallest other group over
        comps_in = sorted((c for c in comps), key=len)
        for c in comps_in:
            if set(c) <= set(train) and len(c) < len(train):
                test = c
                train = [s for s in train if s not in set(c)]
                break
    return sorted(train), sorted(test)


# ============================================================================ export
def _body_model_info(seqs: list[InteractionSequence], num_vertices: int) -> dict[str, Any]:
    kinds = {(t.model, t.model_version, t.bone_names, t.shape_names) for s in seqs for t in s.actors}
    if len(kinds) > 1:
        raise ValueError(
            f"sequences use different body models/versions: {sorted({(k[0], k[1], len(k[2])) for k in kinds})}; "
            "export them separately"
        )
    model, version, bones, shapes = kinds.pop()
    return {"name": model, "version": version, "num_bones": len(bones), "num_shape_params": len(shapes),
            "num_vertices": int(num_vertices), "bone_names": list(bones), "shape_names": list(shapes)}  # fmt: skip


def _clean_folder(folder: Path, keep: set[str]) -> None:
    """Delete files under ``folder`` whose relative path is not in ``keep``, then empty folders."""
    for p in sorted(folder.rglob("*"), reverse=True):
        rel = p.relative_to(folder).as_posix()
        if p.is_file() or p.is_symlink():
            if rel not in keep:
                p.unlink()
        elif p.is_dir() and not any(p.iterdir()):
            p.rmdir()


def _sequence_done(folder: Path, fingerprint: str) -> dict | None:
    """The recorded ``sequence.json`` when it matches ``fingerprint`` and every file it lists is intact."""
    try:
        doc = json.loads((folder / SEQUENCE_JSON).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("fingerprint") != fingerprint or not isinstance(doc.get("files"), dict):
        return None
    for rel, rec in doc["files"].items():
        if not _file_matches(folder / rel, rec.get("bytes", -1), rec.get("sha256", "")):
            return None
    return doc


def _write_sequence(p: _Prepared, folder: Path, fps: float, fingerprint: str) -> tuple[dict, np.ndarray, np.ndarray, int]:
    """Compute and write one sequence folder. Returns ``(sequence.json doc, features a, features b,
    files rewritten)``; ValueError when the motion cannot be turned into features."""
    seq = p.item.sequence
    motion: dict[str, np.ndarray] = {}
    feats = []
    for name, track in zip(PERSONS, seq.actors):
        joints = np.asarray(track.joints(), dtype=np.float32)
        if not np.isfinite(joints).all():
            raise ValueError(f"person {name} joints hold NaN (frames {np.flatnonzero(~np.isfinite(joints).all(axis=(1, 2)))[:5].tolist()})")
        try:
            f = motion_features(joints, fps)
        except ValueError as e:
            raise ValueError(f"person {name} motion features: {e}") from None
        motion.update({f"{name}.pose": track.pose, f"{name}.transl": track.transl, f"{name}.shape": track.shape,
                       f"{name}.joints": joints, f"{name}.features": f})  # fmt: skip
        feats.append(f)
    payload: dict[str, bytes] = {"motion.npz": npz_bytes(motion)}
    if p.contacts is not None:
        c = p.contacts
        payload["contacts.npz"] = npz_bytes({
            "labels_packed": np.packbits(c["labels"], axis=2), "num_vertices": np.int64(c["labels"].shape[2]),
            "distances": c["distances"], "frame_contact": c["frame_contact"]})  # fmt: skip
        payload["contact_events.json"] = json_bytes(c["events"])
    payload["text.json"] = json_bytes({"labels": p.labels, "multi_hot": p.multi_hot, "symmetric": p.symmetric,
                                       "texts": p.texts, "roles": p.roles, "annotations": p.item.annotations})  # fmt: skip
    files: dict[str, dict] = {}
    written = 0
    for rel, data in payload.items():
        files[rel], w = _put_bytes(folder / rel, data)
        written += w
    for rel, src in p.render_files:
        files[rel], w = _put_copy(src, folder / rel)
        written += w
    doc = _sequence_doc(p, seq, fps, files, fingerprint)
    _clean_folder(folder, set(files) | {SEQUENCE_JSON})
    written += _put_bytes(folder / SEQUENCE_JSON, json_bytes(doc))[1]
    return doc, feats[0], feats[1], written


def _sequence_doc(p: _Prepared, seq: InteractionSequence, fps: float, files: dict, fingerprint: str) -> dict:
    views = sorted({rel.split("/")[2] for rel in files if rel.startswith("renders/views/") and rel.count("/") >= 3})
    has = {"motion": True, "contacts": p.contacts is not None, "text": bool(p.texts),
           "cameras": "cameras.json" in files, "renders": bool(views), "keypoints": "renders/keypoints.npz" in files}  # fmt: skip
    return {
        "seq_id": p.item.seq_id,
        "frames": seq.num_frames,
        "fps": fps,
        "subjects": list(p.subjects),
        "roles": p.roles,
        "take": seq.take,
        "frame_range": list(seq.frame_range),
        "has": has,
        "render_views": views,
        "num_texts": len(p.texts),
        "labels": p.labels,
        "symmetric": p.symmetric,
        "meta": json_clean({**seq.meta, **p.item.meta}),
        "fingerprint": fingerprint,
        "files": dict(sorted(files.items())),
    }


def _missing_stages(has: Mapping[str, bool], expect: Iterable[str]) -> list[str]:
    return [s for s in expect if not has.get(s, False)]


def export_dataset(
    items: Iterable[ExportItem],
    out_dir: str | Path,
    split_ratio: float = 0.75,
    subject_disjoint: bool = False,
    seed: int = 0,
    strict: bool = False,
    progress: Callable[[str], None] | None = None,
    expect: Iterable[str] = STAGES,
    vocabulary: Vocabulary | None = None,
) -> dict[str, Any]:
    """Export ``items`` into the folder layout of this module under ``out_dir``; returns the manifest.

    ``split_ratio``: share of sequences in train (0 < r <= 1); ``subject_disjoint``: no subject in
    both splits; ``seed``: the split's seed. ``expect``: stages every sequence should have (of
    ``motion``, ``contacts``, ``text``, ``renders``); a sequence lacking one is exported with what
    it has and listed under ``incomplete``. A sequence without motion or with NaN motion is left out
    and listed under ``skipped``. ``strict=True`` turns both into a ValueError. ``progress`` gets one
    line per sequence. ``vocabulary``: the interaction labels (default: the built-in one,
    :func:`~dualhuman_builder.labels.load_vocabulary`). Re-running completes a partial export and rewrites only what changed.
    Errors (ValueError): duplicate or unsafe ``seq_id``, text that is not UTF-8, a label outside the
    vocabulary, malformed contacts,
    a missing ``render_dir``, mixed fps or body models, an ``out_dir`` that is a non-empty folder
    but no export, nothing exportable.
    """
    say = progress or (lambda _msg: None)
    expect = tuple(expect)
    unknown = sorted(set(expect) - set(STAGES))
    if unknown:
        raise ValueError(f"expect names unknown stages {unknown}; choose from {list(STAGES)}")
    if not (isinstance(split_ratio, (int, float)) and 0.0 < float(split_ratio) <= 1.0):
        raise ValueError(f"split_ratio must be in (0, 1], got {split_ratio!r}")
    items = list(items)
    if not items:
        raise ValueError("nothing to export: no items given")
    ids = [check_seq_id(getattr(it, "seq_id", None)) for it in items]
    dup = sorted({s for s in ids if ids.count(s) > 1})
    if dup:
        raise ValueError(f"duplicate seq_id {dup}: every sequence needs its own id")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not ((out / MANIFEST).exists() or (out / "sequences").is_dir()):
        raise ValueError(f"{out} is a non-empty folder that is not a dataset export; choose an empty or new folder")

    vocabulary = vocabulary or load_vocabulary()
    prepared = [_prepare(it, vocabulary) for it in items]  # every input error surfaces before anything is written
    skipped: dict[str, str] = {p.item.seq_id: p.problem for p in prepared if p.problem}
    good = [p for p in prepared if not p.problem]
    fps_set = sorted({p.item.sequence.fps for p in good})
    if len(fps_set) > 1:
        by = {f: [p.item.seq_id for p in good if p.item.sequence.fps == f][:3] for f in fps_set}
        raise ValueError(f"sequences have different fps {by}; resample them to one rate before exporting")
    if strict:
        lacking = {p.item.seq_id: _missing_stages({"motion": True, "contacts": p.contacts is not None,
                   "text": bool(p.texts), "renders": any(r.startswith("renders/views/") for r, _ in p.render_files)},
                   expect) for p in good}  # fmt: skip
        lacking = {k: v for k, v in lacking.items() if v}
        if skipped or lacking:
            raise ValueError(f"strict export: sequences skipped {skipped}, incomplete {lacking}")
    if not good:
        raise ValueError(f"no sequence can be exported: {skipped}")
    fps = float(fps_set[0])

    from dualhuman_builder.body.model import get_body_model

    body = _body_model_info([p.item.sequence for p in good], get_body_model().num_vertices)
    for p in good:
        if p.contacts is not None and p.contacts["labels"].shape[2] != body["num_vertices"]:
            raise ValueError(f"sequence {p.item.seq_id!r}: contacts have {p.contacts['labels'].shape[2]} vertices, "
                             f"the body model {body['num_vertices']}")  # fmt: skip

    out.mkdir(parents=True, exist_ok=True)
    remove_partials(out)
    seq_root = out / "sequences"
    seq_root.mkdir(exist_ok=True)
    docs: dict[str, dict] = {}
    features: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    rewritten = 0
    for k, p in enumerate(good, 1):
        sid = p.item.seq_id
        folder = seq_root / sid
        fp = _fingerprint(p, fps)
        doc = _sequence_done(folder, fp)
        if doc is not None:
            m = load_motion(folder / "motion.npz")
            features[sid] = (m["a.features"], m["b.features"])
            _clean_folder(folder, set(doc["files"]) | {SEQUENCE_JSON})
            docs[sid] = doc
            say(f"[{k}/{len(good)}] {sid}: up to date")
            continue
        try:
            doc, fa, fb, n = _write_sequence(p, folder, fps, fp)
        except ValueError as e:
            if strict:
                raise ValueError(f"strict export: sequence {sid!r}: {e}") from e
            skipped[sid] = str(e)
            shutil.rmtree(folder, ignore_errors=True)
            say(f"[{k}/{len(good)}] {sid}: skipped ({e})")
            continue
        docs[sid], features[sid] = doc, (fa, fb)
        rewritten += n
        say(f"[{k}/{len(good)}] {sid}: {doc['frames']} frames, {n} files written")
    for stale in sorted(seq_root.iterdir()):
        if stale.name not in docs:
            if stale.is_dir() and not stale.is_symlink():
                shutil.rmtree(stale)
            else:
                stale.unlink()
    if not docs:
        raise ValueError(f"no sequence could be exported: {skipped}")

    subjects = {sid: tuple(d["subjects"]) for sid, d in docs.items()}
    train, test = make_splits(subjects, split_ratio, subject_disjoint, seed)
    if not train:
        raise ValueError("the train split is empty; nothing to compute feature statistics from")
    mean, std = feature_stats([f for sid in train for f in features[sid]])

    files: dict[str, dict] = {}

    def put(rel: str, data: bytes) -> None:
        nonlocal rewritten
        files[rel], w = _put_bytes(out / rel, data)
        rewritten += w

    put("splits/train.txt", "".join(f"{s}\n" for s in train).encode())
    put("splits/test.txt", "".join(f"{s}\n" for s in test).encode())
    put("stats/mean.npy", npy_bytes(mean))
    put("stats/std.npy", npy_bytes(std))
    schema = build_schema(body)
    put("schema.json", json_bytes(schema))
    put(LABELS_JSON, json_bytes(vocabulary.as_dict()))
    for sid in sorted(docs):
        d = docs[sid]
        for rel, rec in d["files"].items():
            files[f"sequences/{sid}/{rel}"] = rec
        data = (seq_root / sid / SEQUENCE_JSON).read_bytes()
        files[f"sequences/{sid}/{SEQUENCE_JSON}"] = {"sha256": _sha(data), "bytes": len(data)}

    split_of = {**{s: "train" for s in train}, **{s: "test" for s in test}}
    incomplete = {sid: miss for sid in sorted(docs) if (miss := _missing_stages(docs[sid]["has"], expect))}
    manifest = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "toolkit_version": __version__,
        "body_model": body,
        "fps": fps,
        "units": {"length": "m", "time": "s", "angle": "rad", "frame_index": "frame at fps"},
        "axes": "Y-up, metres",
        "world_frame": "right-handed, +Y up, floor y = 0; a body at identity faces +Z, its left towards +X",
        "persons": {"a": "actor 0", "b": "actor 1"},
        "feature_dim": FEATURE_DIM,
        "vocabulary": {"file": LABELS_JSON, "size": len(vocabulary)},
        "split": {"ratio": float(split_ratio), "seed": int(seed), "subject_disjoint": bool(subject_disjoint),
                  "files": {"train": "splits/train.txt", "test": "splits/test.txt"}},  # fmt: skip
        "stats": {"mean": "stats/mean.npy", "std": "stats/std.npy", "over": "train features, both persons"},
        "counts": {
            "sequences": len(docs), "train": len(train), "test": len(test),
            "frames": int(sum(d["frames"] for d in docs.values())),
            "subjects": len({s for d in docs.values() for s in d["subjects"] if s}),
            "texts": int(sum(d["num_texts"] for d in docs.values())),
            **{f"with_{k}": sum(bool(d["has"][k]) for d in docs.values())
               for k in ("contacts", "text", "cameras", "renders", "keypoints")},
            "skipped": len(skipped), "incomplete": len(incomplete), "files": 0,
        },  # fmt: skip
        "expect": list(expect),
        "sequences": {sid: {"frames": docs[sid]["frames"], "subjects": docs[sid]["subjects"], "split": split_of[sid],
                            "has": docs[sid]["has"], "render_views": docs[sid]["render_views"],
                            "num_texts": docs[sid]["num_texts"], "labels": docs[sid]["labels"],
                            "symmetric": docs[sid].get("symmetric")}
                      for sid in sorted(docs)},  # fmt: skip
        "incomplete": incomplete,
        "skipped": dict(sorted(skipped.items())),
        "files": {},
    }
    put("README.md", dataset_card(manifest).encode("utf-8"))
    manifest["files"] = dict(sorted(files.items()))
    manifest["counts"]["files"] = len(files)
    for sub in OWN_FOLDERS[1:]:
        _clean_folder(out / sub, {r.split("/", 1)[1] for r in files if r.startswith(sub + "/")})
    rewritten += _put_bytes(out / MANIFEST, json_bytes(manifest))[1]
    say(f"export: {len(docs)} sequences ({len(train)} train, {len(test)} test), {len(skipped)} skipped, "
        f"{rewritten} files written, {out}")  # fmt: skip
    return manifest


# ============================================================================ dataset card
def _layout_section() -> str:
    """The module docstring's layout section as Markdown (the ``::`` block becomes a code fence)."""
    doc = __doc__ or ""
    start = doc.find("Layout\n------")
    if start < 0:
        return "See schema.json for every array."
    out, in_block = ["## Layout", ""], False
    for line in doc[start:].splitlines()[2:]:
        if line.strip() == "::":
            out.append("```")
            in_block = True
            continue
        if in_block and line and not line.startswith(" "):
            while out[-1] == "":
                out.pop()
            out += ["```", ""]
            in_block = False
        if not line.strip() and out[-1] in ("", "```"):
            continue
        if in_block:
            out.append(line[4:])
        else:
            out.append(re.sub(r":\w+:`([^`]+)`", r"`\1`", line).replace("``", "`"))
    if in_block:
        out.append("```")
    return "\n".join(out).strip()


def dataset_card(manifest: Mapping[str, Any]) -> str:
    """The export's ``README.md`` (Markdown) generated from ``manifest`` (its ``files`` may be empty)."""
    c = manifest["counts"]
    bm = manifest["body_model"]
    lines = [
        "# Two-person interaction dataset (dualhuman-builder export)",
        "",
        f"Written by dualhuman-builder {manifest['toolkit_version']}, format {manifest['format']} "
        f"version {manifest['format_version']}.",
        "",
        "| | |",
        "| --- | --- |",
        f"| sequences | {c['sequences']} ({c['train']} train, {c['test']} test) |",
        f"| frames | {c['frames']} at {manifest['fps']:g} fps ({c['frames'] / manifest['fps']:.1f} s) |",
        f"| subjects | {c['subjects']} |",
        f"| texts | {c['texts']} |",
        f"| with contacts / cameras / renders | {c['with_contacts']} / {c['with_cameras']} / {c['with_renders']} |",
        f"| body model | {bm['name']} {bm['version']}: {bm['num_bones']} bones, {bm['num_shape_params']} "
        f"phenotype values, {bm['num_vertices']} vertices |",
        f"| units, frame | metres, seconds, radians; {manifest['world_frame']} |",
        f"| motion features | {manifest['feature_dim']} per person and frame step (HumanML3D 263 + 6) |",
        f"| split | seed {manifest['split']['seed']}, ratio {manifest['split']['ratio']:g}, "
        f"subject-disjoint: {'yes' if manifest['split']['subject_disjoint'] else 'no'} |",
        "",
        "Every array is described in `schema.json` (shape, dtype, units, meaning); `manifest.json` lists every "
        "file with its SHA-256. Check a download with `dualhuman export verify DIR`.",
        "",
        "Files never need unpickling: read the `.npz` files with `numpy.load(path, allow_pickle=False)`.",
        "",
        _layout_section(),
        "",
    ]
    if manifest.get("skipped"):
        lines += ["## Left out", ""] + [f"- `{k}`: {v}" for k, v in manifest["skipped"].items()] + [""]
    if manifest.get("incomplete"):
        lines += ["## Exported without some stages", ""]
        lines += [f"- `{k}`: no {', '.join(v)}" for k, v in manifest["incomplete"].items()] + [""]
    return "\n".join(lines)


def read_manifest(out_dir: str | Path) -> dict[str, Any]:
    """``manifest.json`` of an export; ValueError when missing, unparseable or of a newer format."""
    path = Path(out_dir) / MANIFEST
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ValueError(f"{path} does not exist: not a (finished) dataset export") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path} is not valid UTF-8 JSON ({e})") from e
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ValueError(f"{path} is not a {FORMAT} manifest")
    version = doc.get("format_version")
    if not isinstance(version, int) or version > FORMAT_VERSION:
        raise ValueError(f"{path}: format_version {version!r}; this toolkit reads up to {FORMAT_VERSION}")
    return doc


__all__ = ["ExportItem", "export_dataset", "make_splits", "build_schema", "dataset_card", "read_manifest",
           "load_motion", "load_contacts", "read_npz", "npz_bytes", "json_bytes", "check_seq_id", "FORMAT_VERSION"]  # fmt: skip

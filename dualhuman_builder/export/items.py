"""The sequences to export (:class:`ExportItem`) and their validation before anything is written.

:func:`prepare_item` checks one item against the export's interaction vocabulary and returns a
:class:`PreparedItem`: decoded UTF-8 text, checked labels and roles, contacts as arrays, the render
folder's files, and the reason to skip the sequence when its motion is missing or not finite.
Input errors (unsafe text, unknown labels, malformed contacts, a missing render folder) raise
ValueError, so that every one surfaces before the export writes a file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from dualhuman_builder.export.files import PERSONS, json_clean
from dualhuman_builder.labels import Vocabulary
from dualhuman_builder.tracks import InteractionSequence


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
class PreparedItem:
    """An :class:`ExportItem` checked and resolved by :func:`prepare_item`: subject names, labels
    (in the vocabulary), texts and roles as ``str``, the labels' ``multi_hot`` vector over the
    vocabulary, contacts as arrays (None without), the render files to copy, and ``problem``, the
    reason to skip the sequence (None: exportable)."""

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


def _decode_texts(seq_id: str, values, what: str) -> list[str]:
    """``values`` (``str`` or UTF-8 ``bytes``) as ``str``; ValueError naming the sequence, ``what``
    and the offending position for bytes that are not UTF-8 or strings holding surrogates."""
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
    """``contacts`` (a mapping or an object with the same attributes, e.g. a ``ContactResult``) as
    ``{labels (2, T, V) bool, distances (2, T, V) float16, frame_contact (T,) bool, events}`` with
    JSON-clean events; ValueError on a missing field or a wrong shape."""
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
    """``(path in the sequence folder, source)`` of every file of a render folder, sorted:
    ``cameras.json`` at the top, the rest under ``renders/``; hidden files and folders left out."""
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


def prepare_item(item: ExportItem, vocabulary: Vocabulary) -> PreparedItem:
    """``item`` checked against ``vocabulary`` (see the module docstring); ValueError for input
    errors, ``problem`` set for a sequence to skip (no motion, fewer than 2 frames, NaN motion)."""
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
    return PreparedItem(item, (str(subjects[0]), str(subjects[1])), labels, texts, roles, symmetric,
                     vocabulary.multi_hot(labels).tolist(), contacts, files, problem)  # fmt: skip


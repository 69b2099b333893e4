"""Gather a workspace's finished takes into an export (``dualhuman export WS OUT``).

One exported sequence per take whose ``fit`` stage is complete: the fitted pair (``bodies.npz``),
the ``contacts`` stage's labels when that stage is complete, the ``render`` stage's folder when it
is, the take's labels, texts and roles (its sequences' and annotations', checked against the
workspace's vocabulary), and the take's actors as subjects. Takes without a fit
are listed as left out (an error with ``strict=True``); what each exported sequence lacks is listed
by :func:`~dualhuman_builder.export.writer.export_dataset` under ``incomplete``. Takes the quality
gates flagged (their verdicts in the catalog: :func:`~dualhuman_builder.workspace.catalog.take_flags`)
are left out unless ``include_flagged``; the manifest's ``quality`` says which, and why.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Callable

from dualhuman_builder.errors import WorkspaceError


def _vocabulary(ws):
    from dualhuman_builder.labels import load_vocabulary

    try:
        return load_vocabulary(ws.root)
    except ValueError as e:
        raise WorkspaceError(str(e), path=ws.root) from None


def workspace_items(ws, takes: list[str] | None = None, vocabulary=None) -> tuple[list, list[str]]:
    """``(items, left_out)``: an :class:`~dualhuman_builder.export.items.ExportItem` per take of
    ``takes`` (default: all) with a complete fit, and the names of those without one. Labels,
    texts, roles and the symmetric flag come from the take's sequences and annotations
    (:func:`~dualhuman_builder.export.annotate.take_labels`), checked against ``vocabulary``
    (default: the workspace's, :func:`~dualhuman_builder.labels.load_vocabulary`)."""
    from dualhuman_builder.contacts.stage import CONTACTS, load_contacts
    from dualhuman_builder.export.annotate import take_labels
    from dualhuman_builder.export.items import ExportItem
    from dualhuman_builder.fit.stage import FIT, load_bodies
    from dualhuman_builder.render.stage import RENDER

    vocabulary = vocabulary or _vocabulary(ws)
    known = ws.takes()
    names = list(takes) if takes else known
    unknown = [t for t in names if t not in known]
    if unknown:
        raise WorkspaceError(f"no take named {unknown} in this workspace (it has {known})", path=ws.root)
    items, left_out = [], []
    for take in names:
        if not FIT.done(ws, take):
            left_out.append(take)
            continue
        seq = load_bodies(ws, take)
        contacts = load_contacts(ws, take) if CONTACTS.done(ws, take) else None
        render_dir = ws.artifact_dir("render", take) if RENDER.done(ws, take) else None
        try:
            lab = take_labels(ws, take, vocabulary)
        except ValueError as e:
            raise WorkspaceError(f"take {take!r}: {e}", path=ws.root) from None
        info = ws.take(take)
        subjects = tuple(info.actors) if len(info.actors) == 2 else None
        roles = None
        if subjects is not None and lab["actor"] in subjects:
            roles = ("actor", "reactor") if lab["actor"] == subjects[0] else ("reactor", "actor")
        items.append(ExportItem(take, seq, subjects=subjects, labels=lab["labels"], texts=lab["texts"], roles=roles,
                                symmetric=lab["symmetric"], annotations=lab["annotators"], contacts=contacts,
                                render_dir=render_dir, meta={"take": take, "rig": info.rig}))  # fmt: skip
    return items, left_out


def quality_verdicts(ws, items: list, include_flagged: bool, log: Callable[[str], None]) -> tuple[list, dict]:
    """``(items to export, the manifest's quality section)``: ``items`` less those whose take the
    quality gates flagged, unless ``include_flagged`` (each one logged with its flags). The section:
    ``left_out`` and ``included`` (take -> its flags: gate, stage, subject, value, threshold,
    message), ``unchecked`` (takes never checked) and ``outdated`` (take -> stages that ran again
    since the check)."""
    from dualhuman_builder.workspace.catalog import take_flags

    verdicts = take_flags(ws.conn)
    keep, section = [], {"left_out": {}, "included": {}, "unchecked": [], "outdated": {}}
    for item in items:
        take = (item.meta or {}).get("take", item.seq_id)
        v = verdicts.get(take)
        if v is None:
            section["unchecked"].append(take)
            keep.append(item)
            continue
        if v["outdated"]:
            section["outdated"][take] = v["outdated"]
        if not v["flags"]:
            keep.append(item)
            continue
        flags = [{k: f[k] for k in ("gate", "stage", "subject", "value", "threshold", "message")} for f in v["flags"]]
        why = "; ".join(f"{f['gate']} ({f['stage']}): {f['message']}" for f in flags)
        if include_flagged:
            section["included"][take] = flags
            keep.append(item)
            log(f"WARNING: take {take!r} exported although flagged by the quality gates (--include-flagged): {why}")
        else:
            section["left_out"][take] = flags
            log(f"take {take!r} left out: flagged by the quality gates: {why} (export it with --include-flagged)")
    if section["unchecked"]:
        log(f"note: {len(section['unchecked'])} take(s) never checked by the quality gates: "
            f"{section['unchecked'][:10]} (`dualhuman gates {ws.root}` checks them)")  # fmt: skip
    return keep, section


def run_export(ws, out_dir: str | Path, takes: list[str] | None = None, strict: bool = False, split_ratio: float = 0.75,
               subject_disjoint: bool = False, seed: int = 0, log: Callable[[str], None] = print,
               include_flagged: bool = False, splits: Mapping[str, str] | None = None) -> dict:  # fmt: skip
    """Export the workspace's fitted takes to ``out_dir``; returns the manifest (plus
    ``left_out``: takes without a fit). Takes the quality gates flagged are left out unless
    ``include_flagged``; the manifest's ``quality`` (:func:`quality_verdicts`) says which and why.
    ``splits``: take -> ``"train"``/``"test"`` given from elsewhere (a synthetic plan's hold-outs), kept for the
    takes exported; the others' split is drawn (:func:`~dualhuman_builder.export.writer.export_dataset`)."""
    from dualhuman_builder.export.writer import export_dataset

    vocabulary = _vocabulary(ws)
    from dualhuman_builder.contacts.stage import CONTACTS
    from dualhuman_builder.fit.stage import FIT
    from dualhuman_builder.render.stage import RENDER

    items, left_out = workspace_items(ws, takes, vocabulary)
    for item in items:  # a stale optional part is left out of the item: say why
        stale = [s.name for s in (CONTACTS, RENDER) if s.state(ws, item.seq_id) == "stale"]
        if stale:
            log(f"WARNING: take {item.seq_id!r}: {' and '.join(stale)} stale (an input changed since), exported without; "
                f"run `dualhuman {stale[0]} WS --take {item.seq_id}`")
    if left_out:
        stale = [t for t in left_out if FIT.state(ws, t) == "stale"]
        msg = f"takes without a complete fit, left out: {left_out}" + (
            f" ({stale} stale: an input changed since the fit)" if stale else "")
        if strict:
            raise WorkspaceError(msg, path=ws.root, fix="run `dualhuman fit WS --take T` for each, or drop --strict")
        log("WARNING: " + msg)
    if not items:
        raise WorkspaceError("no take has a complete fit: nothing to export", path=ws.root,
                             fix="run `dualhuman fit WS --take T` first")  # fmt: skip
    items, quality = quality_verdicts(ws, items, include_flagged, log)
    if not items:
        raise WorkspaceError(f"every fitted take is flagged by the quality gates: {sorted(quality['left_out'])}",
                             path=ws.root, fix=f"look at them (`dualhuman status {ws.root}`, `dualhuman review {ws.root}`), "
                                               "or export them anyway with --include-flagged")  # fmt: skip
    manifest = export_dataset(items, out_dir, split_ratio=split_ratio, subject_disjoint=subject_disjoint, seed=seed,
                              strict=strict, progress=log, vocabulary=vocabulary, extra={"quality": quality},
                              splits={k: v for k, v in (splits or {}).items() if k in {i.seq_id for i in items}} or None)  # fmt: skip
    manifest["left_out"] = left_out
    return manifest

"""Exports derived from another export by a model (refined or estimated motion), written with the
input's split so that train and test stay the sequences they were."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping


def write_derived_export(items: list, out_dir: Path, manifest: Mapping[str, Any], vocabulary, splits: Mapping[str, str],
                         extra: Mapping[str, Any]) -> dict:  # fmt: skip
    """Write ``items`` (:class:`~dualhuman_builder.export.items.ExportItem`) to ``out_dir`` as an export of
    motion and text, with the input export's split settings (its ``manifest``), ``splits`` given per
    sequence, and ``extra`` top-level manifest entries saying what the model did; returns the manifest."""
    from dualhuman_builder.export.writer import export_dataset

    split_doc = manifest.get("split", {})
    return export_dataset(items, out_dir, split_ratio=float(split_doc.get("ratio", 0.75)), seed=int(split_doc.get("seed", 0)),
                          subject_disjoint=bool(split_doc.get("subject_disjoint", False)), expect=("motion", "text"),
                          vocabulary=vocabulary, splits=splits, extra=dict(extra))  # fmt: skip


def derived_item(sid: str, seq, seq_doc: Mapping[str, Any], text: Mapping[str, Any], meta: Mapping[str, Any]):
    """The :class:`~dualhuman_builder.export.items.ExportItem` of sequence ``sid`` with the model's
    motion ``seq`` and the input's subjects, labels, texts, roles and annotations (``seq_doc``: its
    ``sequence.json``, ``text``: its ``text.json``), and ``meta`` saying what the model did."""
    from dualhuman_builder.export.items import ExportItem

    roles = text.get("roles")
    return ExportItem(sid, seq, subjects=tuple(seq_doc.get("subjects") or ("", ""))[:2],
                      labels=list(text.get("labels", [])), texts=list(text.get("texts", [])),
                      roles=tuple(roles) if isinstance(roles, list) and len(roles) == 2 else None,
                      symmetric=text.get("symmetric"), annotations=list(text.get("annotations") or []),
                      meta=dict(meta))  # fmt: skip

"""Annotation files in and out of a workspace (``dualhuman annotate import|export``), so that
labelling can happen in any tool: a spreadsheet, a web form, a script.

Two formats, told apart by the file name:

* **CSV** (``.csv``, UTF-8, a BOM is fine, header row required): columns ``take``, ``sequence``
  (empty: the whole take), ``labels`` (vocabulary names separated by ``;``), ``actor``,
  ``reactor``, ``symmetric`` (``true``/``false``/``yes``/``no``/``1``/``0``, empty: derived from
  the labels), ``annotator``, ``annotated_at`` (ISO 8601; empty: the import time), and one or
  more text columns whose names start with ``text`` (``text_1``, ``text_2``, ...), one
  description each. Unknown columns are an error (a typo would otherwise lose data).
* **JSON Lines** (``.jsonl`` / ``.ndjson``): one object per line with the same keys; ``labels``
  and ``texts`` are lists of strings (``labels`` may also be a ``;``-separated string).

Import checks the whole file before it stores anything: every row's take and sequence exist,
labels are in the vocabulary (the built-in one plus ``WS/labels.toml``), actor and reactor are
actors of the take, texts are valid UTF-8, and no (take, sequence, annotator) appears twice. Any
problem is an error naming the line, unless ``skip_invalid`` (then the bad rows are counted and
listed, the good ones stored). Rows with neither labels, texts nor roles are blank template rows
and are skipped (counted). A row replaces the stored annotation of the same take, sequence and
annotator, so re-importing an edited file updates it.

Export writes every stored annotation and, unless ``blank=False``, one blank row per take and per
sequence that has none yet: the template to fill in.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import os
from pathlib import Path
from typing import Any

from dualhuman_builder.errors import WorkspaceError
from dualhuman_builder.labels import Annotation, Vocabulary, check_annotation, load_vocabulary

FIELDS = ("take", "sequence", "labels", "actor", "reactor", "symmetric", "annotator", "annotated_at")
_TRUE, _FALSE = {"true", "yes", "1", "y", "t"}, {"false", "no", "0", "n", "f"}
#: Problems listed in an import error (the rest are counted).
_MAX_LISTED = 12


def _format(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix == ".csv":
        return "csv"
    if suffix in (".jsonl", ".ndjson"):
        return "jsonl"
    raise WorkspaceError(f"cannot tell the annotation format of {path.name!r}: use a .csv or .jsonl file name", path=path)


def _decode(data: bytes, path: Path) -> str:
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        line = data[: e.start].count(b"\n") + 1
        raise WorkspaceError(f"not valid UTF-8 at byte {e.start} (line {line}: {data[max(0, e.start - 12) : e.start + 4]!r}); "
                             "save the file as UTF-8", path=path) from None  # fmt: skip


def _bool(value: Any) -> bool | None:
    if value is None or isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if not text:
        return None
    if text in _TRUE:
        return True
    if text in _FALSE:
        return False
    raise ValueError(f"symmetric must be true or false, got {value!r}")


def _labels(value: Any) -> list[str]:
    if value is None:
        return []
    if isinstance(value, str):
        return [x.strip() for x in value.split(";") if x.strip()]
    if isinstance(value, list) and all(isinstance(x, str) for x in value):
        return [x.strip() for x in value if x.strip()]
    raise ValueError(f"labels must be a list of names or a ';'-separated string, got {value!r}")


def _text(value: Any, what: str) -> str | None:
    if value is None:
        return None
    if not isinstance(value, str):
        raise ValueError(f"{what} must be text, got {value!r}")
    return value.strip() or None


def _records(text: str, fmt: str) -> list[tuple[int, dict[str, Any]]]:
    """``[(line number, {field: value, "texts": [...]})]``; ValueError for a malformed file."""
    out = []
    if fmt == "jsonl":
        for i, line in enumerate(text.splitlines(), 1):
            if not line.strip():
                continue
            try:
                obj = json.loads(line)
            except json.JSONDecodeError as e:
                out.append((i, {"_error": f"not JSON ({e.msg} at column {e.colno})"}))
                continue
            if not isinstance(obj, dict):
                out.append((i, {"_error": "each line must be a JSON object"}))
                continue
            extra = sorted(set(obj) - set(FIELDS) - {"texts"})
            texts = obj.get("texts", [])
            if extra:
                obj = {"_error": f"unknown keys {extra} (known: {[*FIELDS, 'texts']})"}
            elif not isinstance(texts, list):
                obj = {"_error": "texts must be a list of strings"}
            out.append((i, obj))
        return out
    reader = csv.DictReader(io.StringIO(text, newline=""))
    header = reader.fieldnames or []
    text_cols = [c for c in header if c and c.strip().lower().startswith("text")]
    unknown = [c for c in header if c not in FIELDS and c not in text_cols]
    if "take" not in header:
        raise ValueError(f"the CSV header has no 'take' column (header: {header}); columns: {[*FIELDS, 'text_1', '...']}")
    if unknown:
        raise ValueError(f"unknown CSV columns {unknown} (known: {[*FIELDS, 'text_1', 'text_2', '...']})")
    for row in reader:
        if None in row:
            out.append((reader.line_num, {"_error": f"{len(row[None])} more cells than header columns"}))
            continue
        rec: dict[str, Any] = {k: row.get(k) for k in FIELDS}
        rec["texts"] = [row[c] for c in text_cols if row.get(c) and row[c].strip()]
        out.append((reader.line_num, rec))
    return out


def _parse(rec: dict[str, Any], default_annotator: str | None, source: str) -> Annotation:
    if "_error" in rec:
        raise ValueError(rec["_error"])
    take = _text(rec.get("take"), "take")
    if take is None:
        raise ValueError("take is empty")
    texts = [_text(t, "each text") for t in rec.get("texts") or []]
    annotator = _text(rec.get("annotator"), "annotator") or default_annotator
    return Annotation(take, _text(rec.get("sequence"), "sequence"), annotator or "", tuple(_labels(rec.get("labels"))),
                      tuple(t for t in texts if t), _text(rec.get("actor"), "actor"), _text(rec.get("reactor"), "reactor"),
                      _bool(rec.get("symmetric")), _text(rec.get("annotated_at"), "annotated_at") or "", source)  # fmt: skip


def import_annotations(ws, path: str | Path, annotator: str | None = None, skip_invalid: bool = False,
                       vocabulary: Vocabulary | None = None) -> dict[str, Any]:  # fmt: skip
    """Read ``path`` (CSV or JSON Lines, see the module docstring) into ``ws``'s catalog.

    ``annotator``: for rows without an ``annotator`` value. Returns ``{"file", "rows",
    "imported", "blank", "invalid": [[line, message], ...]}``. Raises :class:`WorkspaceError`
    (storing nothing) when the file is unreadable, or when a row is invalid and not
    ``skip_invalid``."""
    from dualhuman_builder.workspace.catalog import now_iso

    path = Path(path)
    fmt = _format(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise WorkspaceError(f"cannot read the annotation file ({e.strerror})", path=path) from None
    try:
        records = _records(_decode(data, path), fmt)
    except ValueError as e:
        raise WorkspaceError(str(e), path=path) from None
    vocab = vocabulary or load_vocabulary(ws.root)
    stamp = now_iso()
    good: list[Annotation] = []
    invalid: list[list] = []
    blank = 0
    seen: dict[tuple, int] = {}
    for line, rec in records:
        try:
            a = _parse(rec, annotator, path.name)
            if not (a.labels or a.texts or a.actor or a.reactor):
                blank += 1
                continue
            if not a.annotator:
                raise ValueError("no annotator: fill the annotator column or pass --annotator NAME")
            info = ws.take(a.take)
            if a.sequence is not None:
                ws.sequence(a.take, a.sequence)
            a = check_annotation(a, vocab, info.actors)
            key = (a.take, a.sequence, a.annotator)
            if key in seen:
                raise ValueError(f"repeats line {seen[key]} (same take, sequence and annotator)")
            seen[key] = line
        except (ValueError, WorkspaceError) as e:
            invalid.append([line, e.message if isinstance(e, WorkspaceError) else str(e)])
            continue
        good.append(dataclasses.replace(a, annotated_at=a.annotated_at or stamp))
    if invalid and not skip_invalid:
        listed = "; ".join(f"line {n}: {m}" for n, m in invalid[:_MAX_LISTED])
        more = f" (and {len(invalid) - _MAX_LISTED} more)" if len(invalid) > _MAX_LISTED else ""
        raise WorkspaceError(f"{len(invalid)} invalid row(s), nothing imported: {listed}{more}", path=path,
                             fix="correct the rows, or pass --skip-invalid to import the others")  # fmt: skip
    stored = ws.annotate(good) if good else 0
    return {"file": str(path), "rows": len(records), "imported": stored, "blank": blank, "invalid": invalid}


def annotation_rows(ws, blank: bool = True) -> list[Annotation]:
    """Every stored annotation, plus (``blank``) an empty one per take and sequence without any."""
    rows = ws.annotations()
    if blank:
        have = {(a.take, a.sequence) for a in rows}
        for take in ws.takes():
            for seq in [None, *(s.name for s in ws.sequences(take))]:
                if (take, seq) not in have:
                    rows.append(Annotation(take, seq, ""))
        rows.sort(key=lambda a: (a.take, a.sequence or "", a.annotator))
    return rows


def _csv_text(rows: list[Annotation]) -> str:
    n_text = max([3, *(len(a.texts) for a in rows)])
    buf = io.StringIO(newline="")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([*FIELDS, *(f"text_{k + 1}" for k in range(n_text))])
    for a in rows:
        sym = "" if a.symmetric is None else str(a.symmetric).lower()
        w.writerow([a.take, a.sequence or "", ";".join(a.labels), a.actor or "", a.reactor or "", sym, a.annotator,
                    a.annotated_at, *a.texts, *([""] * (n_text - len(a.texts)))])  # fmt: skip
    return buf.getvalue()


def export_annotations(ws, path: str | Path | None, fmt: str | None = None, blank: bool = True) -> tuple[str, int]:
    """Write the annotations (see :func:`annotation_rows`) to ``path`` (atomically), or return
    them when ``path`` is None. ``fmt``: ``csv`` or ``jsonl`` (default: from the file name).
    Returns ``(text, rows)``."""
    rows = annotation_rows(ws, blank)
    fmt = fmt or (_format(Path(path)) if path is not None else "jsonl")
    if fmt == "csv":
        text = _csv_text(rows)
    elif fmt == "jsonl":
        text = "".join(json.dumps(a.as_dict(), ensure_ascii=False) + "\n" for a in rows)
    else:
        raise ValueError(f"format must be csv or jsonl, got {fmt!r}")
    if path is not None:
        path = Path(path)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(text, encoding="utf-8", newline="")
        os.replace(tmp, path)
    return text, len(rows)


def take_labels(ws, take: str, vocabulary: Vocabulary) -> dict[str, Any]:
    """What the export stores for ``take``: the union of its sequences' labels and of every
    annotation's labels and texts (take-level and per sequence, in catalog order), roles from the
    latest annotation naming an actor, the symmetric flag (the latest annotation's; else derived
    from the labels), and who annotated when. ``{"labels", "texts", "actor", "symmetric",
    "annotators": [{"annotator", "annotated_at", "sequence"}]}``."""
    labels: list[str] = []
    texts: list[str] = []
    for s in ws.sequences(take):
        labels += [x for x in s.labels if x not in labels]
        texts += [x for x in s.text if x not in texts]
    anns = sorted(ws.annotations(take), key=lambda a: a.annotated_at)
    actor, symmetric = None, None
    for a in anns:
        labels += [x for x in a.labels if x not in labels]
        texts += [x for x in a.texts if x not in texts]
        if a.actor is not None:
            actor = a.actor
        if a.symmetric is not None:
            symmetric = a.symmetric
    vocabulary.check(labels)
    if symmetric is None:
        symmetric = vocabulary.symmetric(labels)
    if symmetric:
        actor = None
    return {"labels": labels, "texts": texts, "actor": actor, "symmetric": symmetric,
            "annotators": [{"annotator": a.annotator, "annotated_at": a.annotated_at, "sequence": a.sequence} for a in anns]}  # fmt: skip

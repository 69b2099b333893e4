"""Annotation files in and out of a workspace (``dualhuman annotate import|export``), so that
labelling can happen in any tool: a spreadsheet, a web form, a script.

Two formats, told apart by the file name:

* **CSV** (``.csv``, UTF-8, a BOM is fine, header row required): columns ``take``, ``sequence``
  (empty: the whole take), ``labels`` (vocabulary names separated by ``;``), ``actor``,
  ``reactor``, ``symmetric`` (``true``/``false``/``yes``/``no``/``1``/``0``, empty: derived from
  the labels), ``annotator``, ``annotated_at`` (ISO 8601; empty: the import time), and one or
  more text columns whose names start with ``text`` (``text_1``, ``text_2``, ...), one
  description each. Unknown columns are an error (a typo would otherwise lose data). A cell that
  starts with a character a spreadsheet reads as a formula (``=``, ``+``, ``-``, ``@``, tab, CR,
  LF; OWASP's advice on CSV injection) is written with a leading ``'``, which import removes, so
  the text survives a round trip and no spreadsheet runs it (see :func:`escape_cell`).
* **JSON Lines** (``.jsonl`` / ``.ndjson``): one object per line with the same keys; ``labels``
  and ``texts`` are lists of strings (``labels`` may also be a ``;``-separated string).

Import checks the whole file before it stores anything: every row's take and sequence exist,
labels are in the vocabulary (the built-in one plus ``WS/labels.toml``), actor and reactor are
actors of the take, texts are valid UTF-8, ``annotated_at`` is an ISO 8601 time, names (take,
sequence, labels, actor, reactor, annotator) hold no control or format characters and texts no
control characters but tab and line breaks, no value is longer than :data:`MAX_VALUE_CHARS`, and no
(take, sequence, annotator) appears twice. Any problem is an error naming the line (a JSON line
nested too deeply included), unless ``skip_invalid`` (then the bad rows are counted and listed, the
good ones stored). A file over :data:`MAX_FILE_BYTES` or a CSV that does not parse is an error.
Rows with neither labels, texts nor roles are blank template rows and are skipped (counted). A row
replaces the stored annotation of the same take, sequence and annotator, so re-importing an edited
file updates it.

Export writes every stored annotation and, unless ``blank=False``, one blank row per take and per
sequence that has none yet: the template to fill in.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import json
import os
import unicodedata
from datetime import datetime
from pathlib import Path
from typing import Any

from dualhuman_builder.errors import WorkspaceError
from dualhuman_builder.labels import Annotation, Vocabulary, check_annotation, load_vocabulary

FIELDS = ("take", "sequence", "labels", "actor", "reactor", "symmetric", "annotator", "annotated_at")
_TRUE, _FALSE = {"true", "yes", "1", "y", "t"}, {"false", "no", "0", "n", "f"}
#: Problems listed in an import error (the rest are counted).
_MAX_LISTED = 12
#: Largest annotation file import reads (bytes): far more than any labelling session writes.
MAX_FILE_BYTES = 64 << 20
#: Longest value (characters) of one cell or key: the csv module's own default field limit.
MAX_VALUE_CHARS = 131072
#: Unicode categories a name may not hold: control, format, surrogate, private use, line and
#: paragraph separators (the workspace refuses the same).
_UNSAFE_IN_NAMES = frozenset({"Cc", "Cf", "Cs", "Co", "Zl", "Zp"})
#: First characters that make a spreadsheet read a cell as a formula (OWASP, "CSV Injection").
FORMULA_START = frozenset("=+-@\t\r\n")


def escape_cell(text: str) -> str:
    """``text`` as a CSV cell no spreadsheet runs as a formula: a ``'`` is put before a text that
    starts with a formula character (``=``, ``+``, ``-``, ``@``, tab, CR, LF), or with ``'``s and
    then one, so that :func:`unescape_cell` gives back exactly ``text``."""
    rest = text.lstrip("'")
    return "'" + text if rest and rest[0] in FORMULA_START else text


def unescape_cell(cell: str) -> str:
    """Inverse of :func:`escape_cell`: one leading ``'`` removed where ``escape_cell`` adds one."""
    rest = cell.lstrip("'")
    return cell[1:] if cell.startswith("'") and rest and rest[0] in FORMULA_START else cell


def _show(value: Any) -> str:
    """A value from the file for a message: scalars shown (long text cut), containers only named."""
    if value is None or isinstance(value, (bool, int, float)):
        return repr(value)
    if isinstance(value, str):
        return repr(value[:60]) + (f"... ({len(value)} characters)" if len(value) > 60 else "")
    return f"a {type(value).__name__}"


def _show_all(values: list) -> str:
    return "[" + ", ".join(_show(v) for v in values[:12]) + (", ...]" if len(values) > 12 else "]")


def _check_chars(value: str, what: str, text: bool = False) -> str:
    """``value`` unless it is too long or holds characters a name (``text``: a description) must not:
    control characters (a text may hold tab and line breaks) and lone surrogates, and in names also
    format (bidirectional overrides), private-use characters and line separators, which would reach
    terminals and files raw."""
    if len(value) > MAX_VALUE_CHARS:
        raise ValueError(f"{what} is {len(value)} characters long, more than {MAX_VALUE_CHARS}")
    for i, ch in enumerate(value):
        cat = unicodedata.category(ch)
        bad = cat in ("Cc", "Cs") and ch not in "\t\n\r" if text else cat in _UNSAFE_IN_NAMES
        if bad:
            kind = "control" if cat == "Cc" else "invisible or invalid"
            raise ValueError(f"{what} holds the {kind} character {ch!r} (U+{ord(ch):04X}) at position {i + 1}; "
                             "remove it")  # fmt: skip
    return value


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
    if not isinstance(value, (str, int)):
        raise ValueError(f"symmetric must be true or false, got {_show(value)}")
    text = str(value).strip().lower()
    if not text:
        return None
    if text in _TRUE:
        return True
    if text in _FALSE:
        return False
    raise ValueError(f"symmetric must be true or false, got {_show(value)}")


def _labels(value: Any) -> list[str]:
    if value is None:
        return []
    if isinstance(value, str):
        _check_chars(value, "labels")
        return [x.strip() for x in value.split(";") if x.strip()]
    if isinstance(value, list) and all(isinstance(x, str) for x in value):
        return [_check_chars(x.strip(), "a label") for x in value if x.strip()]
    raise ValueError(f"labels must be a list of names or a ';'-separated string, got {_show(value)}")


def _text(value: Any, what: str, text: bool = False) -> str | None:
    """``value`` stripped (None when empty), checked as a name (``text``: as a description)."""
    if value is None:
        return None
    if not isinstance(value, str):
        raise ValueError(f"{what} must be text, got {_show(value)}")
    return _check_chars(value.strip(), what, text) or None


def _time(value: Any) -> str:
    """``annotated_at``: an ISO 8601 date and time as given ("" when empty: the import time)."""
    text = _text(value, "annotated_at")
    if text is None:
        return ""
    try:
        if len(text) > 64:
            raise ValueError
        datetime.fromisoformat(text)
    except ValueError:
        raise ValueError(f"annotated_at must be an ISO 8601 time such as 2026-11-01T10:00:00Z, got {_show(text)}") \
            from None
    return text


@contextlib.contextmanager
def _csv_cells_up_to(limit: int):
    """Let the csv module parse cells of up to ``limit`` characters, so that a long cell is one
    invalid row instead of a parse error that loses track of the rows after it."""
    old = csv.field_size_limit()
    csv.field_size_limit(max(old, limit))
    try:
        yield
    finally:
        csv.field_size_limit(old)


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
            except RecursionError:
                out.append((i, {"_error": "not JSON this reader takes (nested too deeply)"}))
                continue
            except ValueError as e:  # an integer over Python's digit limit
                out.append((i, {"_error": f"not JSON this reader takes ({e})"}))
                continue
            if not isinstance(obj, dict):
                out.append((i, {"_error": "each line must be a JSON object"}))
                continue
            extra = sorted(set(obj) - set(FIELDS) - {"texts"})
            texts = obj.get("texts", [])
            if extra:
                obj = {"_error": f"unknown keys {_show_all(extra)} (known: {[*FIELDS, 'texts']})"}
            elif not isinstance(texts, list):
                obj = {"_error": "texts must be a list of strings"}
            out.append((i, obj))
        return out
    reader = csv.DictReader(io.StringIO(text, newline=""))
    try:
        with _csv_cells_up_to(len(text)):
            header = reader.fieldnames or []
            text_cols = [c for c in header if c and c.strip().lower().startswith("text")]
            unknown = [c for c in header if c not in FIELDS and c not in text_cols]
            if "take" not in header:
                raise ValueError(f"the CSV header has no 'take' column (header: {_show_all(header)}); "
                                 f"columns: {[*FIELDS, 'text_1', '...']}")  # fmt: skip
            if unknown:
                raise ValueError(f"unknown CSV columns {_show_all(unknown)} "
                                 f"(known: {[*FIELDS, 'text_1', 'text_2', '...']})")  # fmt: skip
            for row in reader:
                if None in row:
                    out.append((reader.line_num, {"_error": f"{len(row[None])} more cells than header columns"}))
                    continue
                row = {k: unescape_cell(v) if isinstance(v, str) else v for k, v in row.items()}
                rec: dict[str, Any] = {k: row.get(k) for k in FIELDS}
                rec["texts"] = [row[c] for c in text_cols if row.get(c) and row[c].strip()]
                out.append((reader.line_num, rec))
    except csv.Error as e:
        raise ValueError(f"line {reader.line_num}: not CSV this reader takes ({e})") from None
    return out


def _parse(rec: dict[str, Any], default_annotator: str | None, source: str) -> Annotation:
    if "_error" in rec:
        raise ValueError(rec["_error"])
    take = _text(rec.get("take"), "take")
    if take is None:
        raise ValueError("take is empty")
    texts = [_text(t, f"text {k + 1}", text=True) for k, t in enumerate(rec.get("texts") or [])]
    annotator = _text(rec.get("annotator"), "annotator") or _text(default_annotator, "the annotator name")
    return Annotation(take, _text(rec.get("sequence"), "sequence"), annotator or "", tuple(_labels(rec.get("labels"))),
                      tuple(t for t in texts if t), _text(rec.get("actor"), "actor"), _text(rec.get("reactor"), "reactor"),
                      _bool(rec.get("symmetric")), _time(rec.get("annotated_at")), source)  # fmt: skip


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
        with open(path, "rb") as f:  # in blocks: read(n) would set aside n bytes whatever the file holds
            blocks, size = [], 0
            while size <= MAX_FILE_BYTES and (block := f.read(1 << 20)):
                blocks.append(block)
                size += len(block)
        data = b"".join(blocks)
    except OSError as e:
        raise WorkspaceError(f"cannot read the annotation file ({e.strerror})", path=path) from None
    if len(data) > MAX_FILE_BYTES:
        raise WorkspaceError(f"more than {MAX_FILE_BYTES >> 20} MiB, larger than an annotation file can be", path=path,
                             fix="split it into several files and import each")  # fmt: skip
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
        w.writerow([escape_cell(c) for c in (a.take, a.sequence or "", ";".join(a.labels), a.actor or "", a.reactor or "",
                    sym, a.annotator, a.annotated_at, *a.texts, *([""] * (n_text - len(a.texts))))])  # fmt: skip
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

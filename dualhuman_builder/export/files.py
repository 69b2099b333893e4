"""The export's file names and formats, and the byte-level helpers that write and read them.

Every file the export writes is byte-deterministic: JSON with fixed formatting (:func:`json_bytes`),
``.npz``/``.npy`` with fixed zip timestamps and no pickles (:func:`npz_bytes`, :func:`npy_bytes`),
so that a re-run reproduces a dataset bit for bit and :func:`put_bytes` can leave unchanged files
alone. Readers never unpickle (:func:`read_npz`). The folder layout itself is documented in
:mod:`dualhuman_builder.export.card`.
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
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from dualhuman_builder.fileio import atomic_open, sha256_file

FORMAT = "dualhuman-export"
#: Version of the layout; :func:`read_manifest` refuses exports of a newer one.
FORMAT_VERSION = 2
#: Person keys in the files: ``a`` is actor 0 of the interaction, ``b`` actor 1.
PERSONS = ("a", "b")
#: A sequence id: a safe folder name and WebDataset key (no dots: keys end at the first dot).
SEQ_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,127}$")
MANIFEST = "manifest.json"
SEQUENCE_JSON = "sequence.json"
LABELS_JSON = "labels.json"
#: Timestamp of every ``.npz`` member (the earliest a zip can hold), for byte-deterministic files.
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)
#: Folders the export owns: files in them that the manifest does not list are removed on export
#: and reported by verify.
OWN_FOLDERS = ("sequences", "splits", "stats")


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
    """A ``.npy`` of ``a`` as bytes, never pickled."""
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


def sha256_bytes(data: bytes) -> str:
    """Hex SHA-256 of ``data``."""
    return hashlib.sha256(data).hexdigest()


def file_matches(path: Path, size: int, sha: str) -> bool:
    """Whether ``path`` is a file of ``size`` bytes with SHA-256 ``sha`` (False when unreadable)."""
    try:
        return path.is_file() and path.stat().st_size == size and sha256_file(path) == sha
    except OSError:
        return False


def put_bytes(path: Path, data: bytes) -> tuple[dict, bool]:
    """Write ``data`` to ``path`` atomically unless the file already holds exactly these bytes.
    Returns ``({"sha256", "bytes"}, written)``."""
    rec = {"sha256": sha256_bytes(data), "bytes": len(data)}
    if file_matches(path, rec["bytes"], rec["sha256"]):
        return rec, False
    with atomic_open(path, "wb") as f:
        f.write(data)
    return rec, True


def put_copy(src: Path, dest: Path) -> tuple[dict, bool]:
    """Hard-link (same filesystem) or copy ``src`` to ``dest`` atomically, unless ``dest`` already
    is ``src`` or holds the same bytes."""
    sha = sha256_file(src)
    rec = {"sha256": sha, "bytes": src.stat().st_size}
    if dest.is_file():
        try:
            if os.path.samefile(src, dest) or file_matches(dest, rec["bytes"], sha):
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


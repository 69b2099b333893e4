"""``dualhuman export verify OUT``: check a dataset export against its own manifest and schema.

:func:`verify_export` returns a list of problems (empty: the export is intact). It checks that
``manifest.json`` is present and parseable and its entries have the right types; every file it lists
is a regular file inside the export with its size and SHA-256; nothing else sits at the top level
or in the export's own folders; every array matches ``schema.json`` (names, shapes with the symbolic
dims resolved per sequence, dtypes); motion arrays hold no NaN/inf and the stored features are those
of the stored joints; contacts are consistent (vertex count, per-frame flags); a render's image
targets (``renders/targets.npz``) are finite and agree with its keypoints and cameras (the joints
projected within 0.5 px); the JSON files parse (text as UTF-8); labels are in ``labels.json`` and each multi-hot vector matches its labels; the
splits are disjoint, cover every sequence and agree with the manifest (and share no subject when the
export says subject-disjoint); the feature statistics are finite; each sequence has every file the
manifest promises.

The export may be damaged or hostile, so verification reads it without trusting it: every path read
from the manifest is confined to the export (:func:`~dualhuman_builder.fileio.confined_path`:
relative, no ``..``, no symbolic link leading out, regular files only) and only files the manifest
lists are read, each with a size cap; arrays are never read from a file whose size or checksum
failed (a JSON or text file that failed is still parsed, within its cap, to say more); an ``.npz``
member is decompressed only after its ``.npy`` header agrees with the schema (shape with the
manifest's frame count, dtype), with the zip's size record and with the bytes present (deflate
expands at most :data:`DEFLATE_MAX_RATIO` times), and within a per-sequence budget; malformed
manifest and schema entries are reported one by one. Nothing is unpickled. Anything at the top level
or in the export's own folders that the manifest does not list is a problem (not a warning): a
dataset is shared as a whole, so what is not in its manifest would ship unchecked.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import re
import zipfile
from collections import Counter
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from dualhuman_builder.errors import FormatError
from dualhuman_builder.export.features import FEATURE_DIM, FeatureLayout, motion_features
from dualhuman_builder.export.files import (
    FORMAT,
    FORMAT_VERSION,
    LABELS_JSON,
    MANIFEST,
    OWN_FOLDERS,
    PERSONS,
    SEQUENCE_JSON,
    check_seq_id,
)
from dualhuman_builder.fileio import open_confined, read_confined
from dualhuman_builder.labels import Vocabulary

#: Largest difference (feature units) between stored features and those recomputed from the joints.
FEATURE_TOLERANCE = 1e-4
#: Largest ``manifest.json`` verify parses (bytes): parsed JSON takes several times its size in memory.
MAX_MANIFEST_BYTES = 256 << 20
#: Largest other JSON or text file of an export verify parses (schema, labels, texts, splits).
MAX_JSON_BYTES = 64 << 20
#: Largest ``stats/*.npy`` (bytes): ``(FEATURE_DIM,)`` float32 and its header fit many times over.
MAX_STATS_BYTES = 1 << 20
#: Array bytes verify decompresses per sequence (motion, contact labels): about 100,000 frames.
MAX_SEQUENCE_ARRAY_BYTES = 1 << 30
#: Deflate's largest expansion, bytes out per compressed byte in: a member claiming more is forged.
DEFLATE_MAX_RATIO = 1032
#: Most members an ``.npz`` of the export may hold, and most schema array entries.
MAX_NPZ_MEMBERS = 64
MAX_SCHEMA_ARRAYS = 4096
#: Unlisted files named per folder in the problems (the rest are counted).
MAX_NAMED = 20
_HEX64 = re.compile(r"^[0-9a-f]{64}$")
#: Members of a sequence's files whose values verify inspects (the others: header only).
_INSPECTED = {"contacts.npz": {"labels_packed", "num_vertices", "frame_contact"},
              "targets.npz": {"joints_cam", "transl", "prob", "box", "frames", "views"},
              "keypoints.npz": {"joints", "frames", "views"}}  # fmt: skip


def _q(text: Any) -> str:
    """``text`` as it may be printed: itself when printable, else its repr (no control characters)."""
    text = str(text)
    return text if text.isprintable() else repr(text)


def _kind(value: Any) -> str:
    """A value from the file as a short description: scalars shown, containers named (never a deep repr)."""
    if value is None or isinstance(value, (bool, int, float)):
        return repr(value)
    if isinstance(value, str):
        return repr(value[:60]) + ("..." if len(value) > 60 else "")
    return f"a {type(value).__name__}"


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _parse_json(data: bytes) -> tuple[Any, str | None]:
    """``(document, None)`` or ``(None, why it is not valid UTF-8 JSON)``."""
    try:
        return json.loads(data.decode("utf-8")), None
    except RecursionError:
        return None, "not valid JSON (nested too deeply)"
    except (UnicodeDecodeError, ValueError) as e:  # ValueError: JSONDecodeError, an integer over Python's digit limit
        return None, f"not valid UTF-8 JSON ({e})"


# ------------------------------------------------------------------------------------ .npy / .npz
def _npy_header(f: BinaryIO, what: str) -> tuple[tuple[int, ...], np.dtype, bool, int]:
    """``(shape, dtype, fortran_order, data offset)`` of the ``.npy`` stream ``f``; ValueError for a
    foreign format, objects or records (verify reads plain numbers and text)."""
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        else:
            raise ValueError(f".npy format version {version}")
        offset = f.tell()
    except Exception as e:  # noqa: BLE001 - untrusted bytes: zipfile, zlib and numpy's header parser all raise
        raise ValueError(f"{what}: not a readable .npy header ({type(e).__name__}: {e})") from None
    if dtype.hasobject or dtype.kind in "OVMm" or dtype.itemsize == 0:
        raise ValueError(f"{what}: dtype {dtype} (objects, records or empty items are not export arrays)")
    if any(n < 0 for n in shape):
        raise ValueError(f"{what}: negative shape {shape}")
    return tuple(shape), dtype, bool(fortran), offset


def npy_from_bytes(data: bytes, what: str) -> np.ndarray:
    """The array of a whole ``.npy`` file in ``data``; its header must account for every byte."""
    shape, dtype, fortran, offset = _npy_header(io.BytesIO(data), what)
    count = math.prod(shape)
    if offset + count * dtype.itemsize != len(data):
        raise ValueError(f"{what}: header claims {offset + count * dtype.itemsize} bytes, the file has {len(data)}")
    return np.frombuffer(data, dtype, count, offset).reshape(shape, order="F" if fortran else "C")


class _Npz:
    """An ``.npz`` read without trusting it: member headers first, array data only when asked, within a
    byte budget, and only when the ``.npy`` header, the zip's size record and the compressed bytes
    present all agree on its size. ValueError for anything else."""

    def __init__(self, f: BinaryIO, rel: str):
        self.rel = rel
        try:
            self.zf = zipfile.ZipFile(f)
            infos = self.zf.infolist()
        except Exception as e:  # noqa: BLE001 - untrusted bytes: zipfile raises BadZipFile, ValueError, OSError, ...
            raise ValueError(f"not a readable .npz ({type(e).__name__}: {e})") from None
        if len(infos) > MAX_NPZ_MEMBERS:
            raise ValueError(f"{len(infos)} members, more than an export's {MAX_NPZ_MEMBERS}")
        names = [i.filename for i in infos]
        if len(set(names)) != len(names):
            raise ValueError("names a member twice")
        self.infos = {i.filename[:-4]: i for i in infos if i.filename.endswith(".npy")}
        self._headers: dict[str, tuple] = {}

    def header(self, name: str) -> tuple[tuple[int, ...], np.dtype, bool, int]:
        """``(shape, dtype, fortran_order, offset)`` of member ``name``, read from its first bytes only."""
        if name in self._headers:
            return self._headers[name]
        info, what = self.infos[name], f"array {_q(name)}"
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            raise ValueError(f"{what}: compression method {info.compress_type} (an export uses deflate or none)")
        if info.flag_bits & 0x1:
            raise ValueError(f"{what}: encrypted")
        try:
            with self.zf.open(info) as f:
                head = _npy_header(f, what)
        except ValueError:
            raise
        except Exception as e:  # noqa: BLE001 - untrusted bytes: BadZipFile, zlib.error, EOFError, ...
            raise ValueError(f"{what}: unreadable ({type(e).__name__}: {e})") from None
        shape, dtype, _fortran, offset = head
        size = offset + math.prod(shape) * dtype.itemsize
        if info.file_size != size:
            raise ValueError(f"{what}: its header claims {size} bytes, the zip records {info.file_size}")
        present = info.compress_size * (DEFLATE_MAX_RATIO if info.compress_type == zipfile.ZIP_DEFLATED else 1)
        if size > present + (1024 if info.compress_type == zipfile.ZIP_DEFLATED else 0):
            raise ValueError(f"{what}: claims {size} bytes from {info.compress_size} compressed bytes, more than "
                             "deflate can expand (a forged size)")  # fmt: skip
        self._headers[name] = head
        return head

    def array(self, name: str, budget: list[int]) -> np.ndarray:
        """Member ``name`` decompressed, its bytes taken from ``budget[0]`` (ValueError when it would pass it)."""
        shape, dtype, fortran, offset = self.header(name)
        count = math.prod(shape)
        nbytes = count * dtype.itemsize
        if nbytes > budget[0]:
            raise ValueError(f"array {_q(name)}: {nbytes} bytes, more than verify decompresses per sequence "
                             f"({budget[0]} bytes left; max_array_bytes sets the budget)")  # fmt: skip
        budget[0] -= nbytes
        try:
            with self.zf.open(self.infos[name]) as f:
                f.read(offset)
                data = f.read(nbytes)
                tail = f.read(1)  # reaching the end checks the CRC
        except Exception as e:  # noqa: BLE001 - untrusted bytes: BadZipFile, zlib.error, EOFError, ...
            raise ValueError(f"array {_q(name)}: unreadable ({type(e).__name__}: {e})") from None
        if len(data) != nbytes or tail:
            raise ValueError(f"array {_q(name)}: {len(data) + len(tail)} data bytes, its header says {nbytes}")
        return np.frombuffer(data, dtype, count).reshape(shape, order="F" if fortran else "C")


# ------------------------------------------------------------------------------------ the export's files
class _Export:
    """The export folder as verify reads it: only files the manifest lists and that are regular files
    inside it, unchanged since their size and SHA-256 were checked. Arrays are read only from files
    that passed; a JSON or text file that failed is still parsed (within its cap) to say what is wrong."""

    def __init__(self, root: Path, files: dict[str, dict], problems: list[str]):
        self.root, self.files, self.problems = root, files, problems
        self._seen: dict[str, tuple[int, int, int, int]] = {}  # rel -> (dev, inode, size, mtime) when checked
        self._good: set[str] = set()  # size and SHA-256 as the manifest says

    def check_files(self) -> None:
        """Size and SHA-256 of every listed file (a regular file inside the export) against the manifest."""
        for rel, rec in sorted(self.files.items()):
            try:
                with open_confined(self.root, rel, _q(rel)) as f:
                    st = os.fstat(f.fileno())
                    self._seen[rel] = (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
                    if st.st_size != rec["bytes"]:
                        self.problems.append(f"{_q(rel)}: {st.st_size} bytes, manifest says {rec['bytes']}")
                        continue
                    h = hashlib.sha256()
                    while block := f.read(1 << 20):
                        h.update(block)
            except FormatError as e:
                missing = e.message.endswith(": missing")
                self.problems.append(e.message + (" (listed in the manifest)" if missing else ""))
                continue
            except OSError as e:
                self.problems.append(f"{_q(rel)}: unreadable ({e.strerror})")
                continue
            if h.hexdigest() != rec["sha256"]:
                self.problems.append(f"{_q(rel)}: sha256 differs from the manifest (corrupted or modified)")
                continue
            self._good.add(rel)

    def open(self, rel: str, cap: int, unlisted: str | None = None, damaged: bool = False) -> BinaryIO | None:
        """A listed file opened (caller closes) if it holds at most ``cap`` bytes and passed its checks
        (``damaged``: or failed only its size or checksum); None when it is not read, with a problem
        unless one was reported already. ``unlisted``: the problem for a path the manifest does not
        list (None: say nothing, another check reports it)."""
        if rel not in self.files:
            if unlisted is not None:
                self.problems.append(f"{_q(rel)}: {unlisted} but not in its file list")
            return None
        if rel not in self._seen or (rel not in self._good and not damaged):
            return None
        size = self._seen[rel][2]
        if size > cap:
            self.problems.append(f"{_q(rel)}: {size} bytes, more than verify reads of such a file ({cap})")
            return None
        try:
            f = open_confined(self.root, rel, _q(rel))
            st = os.fstat(f.fileno())
        except (FormatError, OSError) as e:
            self.problems.append(getattr(e, "message", f"{_q(rel)}: unreadable ({e})"))
            return None
        if (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns) != self._seen[rel]:
            f.close()
            self.problems.append(f"{_q(rel)}: changed while being verified")
            return None
        return f

    def read(self, rel: str, cap: int, unlisted: str | None = None) -> bytes | None:
        """The bytes of a listed text or JSON file (see :meth:`open`; damaged ones too)."""
        f = self.open(rel, cap, unlisted, damaged=True)
        if f is None:
            return None
        with f:
            data = f.read(self._seen[rel][2] + 1)  # read(n) allocates n bytes up front: the size checked, not the cap
        if len(data) != self._seen[rel][2]:
            self.problems.append(f"{_q(rel)}: changed while being verified")
            return None
        return data

    def json(self, rel: str, unlisted: str | None = None) -> Any:
        """The parsed JSON of a listed file (None: unreadable, with its problem reported)."""
        data = self.read(rel, MAX_JSON_BYTES, unlisted)
        if data is None:
            return None
        doc, why = _parse_json(data)
        if why:
            self.problems.append(f"{_q(rel)}: {why}")
        return doc


def _unlisted(out: Path, files: dict[str, dict]) -> list[str]:
    """Entries at the top level and in the export's own folders that the manifest does not list."""
    problems: list[str] = []
    top = {rel for rel in files if "/" not in rel} | {MANIFEST}
    extra = []
    try:
        with os.scandir(out) as it:
            for e in it:
                if e.name in top:
                    continue
                if e.name in OWN_FOLDERS and not e.is_symlink() and e.is_dir(follow_symlinks=False):
                    continue
                extra.append(e.name)
    except OSError as e:
        return [f"{out}: cannot list the export folder ({e.strerror})"]
    for name in sorted(extra)[:MAX_NAMED]:
        what = ("a symbolic link" if (out / name).is_symlink() else "not a folder" if name in OWN_FOLDERS
                else "not part of the export")  # fmt: skip
        problems.append(f"{_q(name)}: {what} (the manifest does not list it); move it out of the export folder")
    if len(extra) > MAX_NAMED:
        problems.append(f"{len(extra) - MAX_NAMED} more entries at the top level that the manifest does not list")
    for sub in OWN_FOLDERS:
        folder = out / sub
        if sub in extra or not folder.is_dir():
            continue
        count, named = 0, []
        for dirpath, dirnames, filenames in os.walk(folder):  # links to folders are listed, never followed; errors skipped
            for name in filenames + [d for d in dirnames if os.path.islink(os.path.join(dirpath, d))]:
                rel = Path(dirpath, name).relative_to(out).as_posix()
                if rel not in files:
                    count += 1
                    if len(named) < MAX_NAMED:
                        named.append(rel)
        problems += [f"{_q(rel)}: not listed in the manifest" for rel in sorted(named)]
        if count > len(named):
            problems.append(f"{sub}/: {count - len(named)} more files that the manifest does not list")
    return problems


# ------------------------------------------------------------------------------------ manifest and schema
def _read_manifest(out: Path) -> tuple[dict | None, str | None]:
    path = out / MANIFEST
    if not os.path.lexists(path):
        return None, f"{path} does not exist: not a (finished) dataset export"
    try:
        data = read_confined(out, MANIFEST, MAX_MANIFEST_BYTES, str(path))
    except FormatError as e:
        return None, e.message
    except OSError as e:
        return None, f"{path}: unreadable ({e.strerror})"
    doc, why = _parse_json(data)
    if why:
        return None, f"{path} is {why}"
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        return None, f"{path} is not a {FORMAT} manifest"
    version = doc.get("format_version")
    if not _is_int(version) or version > FORMAT_VERSION:
        return None, f"{path}: format_version {_kind(version)}; this toolkit reads up to {FORMAT_VERSION}"
    return doc, None


def _table(manifest: dict, key: str, problems: list[str], default: Any = None) -> dict:
    value = manifest.get(key, default if default is not None else {})
    if not isinstance(value, dict):
        problems.append(f"{MANIFEST}: {key!r} must be an object, got {_kind(value)}")
        return {} if default is None else default
    return value


def _path_table(table: dict, where: str, names: tuple[str, ...] | None, defaults: dict[str, str],
                problems: list[str]) -> dict[str, str]:  # fmt: skip
    """``{name: relative path}`` of a manifest table of paths (``names``: the keys to take; None: all)."""
    out = {}
    for name in names if names is not None else sorted(table, key=str):
        rel = table.get(name, defaults.get(name))
        if rel is None:
            continue
        if not isinstance(rel, str):
            problems.append(f"{MANIFEST}: {where}[{_q(name)}] must be a path, got {_kind(rel)}")
            continue
        out[name] = rel
    return out


def _check_files_table(files: dict, problems: list[str]) -> dict[str, dict]:
    good = {}
    for rel, rec in files.items():
        if not (isinstance(rec, dict) and _is_int(rec.get("bytes")) and rec["bytes"] >= 0
                and isinstance(rec.get("sha256"), str) and _HEX64.match(rec["sha256"])):  # fmt: skip
            problems.append(f"{MANIFEST}: files[{_q(rel)}] needs 'bytes' (an integer >= 0) and 'sha256' (64 hex "
                            f"digits), got {_kind(rec)}")  # fmt: skip
            continue
        good[rel] = rec
    return good


def _sequence_info_problem(info: Any) -> str | None:
    if not isinstance(info, dict):
        return f"must be an object, got {_kind(info)}"
    if not isinstance(info.get("has", {}), dict):
        return f"'has' must be an object, got {_kind(info.get('has'))}"
    for key in ("render_views", "subjects"):
        value = info.get(key, [])
        if not isinstance(value, list) or not all(isinstance(x, str) or (x is None and key == "subjects")
                                                  for x in value):  # fmt: skip
            return f"{key!r} must be a list of names, got {_kind(value)}"
    if not isinstance(info.get("split", ""), str):
        return f"'split' must be a name, got {_kind(info.get('split'))}"
    return None


def _entry_problem(e: Any) -> str | None:
    """Why a schema ``arrays`` entry is malformed (None: usable)."""
    if not isinstance(e, dict):
        return f"must be an object, got {_kind(e)}"
    for key in ("file", "name", "dtype"):
        if not isinstance(e.get(key), str) or not e[key]:
            return f"{key!r} must be text, got {_kind(e.get(key))}"
    if not isinstance(e.get("stage", "motion"), str):
        return f"'stage' must be a name, got {_kind(e.get('stage'))}"
    rel = e["file"].replace("{seq_id}", "x")
    if any(c in rel for c in "{}\\\x00") or rel.startswith("/") or ".." in rel.split("/"):
        return f"'file' {_kind(e['file'])} is not a path inside the export with {{seq_id}}"
    shape = e.get("shape", [])
    if not (isinstance(shape, list) and len(shape) <= 32
            and all((_is_int(s) and s >= 0) or isinstance(s, str) for s in shape)):  # fmt: skip
        return f"'shape' must be a list of sizes and dimension names, got {_kind(shape)}"
    if e["dtype"] != "str":
        try:
            dtype = np.dtype(e["dtype"])
        except Exception:  # noqa: BLE001 - numpy's dtype parser raises TypeError, ValueError, SyntaxError, ...
            return f"'dtype' {_kind(e['dtype'])} is not a numpy dtype"
        if dtype.hasobject or dtype.kind in "OVMm":
            return f"'dtype' {_kind(e['dtype'])} is not a plain number or text type"
    return None


def _schema(doc: Any, problems: list[str]) -> tuple[list[dict], dict]:
    """The usable ``arrays`` entries and the integer ``dims`` of ``schema.json`` (each bad one reported)."""
    if doc is None:
        return [], {}
    if not isinstance(doc, dict):
        problems.append(f"schema.json: must be an object, got {_kind(doc)}")
        return [], {}
    dims, arrays = doc.get("dims", {}), doc.get("arrays", [])
    if not isinstance(dims, dict):
        problems.append(f"schema.json: 'dims' must be an object, got {_kind(dims)}")
        dims = {}
    if not isinstance(arrays, list):
        problems.append(f"schema.json: 'arrays' must be a list, got {_kind(arrays)}")
        arrays = []
    if len(arrays) > MAX_SCHEMA_ARRAYS:
        problems.append(f"schema.json: {len(arrays)} arrays, more than {MAX_SCHEMA_ARRAYS}; the rest are not checked")
    entries = []
    for i, e in enumerate(arrays[:MAX_SCHEMA_ARRAYS]):
        why = _entry_problem(e)
        if why:
            problems.append(f"schema.json: arrays[{i}]: {why}")
        else:
            entries.append(e)
    return entries, {k: v for k, v in dims.items() if _is_int(v)}


def _dim_value(sym, dims: dict, bound: dict[str, int]) -> int | None:
    """Size of a schema dim: an int, a known symbol, ``T-1``, or a symbol bound on first use (None)."""
    if isinstance(sym, int):
        return sym
    if sym in bound:
        return bound[sym]
    if sym in dims:
        return dims[sym]
    if sym.endswith("-1") and sym[:-2] in bound:
        return bound[sym[:-2]] - 1
    return None


def _check_array(name: str, shape: tuple[int, ...], dtype: np.dtype, entry: dict, dims: dict,
                 bound: dict[str, int]) -> str | None:  # fmt: skip
    want_dtype = entry["dtype"]
    if want_dtype == "str":
        if dtype.kind != "U":
            return f"{_q(name)} has dtype {dtype}, schema says str"
    elif dtype != np.dtype(want_dtype):
        return f"{_q(name)} has dtype {dtype}, schema says {_q(want_dtype)}"
    want = entry.get("shape", [])
    if len(shape) != len(want):
        return f"{_q(name)} has shape {shape}, schema says {_q(want)}"
    new = dict(bound)
    for sym, n in zip(want, shape):
        size = _dim_value(sym, dims, new)
        if size is None:
            new[sym] = n
        elif size != n:
            sizes = [_dim_value(s, dims, new) for s in want]
            return f"{_q(name)} has shape {shape}, schema says {_q(want)} (= {sizes})"
    bound.update(new)
    return None


# ------------------------------------------------------------------------------------ verify
def verify_export(out_dir: str | Path, check_features: bool = True,
                  max_array_bytes: int = MAX_SEQUENCE_ARRAY_BYTES) -> list[str]:  # fmt: skip
    """Problems found in the export under ``out_dir`` (empty list: OK). ``check_features``:
    recompute each sequence's motion features from its joints and compare (cheap: numpy only).
    ``max_array_bytes``: array bytes decompressed per sequence at most (a larger array is a problem)."""
    out = Path(out_dir)
    manifest, why = _read_manifest(out)
    if manifest is None:
        return [why]
    problems: list[str] = []
    files, sequences = manifest.get("files"), manifest.get("sequences")
    if not isinstance(files, dict) or not isinstance(sequences, dict):
        return [f"{out / MANIFEST}: lacks the 'files' or 'sequences' table"]
    files = _check_files_table(files, problems)
    version = manifest.get("format_version")
    # format version 1 computed the 6D rotations in another convention (decision 0025): compare the rest
    skip = (FeatureLayout.ROTATIONS,) if isinstance(version, int) and version < 2 else ()
    fps = manifest.get("fps")
    if fps is not None and (not isinstance(fps, (int, float)) or isinstance(fps, bool)):
        problems.append(f"{MANIFEST}: 'fps' must be a number, got {_kind(fps)}")
        fps = None
    split = _table(manifest, "split", problems)
    counts = _table(manifest, "counts", problems)

    # ---- checksums, and nothing besides what the manifest lists
    ex = _Export(out, files, problems)
    ex.check_files()
    problems += _unlisted(out, files)

    # ---- schema and per-sequence contents
    entries, dims = _schema(ex.json("schema.json", "the schema"), problems)
    vocab = None
    if "vocabulary" in manifest:
        rec = _table(manifest, "vocabulary", problems)
        rel = _path_table(rec, "vocabulary", ("file",), {"file": LABELS_JSON}, problems).get("file")
        doc = ex.json(rel, "named by the manifest's vocabulary") if rel is not None else None
        try:
            vocab = Vocabulary.from_dict(doc) if doc is not None else None
        except (ValueError, TypeError) as e:
            problems.append(f"{_q(rel)}: {e}")
        if vocab is not None and rec.get("size") != len(vocab):
            problems.append(f"{_q(rel)}: {len(vocab)} labels, manifest says {_kind(rec.get('size'))}")
    good_seqs: dict[str, dict] = {}
    for sid, info in sorted(sequences.items()):
        try:
            check_seq_id(sid)
        except ValueError as e:
            problems.append(_q(str(e)))
            continue
        why = _sequence_info_problem(info)
        if why:
            problems.append(f"{MANIFEST}: sequences[{sid!r}]: {why}")
            continue
        good_seqs[sid] = info
        problems += _verify_sequence(ex, sid, info, entries, dims, fps, check_features, vocab, max_array_bytes, skip)

    # ---- splits
    table = split.get("files", {"train": "splits/train.txt", "test": "splits/test.txt"})
    if not isinstance(table, dict):
        problems.append(f"{MANIFEST}: 'split.files' must be an object, got {_kind(table)}")
        table = {}
    split_files = _path_table(table, "split.files", None, {}, problems)
    splits: dict[str, list[str]] = {}
    for name, rel in split_files.items():
        data = ex.read(rel, MAX_JSON_BYTES, "named by the manifest's split.files")
        try:
            splits[name] = [s for s in data.decode("utf-8").splitlines() if s.strip()] if data is not None else []
        except UnicodeDecodeError as e:
            problems.append(f"{_q(rel)}: unreadable ({e})")
            splits[name] = []
        dups = sorted(s for s, n in Counter(splits[name]).items() if n > 1)
        if dups:
            problems.append(f"{_q(rel)}: lists {[_q(s) for s in dups[:10]]} more than once")
    names = sorted(splits)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            both = sorted(set(splits[a]) & set(splits[b]))
            if both:
                problems.append(f"splits {_q(a)} and {_q(b)} overlap: {[_q(s) for s in both[:10]]}")
    listed = set().union(*splits.values()) if splits else set()
    if sorted(set(sequences) - listed):
        problems.append(f"sequences in no split: {[_q(s) for s in sorted(set(sequences) - listed)[:10]]}")
    if sorted(listed - set(sequences)):
        unknown = [_q(s) for s in sorted(listed - set(sequences))[:10]]
        problems.append(f"splits name sequences the manifest does not have: {unknown}")
    for name, ids in splits.items():
        wrong = [s for s in ids if s in good_seqs and good_seqs[s].get("split") != name]
        if wrong:
            problems.append(f"sequences {[_q(s) for s in wrong[:10]]} are in splits/{_q(name)}.txt but the manifest "
                            "says otherwise")  # fmt: skip
    if split.get("subject_disjoint") and len(names) >= 2:
        subj = {n: {x for s in ids if s in good_seqs for x in good_seqs[s].get("subjects", [])}
                for n, ids in splits.items()}  # fmt: skip
        for i, a in enumerate(names):
            for b in names[i + 1 :]:
                shared = sorted(subj[a] & subj[b], key=str)
                if shared:
                    problems.append(f"subject-disjoint export, but subjects {[_q(s) for s in shared[:10]]} are in both "
                                    f"{_q(a)} and {_q(b)}")  # fmt: skip

    # ---- statistics and counts
    stats = _path_table(_table(manifest, "stats", problems), "stats", ("mean", "std"),
                        {"mean": "stats/mean.npy", "std": "stats/std.npy"}, problems)  # fmt: skip
    for stat, rel in stats.items():
        f = ex.open(rel, MAX_STATS_BYTES, "named by the manifest's stats")
        if f is None:
            continue
        with f:
            data = f.read(MAX_STATS_BYTES)  # at most its listed size, checked against the cap by open()
        try:
            arr = npy_from_bytes(data, _q(rel))
        except ValueError as e:
            problems.append(f"{_q(rel)}: unreadable ({e})")
            continue
        if arr.shape != (FEATURE_DIM,) or arr.dtype != np.float32:
            problems.append(f"{_q(rel)}: shape {arr.shape} dtype {arr.dtype}, expected ({FEATURE_DIM},) float32")
        elif not np.isfinite(arr).all() or (stat == "std" and (arr <= 0).any()):
            problems.append(f"{_q(rel)}: holds NaN/inf" + (" or non-positive values" if stat == "std" else ""))
    if counts.get("sequences") != len(sequences):
        problems.append(f"manifest counts {_kind(counts.get('sequences'))} sequences but lists {len(sequences)}")
    for name, ids in splits.items():
        if name in counts and counts[name] != len(ids):
            problems.append(f"manifest counts {_kind(counts[name])} {_q(name)} sequences, splits/{_q(name)}.txt "
                            f"lists {len(ids)}")  # fmt: skip
    return problems


def _verify_sequence(ex: _Export, sid: str, info: dict[str, Any], entries: list, dims: dict, fps, check_features: bool,
                     vocab: Vocabulary | None, max_array_bytes: int, skip_columns: tuple = ()) -> list[str]:  # fmt: skip
    problems: list[str] = []
    files = ex.files
    base = f"sequences/{sid}"
    has = info.get("has", {})
    T = info.get("frames")
    if not _is_int(T) or T < 2:
        return [f"{base}: manifest gives {_kind(T)} frames"]
    promised = {"motion": ["motion.npz"], "contacts": ["contacts.npz", "contact_events.json"], "text": ["text.json"],
                "cameras": ["cameras.json"], "keypoints": ["renders/keypoints.npz"],
                "targets": ["renders/targets.npz", "renders/keypoints.npz", "cameras.json"]}  # fmt: skip
    needed = [SEQUENCE_JSON, "text.json"] + [f for stage, fs in promised.items() if has.get(stage) for f in fs]
    views = info.get("render_views", [])
    for view in views:
        if not any(r.startswith(f"{base}/renders/views/{view}/") for r in files):
            problems.append(f"{base}: the manifest promises renders of view {_q(view)!r}, none are listed")
    if has.get("renders") and not views:
        problems.append(f"{base}: has renders but names no views")
    for rel in needed:
        if f"{base}/{rel}" not in files:
            problems.append(f"{base}/{rel}: promised by the manifest but not in its file list")
    if not has.get("motion"):
        problems.append(f"{base}: the manifest says it has no motion")

    # ---- arrays: headers against the schema, then the values verify inspects, within the budget
    bound: dict[str, int] = {"T": T}
    budget = [max_array_bytes]
    opened: dict[str, tuple[BinaryIO, _Npz] | None] = {}
    failed: set[tuple[str, str]] = set()  # (file, array) whose header disagreed with the schema: never decompressed

    def npz(rel: str) -> _Npz | None:
        if rel not in opened:
            f = ex.open(rel, 1 << 62)
            try:
                opened[rel] = (f, _Npz(f, rel)) if f is not None else None
            except ValueError as e:
                f.close()
                problems.append(f"{_q(rel)}: {e}")
                opened[rel] = None
        return opened[rel][1] if opened[rel] else None

    def header(z: _Npz, name: str):
        try:
            return z.header(name)
        except ValueError as e:
            problems.append(f"{_q(z.rel)}: {e}")
            failed.add((z.rel, name))
            return None

    def values(rel: str, names) -> dict[str, np.ndarray]:
        z = npz(rel) if rel in files else None
        out: dict[str, np.ndarray] = {}
        for name in sorted(z.infos if z is not None else ()):
            if (names is not None and name not in names) or (rel, name) in failed or header(z, name) is None:
                continue
            if names is None and z.header(name)[1].kind != "f":
                continue
            try:
                out[name] = z.array(name, budget)
            except ValueError as e:
                problems.append(f"{_q(rel)}: {e}")
                failed.add((rel, name))
        return out

    try:
        for entry in entries:
            rel = entry["file"].replace("{seq_id}", sid)
            if not has.get(entry.get("stage", "motion")) or rel not in files:
                continue
            z = npz(rel)
            if z is None:
                continue
            name = entry["name"]
            if name not in z.infos:
                problems.append(f"{_q(rel)}: lacks array {_q(name)!r} (schema)")
                continue
            head = header(z, name) if (rel, name) not in failed else None
            if head is None:
                continue
            msg = _check_array(name, head[0], head[1], entry, dims, bound)
            if msg:
                problems.append(f"{_q(rel)}: {msg}")
                failed.add((rel, name))
        motion = values(f"{base}/motion.npz", None)  # every float array: no NaN/inf
        contacts = values(f"{base}/contacts.npz", _INSPECTED["contacts.npz"]) if has.get("contacts") else {}
        targets = keypoints = {}
        if has.get("targets"):
            targets = values(f"{base}/renders/targets.npz", _INSPECTED["targets.npz"])
            keypoints = values(f"{base}/renders/keypoints.npz", _INSPECTED["keypoints.npz"])
    finally:
        for item in opened.values():
            if item:
                item[0].close()

    for name, arr in motion.items():
        if not np.isfinite(arr).all():
            problems.append(f"{base}/motion.npz: {_q(name)} holds NaN or inf")
    if check_features and isinstance(fps, (int, float)) and fps > 0:
        for p in PERSONS:
            j, f = motion.get(f"{p}.joints"), motion.get(f"{p}.features")
            if j is None or f is None or j.shape != (T, 22, 3) or f.shape != (T - 1, FEATURE_DIM):
                continue
            if not (np.isfinite(j).all() and np.isfinite(f).all()):
                continue
            try:
                with np.errstate(all="ignore"):
                    diff = np.abs(motion_features(j, fps) - f)
                    for cols in skip_columns:  # columns an older format version defined otherwise
                        diff[:, cols] = 0.0
                    err = float(diff.max())
            except (ValueError, ArithmeticError) as e:
                problems.append(f"{base}/motion.npz: features of {p}.joints cannot be recomputed ({e})")
                continue
            if not err <= FEATURE_TOLERANCE:  # NaN (from overflowing joints) fails too
                problems.append(f"{base}/motion.npz: {p}.features differ from those of {p}.joints by {err:.3g}")
    if all(k in contacts for k in ("labels_packed", "num_vertices", "frame_contact")):
        V, nv = dims.get("V"), contacts["num_vertices"]
        packed, flags = contacts["labels_packed"], contacts["frame_contact"]
        if nv.shape != () or nv.dtype.kind not in "iu":
            problems.append(f"{base}/contacts.npz: num_vertices is not one integer")
        elif V is not None and int(nv) != V:
            problems.append(f"{base}/contacts.npz: num_vertices {int(nv)}, body model has {V}")
        elif packed.ndim == 3 and packed.dtype == np.uint8 and flags.shape == (T,) and flags.dtype.kind in "biu" \
                and packed.shape[1] == T:
            any_contact = (packed != 0).any(axis=(0, 2))
            if not np.array_equal(any_contact, flags.astype(bool)):
                problems.append(f"{base}/contacts.npz: frame_contact disagrees with the labels")
    if has.get("contacts") and f"{base}/contact_events.json" in files:
        events = ex.json(f"{base}/contact_events.json")
        if events is not None and not (isinstance(events, list) and all(isinstance(e, dict) for e in events)):
            problems.append(f"{base}/contact_events.json: not a list of events")
    if f"{base}/text.json" in files:
        text = ex.json(f"{base}/text.json")
        if text is not None:
            ok = isinstance(text, dict) and all(
                isinstance(text.get(k), list) and all(isinstance(t, str) for t in text[k]) for k in ("labels", "texts")
            )
            if not ok:
                problems.append(f"{base}/text.json: needs lists of strings 'labels' and 'texts'")
            elif bool(text["texts"]) != bool(has.get("text")):
                problems.append(f"{base}/text.json: {len(text['texts'])} texts, manifest says has text = "
                                f"{_kind(has.get('text'))}")  # fmt: skip
            elif vocab is not None:
                unknown = [x for x in text["labels"] if x not in vocab]
                if unknown:
                    problems.append(f"{base}/text.json: labels {[_q(x) for x in unknown[:10]]} are not in labels.json")
                elif text.get("multi_hot") != vocab.multi_hot(text["labels"]).tolist():
                    problems.append(f"{base}/text.json: multi_hot disagrees with its labels")
    if has.get("cameras") and f"{base}/cameras.json" in files:
        cams = ex.json(f"{base}/cameras.json")
        if cams is not None:
            listed = cams.get("cameras", []) if isinstance(cams, dict) else []
            listed = listed if isinstance(listed, list) else []
            names = {c.get("name") for c in listed if isinstance(c, dict) and isinstance(c.get("name"), str)}
            missing = sorted(set(views) - names)
            if not names:
                problems.append(f"{base}/cameras.json: no cameras")
            elif missing:
                problems.append(f"{base}: rendered views {[_q(v) for v in missing]} have no camera in cameras.json")
    if has.get("targets") and f"{base}/cameras.json" in files:
        problems += _check_targets(base, targets, keypoints, ex.json(f"{base}/cameras.json"))
    seq_doc = ex.json(f"{base}/{SEQUENCE_JSON}")
    if isinstance(seq_doc, dict) and seq_doc.get("frames") != T:
        problems.append(f"{base}/{SEQUENCE_JSON}: {_kind(seq_doc.get('frames'))} frames, manifest says {T}")
    return problems


def _check_targets(base: str, targets: dict[str, np.ndarray], keypoints: dict[str, np.ndarray], cams: Any) -> list[str]:
    """Problems of a render's ``targets.npz`` (arrays whose headers passed the schema) against its
    ``keypoints.npz`` and ``cameras.json``: finite values, the same views and frames, ``joints_cam``
    projected by each camera's ``K`` within :data:`~.writer.KEYPOINT_TOLERANCE_PX` of the keypoints,
    ``transl`` the normalised root of ``joints_cam``, ``prob`` the keypoints' visible share, boxes
    inside the image."""
    from dualhuman_builder.export.writer import KEYPOINT_TOLERANCE_PX, TARGET_ARRAYS, normalised_root, projection_error

    rel = f"{base}/renders/targets.npz"
    if any(k not in targets for k in TARGET_ARRAYS) or any(k not in keypoints for k in ("joints", "frames", "views")):
        return []  # a missing or malformed array is reported by the schema check
    for name in ("joints_cam", "transl", "prob", "box"):
        if not np.isfinite(targets[name]).all():
            return [f"{rel}: {name} holds NaN or inf"]
    if targets["views"].tolist() != keypoints["views"].tolist() or not np.array_equal(targets["frames"],
                                                                                      keypoints["frames"]):  # fmt: skip
        return [f"{rel}: views or frames differ from renders/keypoints.npz's"]
    listed = cams.get("cameras") if isinstance(cams, dict) else None
    by_name = {c.get("name"): c for c in listed if isinstance(c, dict)} if isinstance(listed, list) else {}
    problems: list[str] = []
    kp, jc = keypoints["joints"], targets["joints_cam"].astype(np.float64)
    prob = targets["prob"]
    if prob.min(initial=0.0) < 0.0 or prob.max(initial=0.0) > 1.0:
        problems.append(f"{rel}: prob outside [0, 1]")
    elif np.abs(prob - (kp[..., 2] > 0.5).mean(axis=-1)).max(initial=0.0) > 1e-5:
        problems.append(f"{rel}: prob is not the share of visible joints in renders/keypoints.npz")
    for c, view in enumerate(targets["views"].tolist()):
        cam = by_name.get(view)
        try:
            K = np.asarray(cam["K"], dtype=np.float64).reshape(3, 3)
            w, h = float(cam["width"]), float(cam["height"])
        except (KeyError, TypeError, ValueError):
            problems.append(f"{base}/cameras.json: no usable K, width and height for view {_q(view)!r}")
            continue
        if not (np.isfinite(K).all() and K[0, 0] > 0 and w > 0 and h > 0):
            problems.append(f"{base}/cameras.json: no usable K, width and height for view {_q(view)!r}")
            continue
        with np.errstate(all="ignore"):
            err = projection_error(jc[c], K, kp[c])
            tr = np.abs(normalised_root(jc[c, :, :, 0], K, w, h) - targets["transl"][c]).max(initial=0.0)
        if not err <= KEYPOINT_TOLERANCE_PX + 1e-3:
            problems.append(f"{rel}: joints_cam of view {_q(view)!r} projected by its K are {err:.3g} px from "
                            "renders/keypoints.npz's joints")  # fmt: skip
        if not tr <= 1e-3:
            problems.append(f"{rel}: transl of view {_q(view)!r} differs from the normalised root of joints_cam by {tr:.3g}")
        b = targets["box"][c]
        if (b[..., 0] > b[..., 2]).any() or (b[..., 1] > b[..., 3]).any() or b.min(initial=0.0) < 0 \
                or (b[..., [0, 2]] > w).any() or (b[..., [1, 3]] > h).any():  # fmt: skip
            problems.append(f"{rel}: a box of view {_q(view)!r} is not inside the {w:g} x {h:g} image")
    return problems


__all__ = ["verify_export", "FEATURE_TOLERANCE", "MAX_SEQUENCE_ARRAY_BYTES"]

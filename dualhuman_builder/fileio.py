"""Crash-safe file writing and the versioned ``.npz`` container every core type is saved in.

Crash safety: artifacts are written to a hidden temporary name in the destination folder, flushed
to disk, then renamed over the final name (``os.replace`` is atomic on POSIX). A process killed
mid-write leaves at most a ``.*.partial`` file, which no reader mistakes for a complete artifact
and :func:`remove_partials` sweeps away.

Container: a NumPy ``.npz`` (zip of ``.npy``) holding the arrays plus ``__meta__``, UTF-8 JSON
bytes with ``kind`` (e.g. ``"SkeletonTrack"``), ``format_version`` and free metadata. Reading never
unpickles (``allow_pickle=False``), so a file from someone else cannot run code.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import secrets
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from dualhuman_builder import __version__
from dualhuman_builder.errors import FormatError, FormatVersionError

PARTIAL_SUFFIX = ".partial"


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success rename it to ``path`` atomically.

    On an exception the temporary file is removed and ``path`` is left untouched (an older
    complete version stays in place).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}{PARTIAL_SUFFIX}")
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
        _fsync_dir(path.parent)
    finally:
        if tmp.exists():
            tmp.unlink()


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "wb", **kwargs) -> Iterator[io.IOBase]:
    """Open a file for writing that only appears under ``path`` once closed without error."""
    with atomic_path(path) as tmp:
        with open(tmp, mode, **kwargs) as f:
            yield f
            f.flush()


def remove_partials(folder: str | Path) -> list[Path]:
    """Delete leftovers of interrupted atomic writes under ``folder``; return what was removed."""
    removed = []
    folder = Path(folder)
    if not folder.exists():
        return removed
    for p in folder.rglob(f".*{PARTIAL_SUFFIX}"):
        p.unlink(missing_ok=True)
        removed.append(p)
    return removed


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB chunks."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def save_npz(
    path: str | Path,
    kind: str,
    format_version: int,
    arrays: Mapping[str, np.ndarray],
    meta: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``arrays`` and JSON ``meta`` as a versioned container, atomically. Returns ``path``."""
    header = {
        "kind": kind,
        "format_version": int(format_version),
        "written_by": f"dualhuman-builder {__version__}",
        "meta": dict(meta or {}),
    }
    payload = {name: np.asarray(a) for name, a in arrays.items()}
    for name, a in payload.items():
        if a.dtype == object:
            raise TypeError(f"array {name!r} has dtype object, which cannot be saved without pickle")
    payload["__meta__"] = np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8)
    with atomic_open(path, "wb") as f:
        np.savez(f, **payload)
    return Path(path)


def load_npz(
    path: str | Path,
    kind: str,
    reader_version: int,
    required: tuple[str, ...] = (),
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read a container written by :func:`save_npz`; return ``(arrays, meta)``.

    Raises :class:`FormatError` for a missing, truncated or foreign file, or one of another kind,
    and :class:`FormatVersionError` when it was written by a newer format version.
    """
    path = Path(path)
    if not path.is_file():
        raise FormatError("no such file", path=path, fix="check the path")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {name: z[name] for name in z.files}
    except Exception as e:  # noqa: BLE001 - damaged bytes: zipfile, zlib, and numpy's header parser (SyntaxError, TokenError) all raise
        raise FormatError(
            f"not a readable dualhuman {kind} file ({e})",
            path=path,
            fix="the file is truncated or corrupt; re-run the stage that wrote it",
        ) from e
    if "__meta__" not in arrays:
        raise FormatError(
            f"not a dualhuman {kind} file (no __meta__ record)",
            path=path,
            fix="this .npz was not written by dualhuman-builder",
        )
    try:
        header = json.loads(arrays.pop("__meta__").tobytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise FormatError(f"corrupt __meta__ record ({e})", path=path) from e
    if header.get("kind") != kind:
        raise FormatError(
            f"holds a {header.get('kind')!r}, expected a {kind!r}",
            path=path,
            fix=f"pass a {kind} file",
        )
    version = header.get("format_version")
    if not isinstance(version, int) or version < 1:
        raise FormatError(f"invalid format_version {version!r}", path=path)
    if version > reader_version:
        raise FormatVersionError(
            f"{kind} format version {version} (written by {header.get('written_by', 'unknown')}); "
            f"this dualhuman-builder {__version__} reads versions up to {reader_version}",
            path=path,
            fix="upgrade dualhuman-builder (git pull && scripts/setup.sh)",
        )
    missing = [name for name in required if name not in arrays]
    if missing:
        raise FormatError(f"{kind} lacks arrays {missing}", path=path, fix="re-run the stage that wrote it")
    meta = header.get("meta", {})
    meta["_format_version"] = version
    return arrays, meta

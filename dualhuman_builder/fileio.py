"""Crash-safe file writing and the versioned ``.npz`` container every core type is saved in.

Crash safety: artifacts are written to a hidden temporary name in the destination folder, flushed
to disk, then renamed over the final name (``os.replace`` is atomic on POSIX). A process killed
mid-write leaves at most a ``.*.partial`` file, which no reader mistakes for a complete artifact
and :func:`remove_partials` sweeps away.

Confinement: a path read from a file (a manifest's file list, a split file's name) is resolved with
:func:`confined_path` and read with :func:`open_confined` / :func:`read_confined`, so that it can
only reach regular files inside the folder that file describes, and never more bytes than allowed.

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
import stat
from pathlib import Path, PurePosixPath
from typing import Any, BinaryIO, Iterator, Mapping

import numpy as np

from dualhuman_builder import __version__
from dualhuman_builder.errors import FormatError, FormatVersionError

PARTIAL_SUFFIX = ".partial"


def fsync_dir(folder: Path) -> None:
    """Make a folder's entries (files created, renamed or removed in it) durable; best effort."""
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
        fsync_dir(path.parent)
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


def _what(rel: object, what: str | None) -> str:
    return what if what is not None else f"path {rel!r:.200}"


def confined_path(folder: str | Path, rel: object, what: str | None = None) -> Path:
    """Where ``rel``, a path read from a file that describes ``folder``, points, confined to ``folder``.

    ``rel`` must be a non-empty relative POSIX path (text without NUL, backslash or ``..`` parts) that
    still lies inside ``folder`` once symbolic links are resolved. Returns the resolved path (it need
    not exist). FormatError otherwise, its message starting with ``what`` (default: ``path '<rel>'``):
    whoever wrote the file must not make a reader open ``/etc/passwd``, ``/dev/zero`` or anything else
    outside what they sent.
    """
    where, what = Path(folder), _what(rel, what)
    if not isinstance(rel, str):
        raise FormatError(f"{what}: must be a relative path (text), got {type(rel).__name__}", path=where)
    parts = PurePosixPath(rel).parts
    if not rel or "\x00" in rel or "\\" in rel or rel.startswith("/") or ".." in parts or not parts:
        raise FormatError(f"{what}: not a relative path inside the folder (absolute, empty, '..' or a backslash)",
                          path=where, fix="only paths relative to the folder, without '..', are allowed")  # fmt: skip
    try:
        root = where.resolve()
        target = (root / rel).resolve()
    except (OSError, RuntimeError) as e:  # RuntimeError: a symlink loop
        raise FormatError(f"{what}: cannot be resolved ({e})", path=where) from None
    if target == root or not target.is_relative_to(root):
        raise FormatError(f"{what}: leads out of the folder (through a symbolic link)", path=where,
                          fix="replace the link by the file it points to, or remove it")  # fmt: skip
    return target


def open_confined(folder: str | Path, rel: object, what: str | None = None) -> BinaryIO:
    """``rel`` (see :func:`confined_path`) opened for reading in binary mode; FormatError unless it is
    a regular file (a missing file, a folder, FIFO, device or socket is refused; a FIFO is opened
    without blocking, so it cannot hang the reader)."""
    target, what = confined_path(folder, rel, what), _what(rel, what)
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(target, flags)
    except FileNotFoundError:
        raise FormatError(f"{what}: missing", path=target) from None
    except OSError as e:
        raise FormatError(f"{what}: cannot be opened ({e.strerror})", path=target) from None
    try:
        regular = stat.S_ISREG(os.fstat(fd).st_mode)
    except OSError:
        regular = False
    if not regular:
        os.close(fd)
        raise FormatError(f"{what}: not a regular file", path=target)
    return os.fdopen(fd, "rb")


def read_confined(folder: str | Path, rel: object, max_bytes: int, what: str | None = None) -> bytes:
    """The bytes of ``rel`` (see :func:`open_confined`); FormatError, before reading, when the file holds
    more than ``max_bytes`` bytes (and when it grows past them while read)."""
    what = _what(rel, what)
    with open_confined(folder, rel, what) as f:
        size = os.fstat(f.fileno()).st_size
        if size > max_bytes:
            raise FormatError(f"{what}: {size} bytes, more than the {max_bytes} allowed", path=Path(folder) / rel)
        data = f.read(size + 1)  # read(n) allocates n bytes up front: ask for what fstat says is there
        while size < len(data) <= max_bytes and (block := f.read(min(1 << 20, max_bytes + 1 - len(data)))):
            data += block  # the file grew while read
    if len(data) > max_bytes:
        raise FormatError(f"{what}: grew past {max_bytes} bytes while read", path=Path(folder) / rel)
    return data

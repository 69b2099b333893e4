"""Training shards: the folder export repacked as WebDataset tar shards, and a safe reader.

WebDataset convention: plain (uncompressed) POSIX tar files; one sample per sequence; a sample's
members are consecutive and named ``<key>.<ext>``, where the key is the ``seq_id`` (which has no
dots) and the extension names the file: ``sequence.json``, ``motion.npz``, ``contacts.npz``,
``contact_events.json``, ``text.json``, ``cameras.json``, ``keypoints.npz`` (the render's 2D
keypoints), ``targets.npz`` (the image models' targets per camera and rendered frame). Images stay
in the folder layout. Shards are named ``<split>-000000.tar``, ... (the
brace pattern ``<split>-{000000..NNNNNN}.tar`` of ``webdataset``) and written byte-deterministically
(mtime 0, uid 0, mode 0644); a new shard starts when the next sample would push a shard past
``max_bytes`` (a single larger sample gets a shard of its own). Next to them: ``<split>.json`` (the
shard index: samples, keys, bytes and sha256 per shard) and ``stats/mean.npy``, ``stats/std.npy``.

:func:`iter_shards` reads shards back without extracting anything to disk and rejects members
with absolute paths, ``..`` components, links or any non-regular member, and samples whose
members are not consecutive.
"""

from __future__ import annotations

import hashlib
import io
import json
import tarfile
from pathlib import Path, PurePosixPath
from typing import Any, Collection, Iterable, Iterator

from dualhuman_builder.errors import FormatError
from dualhuman_builder.export.files import (
    FORMAT_VERSION,
    SEQUENCE_JSON,
    check_seq_id,
    json_bytes,
    read_manifest,
    read_npz,
)
from dualhuman_builder.fileio import atomic_open, read_confined

#: Largest split list or statistics file read from an export (bytes); paths from its manifest are
#: read confined to the export (:func:`~dualhuman_builder.fileio.read_confined`).
MAX_LIST_BYTES = 64 << 20

DEFAULT_MAX_BYTES = 256 * 2**20
#: Sequence files carried in a sample, as (path in the sequence folder, member extension).
SAMPLE_FILES = (
    (SEQUENCE_JSON, "sequence.json"),
    ("motion.npz", "motion.npz"),
    ("contacts.npz", "contacts.npz"),
    ("contact_events.json", "contact_events.json"),
    ("text.json", "text.json"),
    ("cameras.json", "cameras.json"),
    ("renders/keypoints.npz", "keypoints.npz"),
    ("renders/targets.npz", "targets.npz"),
)
_BLOCK = 512
_RECORD = 20 * _BLOCK


def _member_size(n: int) -> int:
    return _BLOCK + -(-n // _BLOCK) * _BLOCK


def _tar_info(name: str, size: int) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.size = size
    info.mtime = 0
    info.mode = 0o644
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    info.type = tarfile.REGTYPE
    return info


def _shard_bytes(samples: list[tuple[str, list[tuple[str, bytes]]]]) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.PAX_FORMAT) as tf:
        for key, members in samples:
            for ext, data in members:
                tf.addfile(_tar_info(f"{key}.{ext}", len(data)), io.BytesIO(data))
    return buf.getvalue()


def _split_ids(out: Path, manifest: dict, split: str) -> list[str]:
    if split == "all":
        return sorted(manifest["sequences"])
    table = manifest.get("split", {}).get("files", {}) if isinstance(manifest.get("split"), dict) else {}
    rel = table.get(split) if isinstance(table, dict) else None
    if rel is None:
        names = sorted(table) if isinstance(table, dict) else []
        raise ValueError(f"unknown split {split!r}; this export has {names} or 'all'")
    data = read_confined(out, rel, MAX_LIST_BYTES, f"split file {rel!r:.200} of {out}")
    try:
        return [s for s in data.decode("utf-8").splitlines() if s.strip()]
    except UnicodeDecodeError as e:
        raise ValueError(f"{out / rel}: not UTF-8 ({e})") from None


def write_shards(out_dir: str | Path, shard_dir: str | Path, max_bytes: int = DEFAULT_MAX_BYTES,
                 split: str = "train") -> list[Path]:  # fmt: skip
    """Pack the sequences of ``split`` (``train``, ``test`` or ``all``) of the export in ``out_dir``
    into WebDataset tar shards of at most ``max_bytes`` bytes under ``shard_dir``.

    Every file is checked against the manifest's sha256 while it is read (ValueError on a mismatch:
    run ``verify``). Shards of the same split left from an earlier run are removed. Returns the
    shard paths in order.
    """
    if not isinstance(max_bytes, int) or max_bytes < 4 * _RECORD:
        raise ValueError(f"max_bytes must be an int of at least {4 * _RECORD}, got {max_bytes!r}")
    if not isinstance(split, str) or not split.isidentifier():
        raise ValueError(f"split must be a name such as 'train', 'test' or 'all', got {split!r}")
    out = Path(out_dir)
    manifest = read_manifest(out)
    files = manifest["files"]
    ids = _split_ids(out, manifest, split)
    if not ids:
        raise ValueError(f"split {split!r} of {out} has no sequences")
    shard_dir = Path(shard_dir)
    shard_dir.mkdir(parents=True, exist_ok=True)

    groups: list[list[tuple[str, list[tuple[str, bytes]]]]] = [[]]
    size = _RECORD
    for sid in ids:
        if sid not in manifest["sequences"]:
            raise ValueError(f"split {split!r} names {sid!r}, which the manifest does not list")
        check_seq_id(sid)
        members = []
        for rel, ext in SAMPLE_FILES:
            key = f"sequences/{sid}/{rel}"
            if key not in files:
                continue
            try:
                data = read_confined(out, key, int(files[key].get("bytes", 0)), f"{key} of {out}")
            except FormatError as e:
                raise FormatError(e.message, fix=f"run `dualhuman export verify {out}`") from None
            if hashlib.sha256(data).hexdigest() != files[key]["sha256"]:
                raise ValueError(f"{out / key}: sha256 differs from the manifest; run `dualhuman export verify {out}`")
            members.append((ext, data))
        sample_size = sum(_member_size(len(d)) + _BLOCK for _, d in members)  # + room for a PAX header each
        if groups[-1] and size + sample_size > max_bytes:
            groups.append([])
            size = _RECORD
        groups[-1].append((sid, members))
        size += sample_size

    paths, index = [], []
    for i, group in enumerate(groups):
        data = _shard_bytes(group)
        path = shard_dir / f"{split}-{i:06d}.tar"
        with atomic_open(path, "wb") as f:
            f.write(data)
        paths.append(path)
        index.append({"name": path.name, "samples": len(group), "keys": [k for k, _ in group], "bytes": len(data),
                      "sha256": hashlib.sha256(data).hexdigest()})  # fmt: skip
    keep = {p.name for p in paths}
    for old in shard_dir.glob(f"{split}-*.tar"):
        if old.name not in keep:
            old.unlink()
    for stat in ("mean", "std"):
        rel = manifest.get("stats", {}).get(stat, f"stats/{stat}.npy")
        data = read_confined(out, rel, MAX_LIST_BYTES, f"statistics file {rel!r:.200} of {out}")
        with atomic_open(shard_dir / "stats" / f"{stat}.npy", "wb") as f:
            f.write(data)
    doc = {"format": "dualhuman-shards", "format_version": FORMAT_VERSION, "split": split,
           "pattern": f"{split}-{{000000..{len(paths) - 1:06d}}}.tar", "samples": len(ids), "fps": manifest["fps"],
           "feature_dim": manifest["feature_dim"], "toolkit_version": manifest["toolkit_version"],
           "manifest_sha256": hashlib.sha256((out / "manifest.json").read_bytes()).hexdigest(), "shards": index}  # fmt: skip
    with atomic_open(shard_dir / f"{split}.json", "wb") as f:
        f.write(json_bytes(doc))
    return paths


def _check_member(path, m: tarfile.TarInfo) -> tuple[str, str]:
    name = m.name
    p = PurePosixPath(name)
    if not name or name.startswith("/") or p.is_absolute() or "\\" in name or (len(name) > 1 and name[1] == ":"):
        raise ValueError(f"{path}: member {name!r} has an absolute path; refusing the shard")
    if ".." in p.parts:
        raise ValueError(f"{path}: member {name!r} contains '..'; refusing the shard")
    if m.issym() or m.islnk():
        raise ValueError(f"{path}: member {name!r} is a link (to {m.linkname!r}); refusing the shard")
    if not m.isreg():
        raise ValueError(f"{path}: member {name!r} is not a regular file; refusing the shard")
    base = p.name
    if "." not in base.strip(".") or base.startswith("."):
        raise ValueError(f"{path}: member {name!r} is not named <key>.<ext>")
    stem, ext = base.split(".", 1)
    key = str(p.parent / stem) if str(p.parent) != "." else stem
    return key, ext


def iter_shards(paths: Iterable[str | Path], members: Collection[str] | None = None) -> Iterator[dict[str, Any]]:
    """Samples of WebDataset tar shards, in order: ``{"__key__": key, "__url__": shard path,
    ext: bytes, ...}``; with ``members`` (extensions such as ``"motion.npz"``), only those are read
    (every member's name is still checked). Nothing is written to disk. ValueError for a member with
    an absolute path or ``..``, a link or other non-regular member, a name that is not
    ``<key>.<ext>``, an extension repeated within a sample, or a key whose members are not
    consecutive."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    for path in paths:
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"shard {path} does not exist")
        seen: set[str] = set()
        sample: dict[str, Any] | None = None
        try:
            with tarfile.open(path, "r:*") as tf:
                for m in tf:
                    key, ext = _check_member(path, m)
                    if sample is None or key != sample["__key__"]:
                        if sample is not None:
                            yield sample
                        if key in seen:
                            raise ValueError(f"{path}: the members of sample {key!r} are not consecutive")
                        seen.add(key)
                        sample, exts = {"__key__": key, "__url__": str(path)}, set()
                    if ext in exts:
                        raise ValueError(f"{path}: sample {key!r} has two {ext!r} members")
                    exts.add(ext)
                    if members is None or ext in members:
                        sample[ext] = tf.extractfile(m).read()
        except tarfile.TarError as e:
            raise ValueError(f"{path}: not a readable tar shard ({e})") from e
        if sample is not None:
            yield sample


def decode_sample(sample: dict[str, Any]) -> dict[str, Any]:
    """A sample of :func:`iter_shards` with ``.npz`` members loaded as dicts of arrays
    (``allow_pickle=False``) and ``.json`` members parsed (UTF-8); other members stay bytes."""
    out: dict[str, Any] = {}
    for k, v in sample.items():
        if k.startswith("__"):
            out[k] = v
        elif k.endswith(".npz"):
            out[k] = read_npz(v)
        elif k.endswith(".json"):
            try:
                out[k] = json.loads(v.decode("utf-8"))
            except (UnicodeDecodeError, json.JSONDecodeError) as e:
                raise ValueError(f"sample {sample.get('__key__')!r}: member {k!r} is not UTF-8 JSON ({e})") from e
        else:
            out[k] = v
    return out


__all__ = ["write_shards", "iter_shards", "decode_sample", "DEFAULT_MAX_BYTES", "SAMPLE_FILES"]

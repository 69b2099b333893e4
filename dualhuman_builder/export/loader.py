"""PyTorch datasets over an export: windows of both persons' motion features, with text.

:class:`MotionWindows` (map-style) reads a folder export (random access; the features of up to ``cache_mb`` of
sequences are cached per process, a whole split by default) or a list of WebDataset shards (their features are read into
memory once). :class:`ShardWindows` (iterable) streams shards for data too large for memory,
splitting the shards over DataLoader workers.

Windows run over the feature rows (row ``t`` describes frame ``t`` and the step ``t -> t+1``, so a
sequence of ``T`` frames has ``T - 1`` rows): ``L`` rows starting at ``0, s, 2s, ...`` with stride
``s = L // 2`` by default (L/2 overlap), as long as a whole window fits; a sequence shorter than
``L + 1`` frames gives no window (listed in ``.too_short``). The rows are exact slices of the
stored features (the canonical frame stays the sequence's, not re-canonicalised per window).

An item is ``{"seq_id": str, "start": int (first row = first frame), "a": (L, 269) float32 tensor,
"b": (L, 269) float32 tensor, "text": str, "mirrored": bool}``; with ``renders=True`` (folder only)
also ``"rgb": (C, L, H, W, 3) uint8`` for the C rendered views of frames ``start .. start+L-1``
(zeros where a frame was not rendered) and ``"rendered": (L,) bool``.

Augmentation: with probability ``mirror_p`` an item is mirrored left/right:
:func:`~dualhuman_builder.export.features.mirror_features` on both persons and
:func:`~dualhuman_builder.export.features.mirror_text` on the text. The choice of text (one of the
sequence's texts, uniformly) and the mirroring draw from a generator seeded by
``(seed, epoch, index)``: deterministic whatever the number of workers; call :meth:`set_epoch` for
fresh draws each epoch (the epoch lives in shared memory, so it reaches workers kept alive with
``persistent_workers=True`` too). ``normalize=True`` applies ``(x - mean) / std`` after
mirroring, with the export's ``stats/`` (or ``stats=(mean, std)``).
"""

from __future__ import annotations

import hashlib
import json
import random
from collections import OrderedDict
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset, IterableDataset, get_worker_info

from dualhuman_builder.export.features import FEATURE_DIM, mirror_features, mirror_text
from dualhuman_builder.export.files import check_seq_id, load_motion, read_manifest, read_npz
from dualhuman_builder.export.shards import decode_sample, iter_shards
from dualhuman_builder.fileio import confined_path, open_confined, read_confined

#: Largest split list or ``text.json`` read (bytes); paths from the manifest are read confined to
#: the export (:func:`~dualhuman_builder.fileio.read_confined`).
MAX_TEXT_BYTES = 64 << 20
#: Default per-process budget of cached motion features (both persons), MiB: a whole split of most
#: exports fits, so shuffled access does not reload files (1,000 ten-second sequences at 30 fps take
#: 614 MiB; ``docs/decisions/0024-export-format-and-loaders.md``).
CACHE_MB = 1024.0


def window_starts(rows: int, window: int, stride: int) -> np.ndarray:
    """First rows of the windows of ``window`` rows every ``stride`` rows that fit in ``rows``."""
    if rows < window:
        return np.zeros(0, dtype=np.int64)
    return np.arange(0, rows - window + 1, stride, dtype=np.int64)


def _check_args(window, stride, mirror_p) -> tuple[int, int, float]:
    if not isinstance(window, (int, np.integer)) or window < 1:
        raise ValueError(f"window must be a positive number of feature rows, got {window!r}")
    stride = max(int(window) // 2, 1) if stride is None else stride
    if not isinstance(stride, (int, np.integer)) or stride < 1:
        raise ValueError(f"stride must be a positive number of rows, got {stride!r}")
    if not (isinstance(mirror_p, (int, float)) and 0.0 <= float(mirror_p) <= 1.0):
        raise ValueError(f"mirror_p must be a probability in [0, 1], got {mirror_p!r}")
    return int(window), int(stride), float(mirror_p)


def _load_stats(stats, folder: Path | None) -> tuple[np.ndarray, np.ndarray]:
    if stats is None:
        if folder is None or not (folder / "stats" / "mean.npy").is_file():
            raise ValueError("normalize=True needs stats=(mean, std) or a stats/ folder (mean.npy, std.npy) beside the data")
        stats = (np.load(folder / "stats" / "mean.npy", allow_pickle=False),
                 np.load(folder / "stats" / "std.npy", allow_pickle=False))  # fmt: skip
    mean, std = (np.asarray(s, dtype=np.float32) for s in stats)
    if mean.shape != (FEATURE_DIM,) or std.shape != (FEATURE_DIM,):
        raise ValueError(f"stats must be two ({FEATURE_DIM},) arrays, got {mean.shape} and {std.shape}")
    if not (np.isfinite(mean).all() and np.isfinite(std).all() and (std > 0).all()):
        raise ValueError("stats hold NaN/inf or a non-positive std")
    return mean, std


def _shard_list(source) -> list[Path] | None:
    if isinstance(source, (list, tuple)):
        if not source:
            raise ValueError("an empty list of shards")
        return [Path(p) for p in source]
    if Path(source).suffix == ".tar":
        return [Path(source)]
    return None


class _Augment:
    """Mirroring, text choice and normalisation shared by both datasets."""

    def __init__(self, mirror_p: float, seed: int, normalize: bool, stats, stats_folder: Path | None):
        self.mirror_p, self.seed = mirror_p, int(seed)
        # in shared memory, so that set_epoch reaches DataLoader workers that persist across epochs
        self._epoch = torch.zeros(1, dtype=torch.int64).share_memory_()
        self.stats = _load_stats(stats, stats_folder) if normalize else None

    def set_epoch(self, epoch: int) -> None:
        """Use fresh (but reproducible) augmentation draws for ``epoch``."""
        self._epoch[0] = int(epoch)

    @property
    def epoch(self) -> int:
        """The epoch of the augmentation draws (:meth:`set_epoch`)."""
        return int(self._epoch[0])

    def draws(self, key: int) -> tuple[float, float]:
        """Two uniform [0, 1) numbers from ``(seed, epoch, key)``: a keyed hash, much cheaper per
        window than seeding a numpy generator, and the same in every worker."""
        h = hashlib.blake2b(f"{self.seed},{self.epoch},{int(key)}".encode(), digest_size=16).digest()
        return int.from_bytes(h[:8], "little") / 2.0**64, int.from_bytes(h[8:], "little") / 2.0**64

    def make(self, key: int, seq_id: str, start: int, a: np.ndarray, b: np.ndarray, texts: list[str]) -> dict:
        u_text, u_mirror = self.draws(key)
        text = texts[min(int(u_text * len(texts)), len(texts) - 1)] if texts else ""
        mirrored = bool(self.mirror_p > 0 and u_mirror < self.mirror_p)
        if mirrored:
            a, b, text = mirror_features(a), mirror_features(b), mirror_text(text)
        if self.stats is not None:
            mean, std = self.stats
            a, b = (a - mean) / std, (b - mean) / std
        return {"seq_id": seq_id, "start": int(start), "a": torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)),
                "b": torch.from_numpy(np.ascontiguousarray(b, dtype=np.float32)), "text": text, "mirrored": mirrored}  # fmt: skip


def _shard_sequences(paths: Iterable[Path]) -> Iterator[tuple[str, np.ndarray, np.ndarray, list[str]]]:
    """``(key, features a, features b, texts)`` per sample; only those are read and decoded."""
    for sample in iter_shards(paths, members=("motion.npz", "text.json")):
        if "motion.npz" not in sample:
            raise ValueError(f"{sample['__url__']}: sample {sample['__key__']!r} has no motion.npz")
        fa, fb = read_npz(sample["motion.npz"], keys=("a.features", "b.features")).values()
        texts = decode_sample({k: v for k, v in sample.items() if k == "text.json"}).get("text.json", {}).get("texts", [])
        yield sample["__key__"], fa, fb, [str(t) for t in texts]


class MotionWindows(Dataset):
    """Windows of ``window`` feature rows of both persons (see the module docstring).

    ``source``: an export folder (with ``manifest.json``), or a shard path / list of shard paths.
    ``split``: ``train``, ``test`` or ``all`` (folder only; shards hold one split each).
    ``stride``: rows between windows (default ``window // 2``). ``normalize``/``stats``: feature
    normalisation (default stats: the export's or the shards' ``stats/``). ``mirror_p``, ``seed``:
    augmentation. ``renders``: also return the rendered RGB frames (folder only, no mirroring).
    ``cache_mb``: features kept in memory per process (folder only; least recently used
    sequences are dropped beyond it); only the two feature arrays are read from ``motion.npz``.
    """

    def __init__(self, source: str | Path | Sequence[str | Path], window: int = 64, stride: int | None = None,
                 split: str = "train", normalize: bool = False, stats=None, mirror_p: float = 0.0, seed: int = 0,
                 renders: bool = False, cache_mb: float = CACHE_MB):  # fmt: skip
        self.window, self.stride, mirror_p = _check_args(window, stride, mirror_p)
        if not cache_mb >= 0:
            raise ValueError(f"cache_mb must be >= 0, got {cache_mb}")
        self._cache_bytes, self._cached_bytes = int(cache_mb * 2**20), 0
        shards = _shard_list(source)
        self.folder = None if shards is not None else Path(source)
        if renders and shards is not None:
            raise ValueError("renders=True needs a folder export; shards carry no images")
        if renders and mirror_p > 0:
            raise ValueError("renders=True with mirror_p > 0: mirrored motion would not match the images")
        self.renders = bool(renders)
        self._cache: OrderedDict[str, tuple[np.ndarray, np.ndarray, list[str]]] = OrderedDict()
        self.too_short: list[str] = []
        index: list[tuple[str, int]] = []
        if shards is not None:
            for sid, fa, fb, texts in _shard_sequences(shards):
                if sid in self._cache:
                    raise ValueError(f"sequence {sid!r} appears twice in the shards")
                self._cache[sid] = (fa, fb, texts)
                self._add(index, sid, len(fa))
            self._keep_all = True
            stats_folder = shards[0].parent
        else:
            self.manifest = read_manifest(self.folder)
            seqs = self.manifest["sequences"]
            if split == "all":
                ids = sorted(seqs)
            elif split in self.manifest.get("split", {}).get("files", {}):
                rel = self.manifest["split"]["files"][split]
                data = read_confined(self.folder, rel, MAX_TEXT_BYTES, f"split file {rel!r:.200} of {self.folder}")
                ids = [s for s in data.decode("utf-8").splitlines() if s.strip()]
            else:
                raise ValueError(f"unknown split {split!r}; choose train, test or all")
            for sid in ids:
                if sid not in seqs:
                    raise ValueError(f"split {split!r} names {sid!r}, which the manifest does not list")
                check_seq_id(sid)  # it names a folder
                self._add(index, sid, int(seqs[sid]["frames"]) - 1)
            self._keep_all = False
            stats_folder = self.folder
        self.index = index
        self.aug = _Augment(mirror_p, seed, normalize, stats, stats_folder)

    def _add(self, index: list, sid: str, rows: int) -> None:
        starts = window_starts(rows, self.window, self.stride)
        if len(starts) == 0:
            self.too_short.append(sid)
        index.extend((sid, int(s)) for s in starts)

    def set_epoch(self, epoch: int) -> None:
        """Fresh, reproducible augmentation draws for ``epoch``."""
        self.aug.set_epoch(epoch)

    def __len__(self) -> int:
        return len(self.index)

    def _sequence(self, sid: str) -> tuple[np.ndarray, np.ndarray, list[str]]:
        if sid in self._cache:
            if not self._keep_all:
                self._cache.move_to_end(sid)
            return self._cache[sid]
        base = f"sequences/{sid}"
        with open_confined(self.folder, f"{base}/motion.npz", f"{base}/motion.npz of {self.folder}") as f:
            fa, fb = load_motion(f, keys=("a.features", "b.features")).values()
        text_file = confined_path(self.folder, f"{base}/text.json", f"{base}/text.json of {self.folder}")
        texts = []
        if text_file.is_file():
            doc = json.loads(read_confined(self.folder, f"{base}/text.json", MAX_TEXT_BYTES).decode("utf-8"))
            texts = doc.get("texts", []) if isinstance(doc, dict) else []
        entry = (fa, fb, [str(t) for t in texts])
        self._cache[sid] = entry
        self._cached_bytes += fa.nbytes + fb.nbytes
        while self._cached_bytes > self._cache_bytes and len(self._cache) > 1:
            _, (old_a, old_b, _t) = self._cache.popitem(last=False)
            self._cached_bytes -= old_a.nbytes + old_b.nbytes
        return entry

    def __getitem__(self, i: int) -> dict[str, Any]:
        if not -len(self) <= i < len(self):
            raise IndexError(f"window {i} of {len(self)}")
        i = i % len(self)
        sid, start = self.index[i]
        fa, fb, texts = self._sequence(sid)
        stop = start + self.window
        item = self.aug.make(i, sid, start, fa[start:stop], fb[start:stop], texts)
        if self.renders:
            item["rgb"], item["rendered"] = self._rgb(sid, start)
        return item

    def _rgb(self, sid: str, start: int) -> tuple[torch.Tensor, torch.Tensor]:
        from PIL import Image

        views = self.manifest["sequences"][sid].get("render_views", [])
        base = f"sequences/{sid}/renders/views"
        frames = range(start, start + self.window)
        images: dict[tuple[int, int], np.ndarray] = {}
        for v, view in enumerate(views):
            for k, f in enumerate(frames):
                rel = f"{base}/{view}/rgb/{f:05d}.png"
                path = confined_path(self.folder, rel, f"{rel!r:.200} (a view named by the manifest) of {self.folder}")
                if path.is_file():
                    with Image.open(path) as im:
                        images[v, k] = np.asarray(im.convert("RGB"))
        sizes = {im.shape for im in images.values()}
        if len(sizes) > 1:
            raise ValueError(f"sequence {sid!r}: rendered views have different image sizes {sorted(sizes)}")
        h, w = next(iter(sizes))[:2] if sizes else (0, 0)
        rgb = np.zeros((len(views), self.window, h, w, 3), dtype=np.uint8)
        for (v, k), im in images.items():
            rgb[v, k] = im
        rendered = np.array([all((v, k) in images for v in range(len(views))) and bool(views) for k in range(self.window)])
        return torch.from_numpy(rgb), torch.from_numpy(rendered)


class ShardWindows(IterableDataset):
    """Streams windows from WebDataset shards (``paths``), for data that does not fit in memory.

    Each epoch the shard order is shuffled with ``(seed, epoch)`` (``shuffle_shards``), the shards
    are dealt to DataLoader workers round-robin, and windows pass through a shuffle buffer of
    ``buffer`` items (0: keep order). Windows, augmentation and normalisation as
    :class:`MotionWindows` (stats default: the ``stats/`` folder beside the first shard).
    """

    def __init__(self, paths: str | Path | Sequence[str | Path], window: int = 64, stride: int | None = None,
                 normalize: bool = False, stats=None, mirror_p: float = 0.0, seed: int = 0, buffer: int = 1000,
                 shuffle_shards: bool = True):  # fmt: skip
        self.window, self.stride, mirror_p = _check_args(window, stride, mirror_p)
        self.paths = _shard_list(paths) or []
        if not self.paths:
            raise ValueError(f"ShardWindows needs .tar shard paths, got {paths!r}")
        missing = [str(p) for p in self.paths if not p.is_file()]
        if missing:
            raise ValueError(f"shards not found: {missing[:5]}")
        if not isinstance(buffer, int) or buffer < 0:
            raise ValueError(f"buffer must be a non-negative int, got {buffer!r}")
        self.buffer, self.shuffle_shards = buffer, shuffle_shards
        self.aug = _Augment(mirror_p, seed, normalize, stats, self.paths[0].parent)

    def set_epoch(self, epoch: int) -> None:
        """Fresh, reproducible shard order and augmentation draws for ``epoch``."""
        self.aug.set_epoch(epoch)

    def _my_shards(self) -> list[Path]:
        order = list(range(len(self.paths)))
        if self.shuffle_shards:
            order = list(np.random.default_rng([self.aug.seed, self.aug.epoch]).permutation(len(order)))
        info = get_worker_info()
        wid, n = (info.id, info.num_workers) if info is not None else (0, 1)
        return [self.paths[i] for i in order[wid::n]]

    def __iter__(self) -> Iterator[dict[str, Any]]:
        info = get_worker_info()
        rng = random.Random(f"{self.aug.seed}-{self.aug.epoch}-{info.id if info is not None else 0}")
        buf: list[dict] = []
        for sid, fa, fb, texts in _shard_sequences(self._my_shards()):
            for s in window_starts(len(fa), self.window, self.stride):
                key = int.from_bytes(hashlib.blake2b(f"{sid}:{int(s)}".encode(), digest_size=8).digest(), "little")
                item = self.aug.make(key, sid, int(s), fa[s : s + self.window], fb[s : s + self.window], texts)
                if self.buffer <= 0:
                    yield item
                    continue
                buf.append(item)
                if len(buf) >= self.buffer:
                    yield buf.pop(rng.randrange(len(buf)))
        rng.shuffle(buf)
        yield from buf


__all__ = ["MotionWindows", "ShardWindows", "window_starts"]

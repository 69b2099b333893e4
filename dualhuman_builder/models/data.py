"""Windows of two-person interactions, read from a dataset export, as the models train on them.

:class:`InteractionWindows` is a PyTorch ``Dataset`` over one split of an export folder (the layout
`dualhuman export` writes, ``docs/guides/export.md``): windows of ``window`` frames of both people's
22 joints (world metres, Y up), every ``stride`` frames (default half a window), with roles resolved
(``text.json``'s roles: when person b is the ``actor``, b becomes the actor; a symmetric sequence or one
without roles: person a acts), the labels' multi-hot vector, one of the sequence's texts, and the
per-joint visibility of both people over a ring of virtual cameras
(:func:`~dualhuman_builder.models.visibility.joint_visibility`), computed once per sequence.

Each item is a dict with the keys of :data:`~dualhuman_builder.models.base.BATCH_KEYS` without the
batch dimension; :func:`collate` stacks a list of them into a batch. Every sequence of the split is
read when the dataset is made (joints and visibility of 1,000 ten-second sequences at 30 fps take
about 210 MB), so an item is a slice and the loader costs next to nothing in a training step.
Paths come from the manifest and are read confined to the export folder; nothing is unpickled.
"""

from __future__ import annotations

import hashlib
import json
from collections import OrderedDict
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.export.files import check_seq_id, load_motion, read_manifest
from dualhuman_builder.export.loader import MAX_TEXT_BYTES, window_starts
from dualhuman_builder.fileio import open_confined, read_confined
from dualhuman_builder.models.visibility import NUM_JOINTS, joint_visibility

#: Visibility results kept per process, keyed by the motion file's SHA-256 (from the manifest) and the
#: ring: a train and a test dataset, or a refinement after training, compute each sequence once.
_VIS_CACHE: OrderedDict[tuple, tuple[np.ndarray, np.ndarray]] = OrderedDict()
VIS_CACHE_ENTRIES = 4096
_FIX_EXPORT = "pass the folder `dualhuman export` wrote (it holds manifest.json); `dualhuman export verify DIR` checks one"


def _visibility(key: tuple, ja: np.ndarray, jb: np.ndarray, cameras: int) -> tuple[np.ndarray, np.ndarray]:
    if key in _VIS_CACHE:
        _VIS_CACHE.move_to_end(key)
        return _VIS_CACHE[key]
    vis = joint_visibility(ja, jb, cameras=cameras)
    _VIS_CACHE[key] = vis
    while len(_VIS_CACHE) > VIS_CACHE_ENTRIES:
        _VIS_CACHE.popitem(last=False)
    return vis


#: The splits a model reads: the export's ``train`` and ``test``, ``all``, and ``fit`` / ``validation``,
#: which divide the train split by people (:func:`validation_subjects`).
SPLITS = ("train", "test", "all", "fit", "validation")
#: The splits a model trains on; the image datasets augment these.
TRAINING_SPLITS = ("train", "fit")
#: The validation split's least share of the train split's sequences.
VALIDATION_SHARE = 0.15


def validation_subjects(manifest: dict[str, Any], train_ids: Sequence[str]) -> list[str]:
    """The people whose train sequences form the ``validation`` split: subjects taken in the order of
    their names' SHA-256 until the train sequences with any of them reach :data:`VALIDATION_SHARE`.

    A sequence with one validation person and one other goes to validation, so the ``fit`` split
    never sees a validation person: a setting chosen on ``validation`` (a refinement weight, a
    checkpoint) is chosen on people the model did not train on, and the test split stays untouched.
    The order depends on the names alone, so every run over the same export holds out the same people.
    """
    seqs = manifest.get("sequences", {})
    subjects = {sid: {str(x) for x in (seqs.get(sid, {}).get("subjects") or []) if x} for sid in train_ids}
    names = sorted({x for v in subjects.values() for x in v}, key=lambda x: hashlib.sha256(x.encode()).hexdigest())
    chosen: list[str] = []
    held = 0
    for name in names:
        if held >= VALIDATION_SHARE * len(train_ids):
            break
        chosen.append(name)
        held = sum(1 for v in subjects.values() if v & set(chosen))
    return chosen


def _fit_or_validation(folder: Path, manifest: dict[str, Any], split: str) -> list[str]:
    train = split_ids(folder, manifest, "train")
    chosen = set(validation_subjects(manifest, train))
    seqs = manifest["sequences"]
    held = [sid for sid in train if chosen & {str(x) for x in (seqs[sid].get("subjects") or [])}]
    held_set = set(held)
    fit = [sid for sid in train if sid not in held_set]
    if not chosen or not held or not fit:
        why = ("its manifest names no subjects" if not chosen else
               "every train sequence shares a person with the validation set")  # fmt: skip
        raise DualhumanError(f"{folder}: the train split cannot be divided into fit and validation by people ({why})",
                             fix="train on the train split, or export more people (`dualhuman export` records each sequence's subjects)")  # fmt: skip
    return held if split == "validation" else fit


def split_ids(folder: Path, manifest: dict[str, Any], split: str) -> list[str]:
    """The sequence ids of ``split`` (one of :data:`SPLITS`) of the export at ``folder``."""
    seqs = manifest.get("sequences")
    if not isinstance(seqs, dict):
        raise DualhumanError(f"{folder}/manifest.json lists no sequences", fix=_FIX_EXPORT)
    if split == "all":
        ids = sorted(seqs)
        for sid in ids:
            _check_id(folder, sid)
        return ids
    if split in ("fit", "validation"):
        return _fit_or_validation(folder, manifest, split)
    files = manifest.get("split", {}).get("files", {}) if isinstance(manifest.get("split"), dict) else {}
    if split not in ("train", "test") or split not in files:
        raise DualhumanError(f"unknown split {split!r} in {folder}", fix="choose one of " + ", ".join(SPLITS))
    rel = files[split]
    data = read_confined(folder, rel, MAX_TEXT_BYTES, f"split file {rel!r:.200} of {folder}")
    ids = [s.strip() for s in data.decode("utf-8", errors="replace").splitlines() if s.strip()]
    for sid in ids:
        if sid not in seqs:
            raise DualhumanError(f"split {split!r} of {folder} names {sid!r}, which the manifest does not list",
                                 fix="re-export the dataset, or run `dualhuman export verify` on it")  # fmt: skip
        _check_id(folder, sid)
    return ids


def _check_id(folder: Path, sid) -> None:
    try:
        check_seq_id(sid)
    except ValueError as e:
        raise DualhumanError(f"{folder}/manifest.json: {e}", fix="re-export the dataset, or run `dualhuman export verify` on it") from None


def actor_is_b(text_doc: dict[str, Any] | None) -> bool:
    """Whether person b is the actor: ``text.json`` roles are exactly ``["reactor", "actor"]`` (the
    export's form) and the sequence is not symmetric; a symmetric sequence, one without roles or with
    roles of another form has person a act."""
    if not isinstance(text_doc, dict) or text_doc.get("symmetric") is True:
        return False
    return text_doc.get("roles") == ["reactor", "actor"]


def read_sequence(folder: Path, sid: str) -> tuple[dict[str, np.ndarray], dict[str, Any] | None]:
    """``({"a.joints", "b.joints"}, text.json or None)`` of one sequence, read confined to ``folder``."""
    base = f"sequences/{sid}"
    with open_confined(folder, f"{base}/motion.npz", f"{base}/motion.npz of {folder}") as f:
        try:
            motion = load_motion(f, keys=("a.joints", "b.joints"))
        except ValueError as e:
            raise DualhumanError(str(e), fix="re-export the dataset, or run `dualhuman export verify` on it") from None
    doc = None
    if (folder / base / "text.json").is_file():
        raw = read_confined(folder, f"{base}/text.json", MAX_TEXT_BYTES, f"{base}/text.json of {folder}")
        try:
            doc = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise DualhumanError(f"{folder}/{base}/text.json is not UTF-8 JSON ({e})", fix="re-export the dataset") from None
    return motion, doc if isinstance(doc, dict) else None


class InteractionWindows(Dataset):
    """Windows of both people of one split of an export (module docstring).

    ``export_dir``: the export folder. ``split``: one of :data:`SPLITS`. ``window``: frames per
    window; ``stride``: frames between window starts (default ``window // 2``). ``visibility``: compute
    the ring visibility (False: ones, for models that ignore it; saves the time). ``cameras``: cameras
    on the ring. ``seed``: which of a sequence's texts an item carries (with :meth:`set_epoch`).

    Attributes: ``manifest``, ``ids`` (the split's sequences), ``too_short`` (sequences shorter than a
    window, left out), ``swapped`` (sequences where person b acts), ``labels`` (the vocabulary's
    names, multi-hot order), ``frames`` (frames read). DualhumanError with a fix for a folder that is
    not an export, an unknown split, or a split without one window.
    """

    def __init__(self, export_dir: str | Path, split: str = "train", window: int = 64, stride: int | None = None,
                 visibility: bool = True, seed: int = 0, cameras: int = 8):  # fmt: skip
        if not isinstance(window, (int, np.integer)) or window < 1:
            raise DualhumanError(f"window must be a positive number of frames, got {window!r}", fix="use e.g. --window 64")
        stride = max(int(window) // 2, 1) if stride is None else stride
        if not isinstance(stride, (int, np.integer)) or stride < 1:
            raise DualhumanError(f"stride must be a positive number of frames, got {stride!r}", fix="leave it out for window/2")
        self.folder, self.split, self.window, self.stride = Path(export_dir), split, int(window), int(stride)
        self.seed, self.epoch, self.visibility, self.cameras = int(seed), 0, bool(visibility), int(cameras)
        if not self.folder.is_dir():
            raise DualhumanError(f"{self.folder} is not a folder", fix=_FIX_EXPORT)
        try:
            self.manifest = read_manifest(self.folder)
        except ValueError as e:
            raise DualhumanError(str(e), fix=_FIX_EXPORT) from None
        self.labels = self._label_names()
        self.ids = split_ids(self.folder, self.manifest, split)
        files = self.manifest.get("files", {}) if isinstance(self.manifest.get("files"), dict) else {}
        self.too_short: list[str] = []
        self.swapped: list[str] = []
        self.frames = 0
        self._seqs: list[dict[str, Any]] = []
        self.index: list[tuple[int, int]] = []
        for sid in self.ids:
            motion, doc = read_sequence(self.folder, sid)
            ja, jb = (np.ascontiguousarray(motion[k], dtype=np.float32) for k in ("a.joints", "b.joints"))
            if ja.ndim != 3 or ja.shape[1:] != (NUM_JOINTS, 3) or ja.shape != jb.shape:
                raise DualhumanError(f"{self.folder}/sequences/{sid}/motion.npz: joints of shape {ja.shape} and {jb.shape}",
                                     fix="re-export the dataset; joints are (T, 22, 3) for both people")  # fmt: skip
            starts = window_starts(len(ja), self.window, self.stride)
            if len(starts) == 0:
                self.too_short.append(sid)
                continue
            swap = actor_is_b(doc)
            if swap:
                self.swapped.append(sid)
            if self.visibility:
                sha = files.get(f"sequences/{sid}/motion.npz", {}).get("sha256") if isinstance(files, dict) else None
                key = (sha or hashlib.sha256(ja.tobytes() + jb.tobytes()).hexdigest(), self.cameras)
                va, vb = _visibility(key, ja, jb, self.cameras)
            else:
                va = vb = np.ones(ja.shape[:2], np.float32)
            hot = np.zeros(len(self.labels), np.float32)
            mh = doc.get("multi_hot") if doc else None
            if isinstance(mh, list) and len(mh) == len(hot):
                hot[:] = np.asarray(mh, dtype=np.float32)
            texts = [str(t) for t in (doc.get("texts") or [])] if doc else []
            k = len(self._seqs)
            self._seqs.append({"seq_id": sid, "actor": jb if swap else ja, "reactor": ja if swap else jb,
                               "vis_actor": vb if swap else va, "vis_reactor": va if swap else vb,
                               "labels": hot, "texts": texts})  # fmt: skip
            self.frames += len(ja)
            self.index.extend((k, int(s)) for s in starts)
        if not self.index:
            n = len(self.ids)
            raise DualhumanError(
                f"{self.folder}: no window of {self.window} frames in split {split!r} ({n} sequence{'s' * (n != 1)}"
                f"{', all shorter' if n else ''})",
                fix="use a shorter window (--set window=N), another split, or an export with longer sequences",
            )
        self._pack()

    def _pack(self) -> None:
        """Put every sequence's arrays end to end, so that a batch is one gather per array
        (:meth:`batch`); the per-sequence dicts keep views into them."""
        lengths = [len(q["actor"]) for q in self._seqs]
        self._offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
        for key in ("actor", "reactor", "vis_actor", "vis_reactor"):
            packed = np.concatenate([q[key] for q in self._seqs])
            setattr(self, f"_all_{key}", packed)
            for q, lo, n in zip(self._seqs, self._offsets, lengths):
                q[key] = packed[lo:lo + n]
        self._labels = np.stack([q["labels"] for q in self._seqs])
        seq_of = np.array([k for k, _ in self.index], dtype=np.int64)
        self._seq_of, self._starts = seq_of, np.array([st for _, st in self.index], dtype=np.int64)
        self._gstart = self._offsets[seq_of] + self._starts

    def _label_names(self) -> list[str]:
        vocab = self.manifest.get("vocabulary", {})
        rel = vocab.get("file", "labels.json") if isinstance(vocab, dict) else "labels.json"
        try:
            doc = json.loads(read_confined(self.folder, rel, MAX_TEXT_BYTES, f"vocabulary {rel!r:.200}").decode("utf-8"))
            return [str(e["name"]) for e in doc["labels"]]
        except (DualhumanError, ValueError, KeyError, TypeError) as e:
            raise DualhumanError(f"{self.folder}: cannot read the label vocabulary ({e})", fix=_FIX_EXPORT) from None

    @property
    def num_sequences(self) -> int:
        return len(self._seqs)

    def sequence(self, k: int) -> dict[str, Any]:
        """The ``k``-th usable sequence: ``seq_id``, ``actor``/``reactor`` joints ``(T, 22, 3)``,
        ``vis_actor``/``vis_reactor`` ``(T, 22)``, ``labels (C,)``, ``texts``."""
        return self._seqs[k]

    def set_epoch(self, epoch: int) -> None:
        """Draw the items' texts afresh, reproducibly, for ``epoch``."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.index)

    def _text(self, i: int) -> str:
        texts = self._seqs[int(self._seq_of[i])]["texts"]
        if len(texts) > 1:
            return texts[int(np.random.default_rng([self.seed, self.epoch, i]).integers(len(texts)))]
        return texts[0] if texts else ""

    def __getitem__(self, i: int) -> dict[str, Any]:
        if not -len(self) <= i < len(self):
            raise IndexError(f"window {i} of {len(self)}")
        i = i % len(self)
        k, start = self.index[i]
        s = self._seqs[k]
        stop = start + self.window
        return {
            "joints_actor": torch.from_numpy(s["actor"][start:stop]),
            "joints_reactor": torch.from_numpy(s["reactor"][start:stop]),
            "visibility_actor": torch.from_numpy(s["vis_actor"][start:stop]),
            "visibility_reactor": torch.from_numpy(s["vis_reactor"][start:stop]),
            "labels": torch.from_numpy(s["labels"]),
            "text": self._text(i),
            "seq_id": s["seq_id"],
            "start": torch.tensor(start, dtype=torch.int64),
        }

    def batch(self, indices: Sequence[int] | np.ndarray) -> dict[str, Any]:
        """``collate([self[i] for i in indices])``, built with one gather per array (the training
        loop's fast path: a batch of 256 windows of 64 frames in a few milliseconds)."""
        idx = np.asarray(indices, dtype=np.int64)
        if idx.ndim != 1 or len(idx) == 0 or idx.min() < -len(self) or idx.max() >= len(self):
            raise IndexError(f"windows {indices!r} of {len(self)}")
        idx = idx % len(self)
        rows = self._gstart[idx][:, None] + np.arange(self.window)  # (B, L)
        seq = self._seq_of[idx]
        return {
            "joints_actor": torch.from_numpy(self._all_actor[rows]),
            "joints_reactor": torch.from_numpy(self._all_reactor[rows]),
            "visibility_actor": torch.from_numpy(self._all_vis_actor[rows]),
            "visibility_reactor": torch.from_numpy(self._all_vis_reactor[rows]),
            "labels": torch.from_numpy(self._labels[seq]),
            "text": [self._text(int(i)) for i in idx],
            "seq_id": [self._seqs[int(k)]["seq_id"] for k in seq],
            "start": torch.from_numpy(self._starts[idx].copy()),
        }


def collate(items: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """A batch (keys of :data:`~dualhuman_builder.models.base.BATCH_KEYS`) from a list of items:
    tensors stacked along a new first dimension, strings as lists."""
    if not items:
        raise ValueError("collate needs at least one item")
    out: dict[str, Any] = {}
    for key, value in items[0].items():
        if isinstance(value, torch.Tensor):
            out[key] = torch.stack([it[key] for it in items])
        else:
            out[key] = [it[key] for it in items]
    return out

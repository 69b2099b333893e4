"""Read a folder in HumanML3D's or InterHuman's layout into a dataset export (:func:`export_dataset`).

The inverse of :mod:`dualhuman_builder.export.convert`, for a user who holds such a dataset and wants
to train the toolkit's models on it. Only joints are read: the export's body-model arrays hold no
body-model parameters (``body_model.name`` is :data:`JOINTS_ONLY`, zero bones and zero phenotype
values: ``pose (T, 0, 3)``, ``shape (0,)``; ``num_vertices`` 0, no mesh, so the body model is never
loaded), ``transl`` is the root joint (pelvis), ``joints`` and ``features`` are as in any export, so
``dualhuman export verify`` and the feature-based loaders work.

InterHuman (:func:`import_interhuman`): ``motions_processed/person1|person2/<id>.npy`` ``(T, 492)`` at
30 fps, columns ``[0:66]`` the 22 body joints in world metres, Z up, mapped to our Y-up axes with
``(x, y, z) -> (x, z, -y)``; ``annots/<id>.txt`` one text per line; ``ignore_list.txt`` names left out.
When the folder was written by :func:`~dualhuman_builder.export.convert.to_interhuman` (its
``conversion.json`` gives the sequence's transform) the joints are mapped back to the original world
frame, as :func:`~dualhuman_builder.export.convert.read_interhuman` does.

HumanML3D (:func:`import_humanml3d`): ``new_joints/<name>.npy`` ``(T, 22, 3)`` at 20 fps, each motion in
its own canonical frame (root at the origin at frame 0, facing +Z, floor y = 0); ``texts/<name>.txt``
lines ``caption#tokens#from#to`` (the captions are kept). The layout is one person per motion; the
export holds pairs, so motions named ``<id>_a`` and ``<id>_b`` (as ``to_humanml3d`` writes them) become
sequence ``<id>`` and any other motion is skipped with the reason counted. HumanML3D keeps no relative
placement: both persons of an imported pair start at the origin facing +Z.

Both: the source's split lists (``train/val/test.txt``) are recorded per sequence in
``sequence.json`` ``meta.imported_from.split`` and, with ``keep_split`` (the default), kept as the
export's split (:func:`export_dataset`'s ``splits``): ``train`` stays train, ``val`` and ``test`` become
test (the export has two splits; held-out data stays held out); a HumanML3D pair whose two motions are
listed differently is train only when both are listed train. Sequences in no list are drawn by
:func:`export_dataset` (``split_ratio``, ``seed``), as is everything when ``keep_split`` is off or when
the lists would leave train empty (the feature statistics need train; the result's ``notes`` say so).
Every file is read through :func:`~dualhuman_builder.fileio.read_confined` with a size cap (the folder
comes from elsewhere) and arrays with ``allow_pickle=False``. A folder that is not in the layout raises FormatError; a file
that cannot be used (wrong shape, not finite, unreadable, an id the export cannot name) is skipped
with its reason in the returned ``skipped``.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dualhuman_builder.errors import DualhumanError, FormatError
from dualhuman_builder.export.convert import CONVERSION, INTERHUMAN_RAW_DIM, TO_Z_UP
from dualhuman_builder.export.features import HUMANML3D_FPS, NUM_JOINTS, _rotate_y
from dualhuman_builder.export.files import PERSONS, SEQ_ID_RE
from dualhuman_builder.export.interhuman import INTERHUMAN_FPS, PairTransform
from dualhuman_builder.export.items import ExportItem
from dualhuman_builder.export.verify import npy_from_bytes
from dualhuman_builder.fileio import confined_path, read_confined
from dualhuman_builder.tracks import BodyTrack, InteractionSequence

#: ``body_model.name`` of an imported export: joints only, no body-model parameters.
JOINTS_ONLY = "joints-only"
#: Largest motion file read (bytes): about 13 minutes of InterHuman at 30 fps (492 float32 per frame).
MAX_MOTION_BYTES = 48 * 2**20
#: Largest text, split list or conversion.json read (bytes).
MAX_TEXT_BYTES = 4 * 2**20
_SPLITS = ("train", "test", "val")  # a name in several lists: the first wins (our converters' val repeats test)


class JointsTrack(BodyTrack):
    """A :class:`BodyTrack` known only by its joints ``(T, 22, 3)`` world metres: no bones, no phenotype
    values, ``transl`` the root joint; :meth:`joints` returns the joints (no body model is run)."""

    @classmethod
    def from_joints(cls, joints: np.ndarray, fps: float, actor: str = "") -> JointsTrack:
        j = np.ascontiguousarray(joints, dtype=np.float32)
        T = len(j)
        track = cls(pose=np.zeros((T, 0, 3), np.float32), transl=j[:, 0], shape=np.zeros(0, np.float32), fps=fps,
                    bone_names=(), shape_names=(), model=JOINTS_ONLY, actor=actor)  # fmt: skip
        j.setflags(write=False)
        track._joints = j
        return track

    def joints(self) -> np.ndarray:
        return self._joints


# ================================================================================ reading
def _layout_error(root: Path, layout: str, what: str, fix: str) -> FormatError:
    return FormatError(f"not in the {layout} layout: {what}", path=root, fix=fix)


def _text(root: Path, rel: str) -> str | None:
    """UTF-8 text of ``rel`` under ``root`` (None when absent); FormatError when too large or not UTF-8."""
    if not confined_path(root, rel).is_file():
        return None
    data = read_confined(root, rel, MAX_TEXT_BYTES)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise FormatError(f"{rel} is not UTF-8 text ({e.reason} at byte {e.start})", path=root,
                          fix="save it as UTF-8") from None  # fmt: skip


def _lines(text: str | None) -> list[str]:
    return [s.strip() for s in (text or "").splitlines() if s.strip()]


def _split_of(root: Path) -> dict[str, str]:
    """Name -> split from ``train/test/val.txt``, in that order of precedence."""
    out: dict[str, str] = {}
    for split in _SPLITS:
        for name in _lines(_text(root, f"{split}.txt")):
            out.setdefault(name, split)
    return out


def _npy(root: Path, rel: str) -> np.ndarray:
    """Array of the ``.npy`` file ``rel`` (read-only); ValueError (a reason to skip) when it is not one."""
    try:
        data = read_confined(root, rel, MAX_MOTION_BYTES)
    except FormatError as e:
        raise ValueError(e.message) from None
    a = npy_from_bytes(data, rel)  # header checked against the file's size before anything is allocated
    if a.dtype.kind not in "fiu":
        raise ValueError(f"{rel} holds {a.dtype}, not numbers")
    return a


def _check_motion(j: np.ndarray, rel: str, min_frames: int = 2) -> np.ndarray:
    if j.ndim != 3 or j.shape[1:] != (NUM_JOINTS, 3):
        raise ValueError(f"{rel}: joints of shape {j.shape}, expected (T, {NUM_JOINTS}, 3)")
    if len(j) < min_frames:
        raise ValueError(f"{rel}: {len(j)} frame(s), at least {min_frames} needed")
    j = j.astype(np.float64)
    if not np.isfinite(j).all():
        first = tuple(int(i) for i in np.argwhere(~np.isfinite(j))[0])
        raise ValueError(f"{rel}: holds NaN or inf (first at index {first})")
    if np.abs(j).max() > 1e5:
        raise ValueError(f"{rel}: coordinates up to {np.abs(j).max():.3g}, not metres")
    return j


def _stems(folder: Path) -> list[str]:
    """Names of the ``*.npy`` files directly in ``folder`` (sorted; hidden files left out)."""
    return sorted(p.name[:-4] for p in folder.iterdir() if p.name.endswith(".npy") and not p.name.startswith("."))


def _item(sid: str, a: np.ndarray, b: np.ndarray, fps: float, texts: list[str], source: dict) -> ExportItem:
    h = hashlib.sha256(np.float32(a).tobytes() + np.float32(b).tobytes()).hexdigest()
    seq = InteractionSequence((JointsTrack.from_joints(a, fps), JointsTrack.from_joints(b, fps)), take=sid,
                              text=tuple(texts), meta={"imported_from": source, "joints_sha256": h})  # fmt: skip
    return ExportItem(sid, seq, subjects=("", ""))


def _export_split(source_split) -> str | None:
    """The export split (``train``/``test``) of a source's split name(s), None when it lists none."""
    names = {source_split} if isinstance(source_split, str) or source_split is None else set(source_split)
    names = {n for n in names if n}
    if not names:
        return None
    return "train" if names == {"train"} else "test"


def _source_splits(items: list[ExportItem]) -> tuple[dict[str, str], list[str]]:
    """``(seq_id -> export split, notes)`` from the items' recorded source splits (module docstring)."""
    given = {it.seq_id: sp for it in items if (sp := _export_split(it.sequence.meta["imported_from"].get("split")))}
    if given and len(given) == len(items) and "train" not in given.values():
        return {}, [("the source's split lists put no imported sequence in train (the feature statistics need one), "
                     "so the export's split was drawn with --split and --seed")]  # fmt: skip
    return given, []


def _finish(root: Path, out, layout: str, items: list[ExportItem], skipped: dict[str, str],
            progress: Callable[[str], None] | None, keep_split: bool = True,
            **export_kw) -> dict[str, Any]:  # fmt: skip
    from dualhuman_builder.export.writer import export_dataset

    if not items:
        raise FormatError(f"no {layout} sequence could be imported ({len(skipped)} skipped: "
                          f"{dict(sorted(skipped.items())[:5])})", path=root,
                          fix="see the reasons; at least one usable two-person motion is needed")  # fmt: skip
    splits, notes = _source_splits(items) if keep_split else ({}, [])
    try:
        manifest = export_dataset(items, out, progress=progress, expect=("motion",), splits=splits, **export_kw)
    except ValueError as e:
        raise DualhumanError(str(e), path=out, fix="OUT must be new, empty, or an earlier export (updated in place); "
                             "see the message for anything else") from None  # fmt: skip
    skipped = {**skipped, **manifest.get("skipped", {})}  # the writer's own skips (features not computable)
    return {"layout": layout, "source": str(root), "imported": len(manifest["sequences"]),
            "split_from_source": manifest["split"]["given"], "notes": notes,
            "skipped": dict(sorted(skipped.items())), "manifest": manifest}  # fmt: skip


def _open(src, layout: str, need: str, fix: str) -> Path:
    root = Path(src)
    if not root.is_dir():
        raise FormatError("is not a folder", path=root, fix=fix)
    if not confined_path(root, need).is_dir():
        raise _layout_error(root, layout, f"it has no {need}/ folder", fix)
    return root


# ================================================================================ InterHuman
def _conversion_transforms(root: Path) -> dict[str, dict]:
    """Per-sequence transforms of a ``to_interhuman`` conversion's ``conversion.json`` ({} without one)."""
    text = _text(root, CONVERSION)
    if text is None:
        return {}
    try:
        doc = json.loads(text)
    except (ValueError, RecursionError) as e:
        raise FormatError(f"{CONVERSION} is not JSON ({type(e).__name__}: {str(e)[:200]})", path=root,
                          fix=f"remove {CONVERSION} or restore it") from None  # fmt: skip
    if not isinstance(doc, dict) or doc.get("layout") != "interhuman" or not isinstance(doc.get("sequences"), dict):
        return {}
    seqs = doc["sequences"].items()
    return {k: v["transform"] for k, v in seqs if isinstance(v, dict) and isinstance(v.get("transform"), dict)}


def _to_world(joints: np.ndarray, tr: dict | None) -> np.ndarray:
    if tr is None:
        return joints
    try:
        transform = PairTransform(float(tr["yaw0"]), tuple(float(v) for v in tr["translation"]))
        raw_yaw = float(tr.get("raw_yaw", 0.0))
    except (KeyError, TypeError, ValueError) as e:
        raise ValueError(f"{CONVERSION}: malformed transform ({e!r})") from None
    if not all(np.isfinite([transform.yaw0, raw_yaw, *transform.translation])) or len(transform.translation) != 3:
        raise ValueError(f"{CONVERSION}: transform is not three finite numbers and two angles")
    return transform.to_world(_rotate_y(joints, -raw_yaw))


def import_interhuman(src, out, progress: Callable[[str], None] | None = None, keep_split: bool = True,
                      **export_kw) -> dict[str, Any]:  # fmt: skip
    """Import the InterHuman folder ``src`` (module docstring) as an export in ``out`` (30 fps).
    ``keep_split``: keep the source's split lists (module docstring); ``export_kw``:
    :func:`~dualhuman_builder.export.writer.export_dataset`'s ``split_ratio``, ``seed``, ... (the split
    of sequences the lists do not place). Returns ``{layout, source, imported, split_from_source (count),
    notes, skipped (name -> reason), manifest}``. FormatError: ``src`` is not in the layout or nothing in
    it is usable; DualhumanError: ``out`` cannot be written."""
    fix = "give InterHuman's data root: the folder holding motions_processed/person1/, person2/ and annots/"
    root = _open(src, "InterHuman", "motions_processed/person1", fix)
    if not confined_path(root, "motions_processed/person2").is_dir():
        raise _layout_error(root, "InterHuman", "it has no motions_processed/person2/ folder", fix)
    split_of = _split_of(root)
    ignore = set(_lines(_text(root, "ignore_list.txt")))
    transforms = _conversion_transforms(root)
    items, skipped = [], {}
    for sid in _stems(confined_path(root, "motions_processed/person1")):
        if sid in ignore:
            skipped[sid] = "listed in ignore_list.txt"
            continue
        if not SEQ_ID_RE.match(sid):
            skipped[sid] = "the name is not a usable sequence id ([A-Za-z0-9][A-Za-z0-9_-]*, at most 128 characters)"
            continue
        try:
            pair = []
            for k in (1, 2):
                rel = f"motions_processed/person{k}/{sid}.npy"
                if not confined_path(root, rel).is_file():
                    raise ValueError(f"{rel} is missing (person 1 has a motion)")
                raw = _npy(root, rel)
                if raw.ndim != 2 or raw.shape[1] != INTERHUMAN_RAW_DIM:
                    raise ValueError(f"{rel}: shape {raw.shape}, InterHuman's raw layout is (T, {INTERHUMAN_RAW_DIM})")
                pair.append(_check_motion(raw[:, :66].reshape(len(raw), NUM_JOINTS, 3), rel) @ TO_Z_UP)
            if len(pair[0]) != len(pair[1]):
                raise ValueError(f"person1 has {len(pair[0])} frames, person2 {len(pair[1])}")
            a, b = (_to_world(j, transforms.get(sid)) for j in pair)
            texts = _lines(_text(root, f"annots/{sid}.txt"))
        except (ValueError, FormatError) as e:
            skipped[sid] = e.message if isinstance(e, FormatError) else str(e)
            continue
        source = {"layout": "interhuman", "name": sid, "split": split_of.get(sid), "world": sid in transforms}
        items.append(_item(sid, a, b, INTERHUMAN_FPS, list(dict.fromkeys(texts)), source))
    return _finish(root, out, "InterHuman", items, skipped, progress, keep_split, **export_kw)


# ================================================================================ HumanML3D
def _captions(text: str | None) -> list[str]:
    """The captions of a HumanML3D text file (``caption#tokens#from#to`` lines), duplicates dropped."""
    return list(dict.fromkeys(c for c in (line.split("#", 1)[0].strip() for line in _lines(text)) if c))


def import_humanml3d(src, out, progress: Callable[[str], None] | None = None, keep_split: bool = True,
                     **export_kw) -> dict[str, Any]:  # fmt: skip
    """Import the HumanML3D-layout folder ``src`` (module docstring) as an export in ``out`` (20 fps):
    motions ``<id>_a`` + ``<id>_b`` become sequence ``<id>``; others are skipped as unpaired. Returns,
    raises and takes ``export_kw`` as :func:`import_interhuman`."""
    fix = "give the HumanML3D data root: the folder holding new_joints/ and texts/"
    root = _open(src, "HumanML3D", "new_joints", fix)
    split_of = _split_of(root)
    names = _stems(confined_path(root, "new_joints"))
    by_id: dict[str, dict[str, str]] = {}
    skipped: dict[str, str] = {}
    for name in names:
        sid, _, p = name.rpartition("_")
        if sid and p in PERSONS:
            by_id.setdefault(sid, {})[p] = name
        else:
            skipped[name] = "unpaired: one-person motion (the export holds pairs named <id>_a and <id>_b)"
    items = []
    for sid, pair in sorted(by_id.items()):
        if set(pair) != set(PERSONS):
            for name in pair.values():
                skipped[name] = f"unpaired: no {sid}_{'b' if 'a' in pair else 'a'} beside it"
            continue
        if not SEQ_ID_RE.match(sid):
            skipped[sid] = "the name is not a usable sequence id ([A-Za-z0-9][A-Za-z0-9_-]*, at most 128 characters)"
            continue
        try:
            joints = []
            for p in PERSONS:
                rel = f"new_joints/{pair[p]}.npy"
                joints.append(_check_motion(_npy(root, rel), rel))
            if len(joints[0]) != len(joints[1]):
                raise ValueError(f"{pair['a']} has {len(joints[0])} frames, {pair['b']} {len(joints[1])}")
            texts = list(dict.fromkeys(c for p in PERSONS for c in _captions(_text(root, f"texts/{pair[p]}.txt"))))
        except (ValueError, FormatError) as e:
            skipped[sid] = e.message if isinstance(e, FormatError) else str(e)
            continue
        splits = {split_of.get(n) for n in pair.values()}
        source = {"layout": "humanml3d", "name": [pair["a"], pair["b"]],
                  "split": splits.pop() if len(splits) == 1 else sorted(s or "" for s in splits)}  # fmt: skip
        items.append(_item(sid, joints[0], joints[1], HUMANML3D_FPS, texts, source))
    return _finish(root, out, "HumanML3D", items, skipped, progress, keep_split, **export_kw)


__all__ = ["JOINTS_ONLY", "JointsTrack", "import_humanml3d", "import_interhuman"]

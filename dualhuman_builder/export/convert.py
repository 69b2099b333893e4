"""Convert a dataset export (``dualhuman export WS OUT``) to the layouts the field's training code reads.

InterGen / InterHuman (:func:`to_interhuman`, ``dualhuman export interhuman OUT DEST``)
-------------------------------------------------------------------------------------

Facts relied on (tr3e/InterGen ``datasets/interhuman.py``, ``utils/preprocess.py``, ``utils/utils.py``;
issues #12, #15, #27): the loader walks ``DATA_ROOT`` for ``*.npy`` files whose folder path contains
``person1``; the motion name is the file name up to its first dot; it keeps the names listed in
``DATA_ROOT/{train,val,test}.txt`` (compared as ``name + "\\n"``, so every line ends with a newline)
and drops those in ``DATA_ROOT/ignore_list.txt``; person 2 is the same path with ``person1`` replaced by
``person2``, the text ``annots/<name>.txt`` (path derived by replacing ``motions_processed`` -> ``annots``,
``person1`` -> ``""``, ``npy`` -> ``txt`` anywhere in the path), one sentence per line, one drawn at
random per sample. A ``motions_processed`` file is NOT the 262-dim feature: it is InterHuman's raw
per-frame ``(T, 492)`` array at 30 fps, 62 SMPL-H joint positions (22 body, 15 + 15 hand, 5 + 5
finger tips; world metres, Z up) then 51 local rotations in 6D; InterGen reads columns ``[0:66]``
(22 body joints) and ``[186:312]`` (21 body rotations), rotates Z-up to Y-up with
``(x, y, z) -> (x, z, -y)``, and computes the 262-dim features itself (``process_motion_np``: each
person floored, moved to the origin and turned to face +Z, person 2 then put back relative to person
1), dropping motions shorter than 15 frames. Mirroring swaps the texts' "left"/"right".

Written under ``DEST``::

    motions_processed/person1/<id>.npy   (T30, 492) float32: person a, InterHuman's raw layout in the
    motions_processed/person2/<id>.npy   shared frame of export/interhuman.py (person a's canonical
                                         frame), axes as InterHuman (X, Y, Z) = (x, -z, y) of ours;
                                         [0:66] our 22 joints, [66:186] the 40 hand joints placed at
                                         their wrist (we capture no fingers; InterHuman ships none
                                         either, #15), [186:312] 21 local rotations in 6D (below),
                                         [312:492] identity hand rotations
    features/p1/<id>.npy, features/p2/<id>.npy  (T30-1, 262) float32 interhuman_features, with [132:258]
                                         the raw file's rotations of frames 0..T30-2 (what InterGen's
                                         process_motion_np passes through; the folder avoids the word
                                         person1: InterGen would load it as motions)
    annots/<id>.txt                      the sequence's texts, one per line, at least three (fewer are
                                         repeated in turn)
    train.txt, val.txt, test.txt         what InterGen reads; split/{train,val,test}.txt the same
                                         (InterHuman's download layout)
    ignore_list.txt                      the sequences left out (their reasons are in conversion.json)
    global_mean.npy, global_std.npy      (262,) float32 per-dimension mean/std of the train features,
                                         both persons (std < 1e-6 -> 1): copy over InterGen's
                                         data/global_{mean,std}.npy to normalise with ours
    conversion.json                      source export, settings, per sequence its split, frame count,
                                         text source and ``transform`` {yaw0 (rad), translation (m),
                                         raw_yaw (rad)}: world = R_y(yaw0) shared + translation
                                         (PairTransform), the raw files' positions = R_y(raw_yaw)
                                         shared; ``raw_yaw_turned`` lists the pairs with raw_yaw != 0;
                                         the skipped sequences with their reasons ("complete": false
                                         until the conversion finishes)

Rotations, slots ``[186:312]``: joint ``i + 1`` (i = 0..20) as 6D in InterHuman's layout, the first two
matrix columns flattened by row, ``rot_mat[..., :2].reshape(6) = [r00, r01, r10, r11, r20, r21]``
(:func:`rotations_6d_rows`, inverse :func:`rotations_from_6d_rows`). That is the layout InterGen's
``swap_left_right_rot`` assumes: it negates slots 1, 2, 4 (``M R M``, ``M = diag(-1, 1, 1)``, an
x-reflection) and swaps the left and right chains, so a mirrored sample holds valid rotations, and
our mirror of the joints (x -> -x, left <-> right) gives exactly those rotations. What a slot means
differs, and is approximated: InterHuman stores SMPL-H's pose rotations, each joint's rotation relative
to its parent in the body model's T-pose rest frame, twist included; ours are
:func:`~dualhuman_builder.export.features.local_rotations` recomputed from the joint positions: the
smallest rotation ("swing") taking HumanML3D's rest direction of the bone ENDING at joint ``i + 1``
onto the bone, relative to the parent bone's, in the root facing frame, rest arms down (not SMPL's
T-pose), no twist (not observable from positions). InterGen feeds these dims to its model and its
normaliser, so a model trained on InterHuman sees different values there; positions, velocities and
contacts are exact.

Facing -Z: InterGen turns each person to face +Z with ``qbetween(forward, +Z)`` in float32, which is
NaN when that hip facing is exactly -Z (every face-to-face pair written in person 1's frame).
InterGen canonicalises at the first frame of a sample (frame 0, or a random frame for motions longer
than 300 frames), so a pair in which some frame's hip facing lies within
:data:`INTERGEN_MIN_FROM_MINUS_Z` of -Z has its raw positions turned by a small multiple of
:data:`INTERGEN_YAW_NUDGE` (0.11 degrees) about the vertical through the origin, the one leaving the
fewest frames near -Z (none, unless a person turns through -Z while moving): one rigid turn of both
persons, so no relative geometry changes, and InterGen's own canonicalisation removes it again (person
2 lands where :func:`to_interhuman`'s own features put it, to float32 precision).
The local rotations do not depend on it; ``raw_yaw`` records it and :func:`read_interhuman` undoes it.

HumanML3D (:func:`to_humanml3d`, ``dualhuman export humanml3d OUT DEST``)
--------------------------------------------------------------------------

Facts relied on (EricGuo5513/HumanML3D ``motion_representation``, ``cal_mean_variance``,
``text_process.py``; the T2M / MDM ``Text2MotionDataset``): 20 fps; ``new_joint_vecs/<name>.npy``
``(T-1, 263)``; ``new_joints/<name>.npy`` = ``recover_from_ric`` of those vectors, ``(T-1, 22, 3)``
canonical frame; ``texts/<name>.txt`` lines ``caption#tokens#from#to`` (seconds; ``0.0#0.0`` = whole
clip), tokens ``word/POS`` separated by spaces (spaCy: alphabetic tokens only, lemmas of nouns and
verbs except "left"); ``Mean.npy``/``Std.npy`` with one std per feature group; split lists
``train.txt``, ``val.txt``, ``test.txt``, ``all.txt``. The T2M loaders skip motions with fewer than 40
or at least 200 rows (2 s to 10 s) and silently drop a motion whose text line does not parse.

Written under ``DEST``, one motion per person, named ``<id>_a`` and ``<id>_b`` (the export's person
keys; there is no established two-person naming in this layout): ``new_joint_vecs/`` the first 263
dims of :func:`~dualhuman_builder.export.features.motion_features` of the joints resampled to 20 fps
(exactly HumanML3D's part; the export's 6 extra dims are dropped, so the world placement is not kept;
the performers' own bone lengths unless ``retarget``), ``new_joints/``, ``texts/`` (every motion gets its
sequence's texts: they describe the pair), ``Mean.npy``/``Std.npy`` (263,) float32 over the train
motions (HumanML3D computed them over all clips), the split lists, ``conversion.json``.

Tokens: no spaCy model is available offline, so by default the tokens are the caption's alphabetic
words, lowercased (hyphens removed, apostrophe suffixes dropped), not lemmatised, each tagged
``OTHER``. The T2M evaluator's word vectoriser still tags its motion words (left, arm, walk, ...) by its
own list, but unknown inflections become ``unk``: evaluator metrics on such tokens are not comparable
to published ones. Pass ``tokenize`` (caption -> list of ``word/POS`` strings, e.g. built on spaCy as
HumanML3D's ``process_text``) for exact tokens.

Both converters
---------------

``split`` picks the export split to convert (``train``, ``test``) or ``all``; the lists keep the
export's split of every converted sequence. The export has no validation split, so ``val.txt`` repeats
``test.txt`` (code that validates runs; do not select a model on it and report test numbers). No list
is ever empty (InterGen's and the T2M loaders raise on an empty split): a list whose split has no
converted sequence (a one-sequence export, ``split="train"``) lists every converted sequence instead;
``conversion.json`` names those under ``filled_splits`` and says so in ``notes``. Figures on such a
list measure the training data. No file holds NaN or inf: a value that is not finite in float32
(joints so large that a velocity overflows) stops the conversion with a DualhumanError naming the
file, hence the sequence, before it is written.
Captions are put on one line (whitespace collapsed; ``#`` becomes a space in HumanML3D). A sequence
without text gets ``"two people interact: <label>."`` per label when ``label_texts`` (counted as
``texts_from_labels``), else it is skipped; skipped sequences are listed with their reason. The
export is read safely: its manifest is checked, every file read is checked against the manifest's
SHA-256, arrays are loaded with ``allow_pickle=False``. ``DEST`` must be new, empty, or an earlier
conversion of the same layout (whose files are then replaced).

``retarget`` (``--retarget``): ``"none"`` (default) keeps the performers' bone lengths, and the output
is byte for byte what it is without the option; ``"humanml3d"`` retargets both persons, after
resampling, to HumanML3D's reference skeleton (:mod:`dualhuman_builder.export.retarget`: each bone's
direction kept per frame, its length set to the reference's, the root path scaled by the leg ratio,
the feet put back on the floor), so the features lie where HumanML3D's Mean/Std and the T2M evaluators
expect them; every file, ``new_joints`` included, then holds the retargeted joints, which
``recover_from_ric`` and ``recover_from_rot`` (with offsets from ``new_joints`` frame 0) rebuild.
``conversion.json`` ``retarget`` gives the skeleton, its bone lengths and the ratios reference /
source (min, max, mean, per bone), and each sequence's ``retarget`` the same per person.
``"interhuman"`` raises: no published numbers give InterHuman's (SMPL neutral) skeleton.
"""

from __future__ import annotations

import hashlib
import json
import re
import shutil
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from dualhuman_builder import __version__
from dualhuman_builder.errors import DualhumanError, FormatError
from dualhuman_builder.export.features import (
    HUMANML3D_DIM,
    HUMANML3D_FPS,
    _rotate_y,
    feature_stats,
    local_rotations,
    motion_features,
    recover_joints,
    resample_joints,
    root_facing,
)
from dualhuman_builder.export.interhuman import (HIP_JOINTS, INTERHUMAN_FPS, PairTransform, interhuman_features,
                                                 rotations_6d_rows, rotations_from_6d_rows)  # fmt: skip
from dualhuman_builder.export.files import MANIFEST, PERSONS, json_bytes, read_manifest, read_npz
from dualhuman_builder.export.retarget import reference_lengths, retarget_joints, summarize
from dualhuman_builder.fileio import atomic_open

CONVERSION = "conversion.json"
CONVERT_FORMAT = "dualhuman-conversion"
#: InterGen drops motions with fewer frames (``min_gt_length``).
INTERGEN_MIN_FRAMES = 15
#: InterHuman raw layout: 62 joint positions then 51 6D rotations.
INTERHUMAN_RAW_DIM = 62 * 3 + 51 * 6
#: Our Y-up world to InterHuman's Z-up axes (row vectors: ``raw = ours @ TO_Z_UP.T``).
TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
#: SMPL-H hand joints (hand chains, then finger tips) of each side, as in InterGen's mirroring.
HAND_JOINTS = {20: [*range(22, 37), *range(52, 57)], 21: [*range(37, 52), *range(57, 62)]}
#: T2M loaders keep motions with ``T2M_MIN_ROWS <= rows < T2M_MAX_ROWS`` (HumanML3D).
T2M_MIN_ROWS, T2M_MAX_ROWS = 40, 200
#: Slice of a 262-dim InterGen feature row holding the 21 rotations (``[186:312]`` of the raw row).
INTERGEN_ROT_FEATURES = slice(132, 258)
#: A hip facing closer than this to -Z (rad) at the frame InterGen canonicalises at makes its ``qbetween``
#: (rotation from the facing onto +Z) degenerate; the raw files of such a pair are turned by a multiple
#: of :data:`INTERGEN_YAW_NUDGE` about the vertical through the origin.
INTERGEN_MIN_FROM_MINUS_Z = 1e-3
INTERGEN_YAW_NUDGE = 2e-3
_IDENTITY_6D = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 0.0])  # rot_mat[:, :2] of the identity, flattened by row
_TOKEN_RE = re.compile(r"^[^\s/#]+/[^\s/#]+$")


# ================================================================================ reading
def _open_export(export_dir, split: str) -> tuple[Path, dict, list[str]]:
    """``(root, manifest, sequence ids of split)``; FormatError when ``export_dir`` is no export."""
    root = Path(export_dir)
    fix = "give the folder written by `dualhuman export WS OUT` (it holds manifest.json)"
    if not root.is_dir():
        raise FormatError("is not a folder", path=root, fix=fix)
    try:
        manifest = read_manifest(root)
    except ValueError as e:
        raise FormatError(str(e), path=root, fix=fix) from None
    seqs = manifest.get("sequences")
    if not isinstance(seqs, dict) or not isinstance(manifest.get("files"), dict):
        raise FormatError("manifest.json lacks its 'sequences' or 'files' table", path=root,
                          fix=f"re-run the export, then `dualhuman export verify {root}`")  # fmt: skip
    fps = manifest.get("fps")
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not fps > 0:
        raise FormatError(f"manifest.json gives fps {fps!r}", path=root, fix="re-run the export")
    names = sorted({info.get("split") for info in seqs.values() if isinstance(info, dict)} - {None})
    if split != "all" and split not in names:
        raise ValueError(f"unknown split {split!r}; this export has {names} or 'all'")
    ids = sorted(s for s, info in seqs.items() if split == "all" or info.get("split") == split)
    if not ids:
        raise ValueError(f"split {split!r} of {root} has no sequences")
    return root, manifest, ids


def _read_checked(root: Path, manifest: dict, rel: str) -> bytes:
    rec = manifest["files"].get(rel)
    fix = f"run `dualhuman export verify {root}` and re-run the export"
    if not isinstance(rec, dict):
        raise FormatError(f"the manifest does not list {rel}", path=root, fix=fix)
    try:
        data = (root / rel).read_bytes()
    except OSError as e:
        raise FormatError(f"{rel} is unreadable ({e.strerror or e})", path=root, fix=fix) from None
    if hashlib.sha256(data).hexdigest() != rec.get("sha256"):
        raise FormatError(f"{rel}: sha256 differs from the manifest (corrupted or modified)", path=root, fix=fix)
    return data


def _read_sequence(root: Path, manifest: dict, sid: str) -> tuple[np.ndarray, np.ndarray, list[str], list[str]]:
    """``(joints a, joints b (T, 22, 3) world m, texts, labels)`` of one exported sequence."""
    base = f"sequences/{sid}"
    try:
        motion = read_npz(_read_checked(root, manifest, f"{base}/motion.npz"))
    except ValueError as e:
        raise FormatError(f"{base}/motion.npz: {e}", path=root) from None
    missing = [f"{p}.joints" for p in PERSONS if f"{p}.joints" not in motion]
    if missing:
        raise FormatError(f"{base}/motion.npz lacks {missing}", path=root)
    texts, labels = [], []
    if f"{base}/text.json" in manifest["files"]:
        try:
            doc = json.loads(_read_checked(root, manifest, f"{base}/text.json").decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise FormatError(f"{base}/text.json is not UTF-8 JSON ({e})", path=root) from None
        texts = [t for t in doc.get("texts", []) if isinstance(t, str)]
        labels = [t for t in doc.get("labels", []) if isinstance(t, str)]
    return motion["a.joints"], motion["b.joints"], texts, labels


# ================================================================================ writing
def _one_line(text: str) -> str:
    return " ".join(text.split())


def _sentences(texts: list[str], labels: list[str], label_texts: bool) -> tuple[list[str], str | None]:
    """The sentences of a sequence and their source (``texts``, ``labels``, or None: none)."""
    out = [s for s in map(_one_line, texts) if s]
    if out:
        return out, "texts"
    if label_texts:
        out = [f"two people interact: {_one_line(lb.replace('_', ' '))}." for lb in labels if _one_line(lb)]
    return (out, "labels") if out else ([], None)


def _prepare_dest(dest, layout: str, owned: Sequence[str]) -> Path:
    dest = Path(dest)
    if dest.exists() and not dest.is_dir():
        raise ValueError(f"{dest} exists and is not a folder")
    if dest.is_dir() and any(dest.iterdir()):
        try:
            doc = json.loads((dest / CONVERSION).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            doc = None
        if not (isinstance(doc, dict) and doc.get("format") == CONVERT_FORMAT and doc.get("layout") == layout):
            raise ValueError(f"{dest} is a non-empty folder that is not an earlier {layout} conversion; "
                             "choose an empty or new folder")  # fmt: skip
        (dest / CONVERSION).unlink()
        for name in owned:
            path = dest / name
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            elif path.exists() or path.is_symlink():
                path.unlink()
    dest.mkdir(parents=True, exist_ok=True)
    with atomic_open(dest / CONVERSION, "wb") as f:  # marks an unfinished conversion; replaced at the end
        f.write(json_bytes({"format": CONVERT_FORMAT, "layout": layout, "complete": False}))
    return dest


def _save(path: Path, arr: np.ndarray) -> None:
    """Write ``arr`` as float32 ``.npy``; DualhumanError (nothing written) when a value is NaN or inf
    once in float32 (the training code would silently learn from it). The file name names the motion."""
    data = np.asarray(arr, dtype=np.float32)
    bad = ~np.isfinite(data)
    if bad.any():
        raise DualhumanError(f"refusing to write {path.parent.name}/{path.name}: {int(bad.sum())} value(s) are NaN or "
                             f"inf in float32 (first at index {tuple(int(i) for i in np.argwhere(bad)[0])})",
                             path=path, fix="check that sequence's joints (`dualhuman export verify OUT`); leave it "
                             "out of the export or fix its motion, then convert again")  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, data, allow_pickle=False)


def _write_lines(path: Path, lines: Sequence[str]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"{line}\n" for line in lines), encoding="utf-8")


def _split_lists(split_of: dict[str, str]) -> dict[str, list[str]]:
    """train/val/test/all lists of names; val repeats test (the export has no validation split). A list
    that would be empty gets every converted name: the loaders raise on an empty split (see
    :func:`_filled_splits`)."""
    lists = {name: sorted(n for n, s in split_of.items() if s == name) for name in ("train", "test")}
    lists = {name: names or sorted(split_of) for name, names in lists.items()}
    return {**lists, "val": lists["test"], "all": sorted(split_of)}


def _filled_splits(split_of: dict[str, str]) -> list[str]:
    """The lists of :func:`_split_lists` that hold every converted name because their split is empty."""
    empty = [name for name in ("train", "test") if not any(s == name for s in split_of.values())]
    return sorted(empty + (["val"] if "test" in empty else []))


def _finish(dest: Path, layout: str, root: Path, manifest: dict, split: str, fps: float, split_of: dict,
            sequences: dict, skipped: dict, extra: dict) -> dict[str, Any]:  # fmt: skip
    n = {k: len(v) for k, v in _split_lists(split_of).items()}
    filled = _filled_splits(split_of)
    notes = [(f"{', '.join(f'{k}.txt' for k in filled)} would be empty (no converted sequence in that split) "
              "and list every converted sequence instead, so that the loaders run; do not report figures on them")]
    notes = notes if filled else []
    doc = {
        "format": CONVERT_FORMAT, "layout": layout, "complete": True, "toolkit_version": __version__,
        "source": {"export": str(root.resolve()), "format_version": manifest.get("format_version"),
                   "toolkit_version": manifest.get("toolkit_version"),
                   "manifest_sha256": hashlib.sha256((root / MANIFEST).read_bytes()).hexdigest()},
        "dest": str(dest), "split": split, "fps": fps, "sequences_converted": len(sequences),
        "counts": {"train": n["train"], "val": n["val"], "test": n["test"], "all": n["all"]},
        "texts_from_labels": sorted(s for s, d in sequences.items() if d["text_source"] == "labels"),
        "filled_splits": filled, "notes": notes,
        **extra, "skipped": dict(sorted(skipped.items())), "sequences": dict(sorted(sequences.items())),
    }  # fmt: skip
    with atomic_open(dest / CONVERSION, "wb") as f:
        f.write(json_bytes(doc))
    return doc


def _retarget_doc(retarget, ref: np.ndarray | None, sequences: dict) -> dict[str, Any]:
    """``conversion.json``'s ``retarget``: the skeleton (``none``, ``humanml3d`` or ``custom``), its bone
    lengths and the bone-length ratios (reference / source) over every converted person."""
    if ref is None:
        return {"skeleton": "none"}
    reports = [r for d in sequences.values() for r in d.get("retarget", {}).values()]
    return {"skeleton": retarget if isinstance(retarget, str) else "custom", "bone_lengths": ref[1:].tolist(),
            **summarize(reports)}


# ================================================================================ InterGen
_INTERGEN_PATH_WORDS = ("person1", "person2", "motions_processed", "npy")


def _intergen_yaw_nudge(ca: np.ndarray, cb: np.ndarray) -> float:
    """Yaw (rad) to turn the pair's raw files by so that the fewest frames have a hip facing within
    :data:`INTERGEN_MIN_FROM_MINUS_Z` of -Z: 0 when none has, else the best of +-1, +-2
    :data:`INTERGEN_YAW_NUDGE`. Every frame counts: InterGen canonicalises at the first frame of a random
    300-frame window. Frames whose hips are vertically aligned (facing undefined) are not counted."""
    yaws = []
    for c in (ca, cb):
        across = c[:, HIP_JOINTS[0]] - c[:, HIP_JOINTS[1]]
        ok = np.hypot(across[:, 0], across[:, 2]) > 1e-6
        yaws.append(np.arctan2(across[ok, 2], -across[ok, 0]))  # forward = up x across, yaw 0 = +Z
    yaw = np.concatenate(yaws)

    def near(nudge: float) -> int:
        return int((np.abs(np.angle(np.exp(1j * (yaw + nudge - np.pi)))) < INTERGEN_MIN_FROM_MINUS_Z).sum())

    candidates = [0.0] + [k * INTERGEN_YAW_NUDGE for k in (1, -1, 2, -2)]
    return min(candidates, key=near)  # the first of the fewest: 0 when no frame is near -Z


def _intergen_raw(c: np.ndarray, yaw: float = 0.0) -> np.ndarray:
    """InterHuman's raw ``(T, 492)`` float32 of canonical joints ``c (T, 22, 3)`` (Y-up, 30 fps), the
    positions turned by ``yaw`` rad about +Y (the local rotations do not change under a turn)."""
    T = len(c)
    pos = np.empty((T, 62, 3))
    pos[:, :22] = _rotate_y(c, yaw) if yaw else c
    for wrist, hand in HAND_JOINTS.items():
        pos[:, hand] = pos[:, wrist, None]
    rot = np.tile(_IDENTITY_6D, (T, 51, 1))
    rot[:, :21] = rotations_6d_rows(local_rotations(c, root_facing(c, INTERHUMAN_FPS)))
    return np.concatenate([(pos @ TO_Z_UP.T).reshape(T, -1), rot.reshape(T, -1)], axis=1).astype(np.float32)


def to_interhuman(export_dir, dest, split: str = "all", label_texts: bool = True, retarget="none") -> dict[str, Any]:
    """Write the export in ``export_dir`` in InterGen's InterHuman layout under ``dest`` (module
    docstring: files, frames, units). ``retarget``: ``"none"``, ``"humanml3d"`` or 21 bone lengths (m),
    see :func:`~dualhuman_builder.export.retarget.reference_lengths` (``"interhuman"`` has no published
    skeleton and raises). Returns the ``conversion.json`` document (counts, skipped sequences with
    reasons, per-sequence transforms and bone-length ratios). FormatError: not an export, or a file
    differs from its manifest; ValueError: unknown split, ``dest`` not usable; DualhumanError: a
    ``retarget`` that names no usable skeleton."""
    ref = reference_lengths(retarget)
    root, manifest, ids = _open_export(export_dir, split)
    where = str(Path(dest).absolute())
    bad = [w for w in _INTERGEN_PATH_WORDS if w in where]
    if bad:
        raise ValueError(f"{dest}: the path contains {bad}; InterGen derives file paths by replacing these words "
                         "anywhere in the path, so choose a folder whose path does not contain them")  # fmt: skip
    owned = ("motions_processed", "features", "annots", "split", "train.txt", "val.txt", "test.txt",
             "ignore_list.txt", "global_mean.npy", "global_std.npy")  # fmt: skip
    dest = _prepare_dest(dest, "interhuman", owned)
    fps = float(manifest["fps"])
    sequences: dict[str, dict] = {}
    skipped: dict[str, str] = {}
    feats_of: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for sid in ids:
        ja, jb, texts, labels = _read_sequence(root, manifest, sid)
        sentences, source = _sentences(texts, labels, label_texts)
        hit = [w for w in _INTERGEN_PATH_WORDS if w in sid]
        if hit:
            skipped[sid] = f"the id contains {hit}, which InterGen's path derivation breaks on"
            continue
        if source is None:
            skipped[sid] = "no text and no labels" if label_texts else "no text (label_texts is off)"
            continue
        try:
            a30, b30 = resample_joints(ja, fps, INTERHUMAN_FPS), resample_joints(jb, fps, INTERHUMAN_FPS)
            if len(a30) < INTERGEN_MIN_FRAMES:
                raise ValueError(f"{len(a30)} frames at 30 fps, InterGen needs at least {INTERGEN_MIN_FRAMES}")
            reports = None
            if ref is not None:
                (a30, rep_a), (b30, rep_b) = retarget_joints(a30, ref), retarget_joints(b30, ref)
                reports = {"a": rep_a, "b": rep_b}
            feats = interhuman_features(a30, b30, INTERHUMAN_FPS, target_fps=None)
            canon = [feats.transform.to_canonical(j) for j in (a30, b30)]
            nudge = _intergen_yaw_nudge(*canon)
            raws = [_intergen_raw(c, nudge) for c in canon]
        except ValueError as e:
            skipped[sid] = str(e)
            continue
        pair = []
        for raw, f in zip(raws, (feats.person1, feats.person2)):
            f = f.copy()  # InterGen passes the raw rotations of frames 0..T-2 through to its features
            f[:, INTERGEN_ROT_FEATURES] = raw[:-1, 186:312]
            pair.append(f)
        for k, (raw, f) in enumerate(zip(raws, pair), 1):
            _save(dest / "motions_processed" / f"person{k}" / f"{sid}.npy", raw)
            _save(dest / "features" / f"p{k}" / f"{sid}.npy", f)
        _write_lines(dest / "annots" / f"{sid}.txt", [sentences[i % len(sentences)] for i in range(max(3, len(sentences)))])
        tr = feats.transform
        sequences[sid] = {"split": manifest["sequences"][sid].get("split"), "frames": len(a30), "text_source": source,
                          "transform": {"yaw0": tr.yaw0, "translation": list(tr.translation),
                                        "raw_yaw": nudge}}  # fmt: skip
        if reports is not None:
            sequences[sid]["retarget"] = reports
        feats_of[sid] = (pair[0], pair[1])
    if not sequences:
        raise ValueError(f"no sequence of {root} could be converted: {skipped}")
    split_of = {sid: d["split"] for sid, d in sequences.items()}
    for name, names in _split_lists(split_of).items():
        if name != "all":
            _write_lines(dest / f"{name}.txt", names)
            _write_lines(dest / "split" / f"{name}.txt", names)
    _write_lines(dest / "ignore_list.txt", sorted(skipped))
    train = [f for sid in sorted(feats_of) if split_of[sid] == "train" for f in feats_of[sid]]
    data = np.concatenate(train or [f for sid in sorted(feats_of) for f in feats_of[sid]]).astype(np.float64)
    std = data.std(axis=0)
    std[std < 1e-6] = 1.0
    _save(dest / "global_mean.npy", data.mean(axis=0))
    _save(dest / "global_std.npy", std)
    extra = {"stats_over": "train" if train else "all converted (no train sequence)",
             "persons": {"person1": "a", "person2": "b"},
             "raw_yaw_turned": sorted(s for s, d in sequences.items() if d["transform"]["raw_yaw"]),
             "retarget": _retarget_doc(retarget, ref, sequences)}  # fmt: skip
    return _finish(dest, "interhuman", root, manifest, split, INTERHUMAN_FPS, split_of, sequences, skipped, extra)


def read_interhuman(dest, seq_id: str) -> np.ndarray:
    """World joints ``(2, T30, 22, 3)`` float32 (metres, Y up; persons a, b) of ``seq_id`` in an
    InterHuman conversion ``dest``: the raw files' positions turned back by the saved ``raw_yaw`` and
    mapped to the world with the saved transform."""
    dest = Path(dest)
    try:
        tr = json.loads((dest / CONVERSION).read_text(encoding="utf-8"))["sequences"][seq_id]["transform"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{dest}: no transform of {seq_id!r} in {CONVERSION} ({e!r})") from None
    transform = PairTransform(float(tr["yaw0"]), tuple(float(v) for v in tr["translation"]))
    raw_yaw = float(tr.get("raw_yaw", 0.0))
    out = []
    for k in (1, 2):
        raw = np.load(dest / "motions_processed" / f"person{k}" / f"{seq_id}.npy", allow_pickle=False)
        out.append(transform.to_world(_rotate_y(raw[:, :66].reshape(len(raw), 22, 3) @ TO_Z_UP, -raw_yaw)))
    return np.stack(out).astype(np.float32)


# ================================================================================ HumanML3D
def humanml3d_tokens(caption: str) -> list[str]:
    """Default tokens of ``caption``: its alphabetic words lowercased, tagged ``OTHER`` (``word/OTHER``);
    hyphens are removed and apostrophe suffixes dropped first (no lemmas, no POS: see the module)."""
    text = re.sub(r"['\u2019]\w*", "", caption.replace("-", ""))
    return [f"{w.lower()}/OTHER" for w in re.findall(r"[^\W\d_]+", text)]


def to_humanml3d(export_dir, dest, split: str = "all", label_texts: bool = True,
                 tokenize: Callable[[str], Sequence[str]] | None = None,
                 retarget="none") -> dict[str, Any]:  # fmt: skip
    """Write the export in ``export_dir`` in HumanML3D's per-person layout under ``dest`` (module
    docstring). ``tokenize``: caption -> ``word/POS`` tokens (default :func:`humanml3d_tokens`).
    The vectors are recomputed from the export's joints, so dims [67:193] follow HumanML3D's rotation
    convention (:func:`~dualhuman_builder.export.features.humanml3d_rotations`) whatever the export's
    format version: its ``recover_from_rot`` rebuilds the joints given each motion's own bone lengths.
    Returns the ``conversion.json`` document; ``outside_t2m_length`` names the motions the T2M loaders
    would skip (fewer than 40 or at least 200 rows). ``retarget`` as :func:`to_interhuman`: with
    ``"humanml3d"`` every motion has HumanML3D's reference bone lengths, as HumanML3D's own clips.
    Errors as :func:`to_interhuman`; ValueError when ``tokenize`` returns a token that is not ``word/POS``."""
    ref = reference_lengths(retarget)
    root, manifest, ids = _open_export(export_dir, split)
    owned = ("new_joint_vecs", "new_joints", "texts", "Mean.npy", "Std.npy", "train.txt", "val.txt", "test.txt", "all.txt")
    dest = _prepare_dest(dest, "humanml3d", owned)
    tokenize = tokenize or humanml3d_tokens
    fps = float(manifest["fps"])
    sequences: dict[str, dict] = {}
    skipped: dict[str, str] = {}
    split_of: dict[str, str] = {}
    vecs: dict[str, np.ndarray] = {}
    for sid in ids:
        ja, jb, texts, labels = _read_sequence(root, manifest, sid)
        sentences, source = _sentences(texts, labels, label_texts)
        lines = []
        for s in (_one_line(s.replace("#", " ")) for s in sentences):
            toks = [str(t) for t in tokenize(s)]
            wrong = [t for t in toks if not _TOKEN_RE.match(t)]
            if wrong:
                raise ValueError(f"tokenize({s!r}) returned {wrong[:3]}: tokens must be 'word/POS' without spaces or '#'")
            if toks:  # a caption without words would break the loaders' token parsing
                lines.append(f"{s}#{' '.join(toks)}#0.0#0.0")
        if not lines:
            skipped[sid] = "no caption with words (from texts" + (" or labels)" if label_texts else "; label_texts is off)")
            continue
        try:
            j20 = [resample_joints(j, fps, HUMANML3D_FPS) for j in (ja, jb)]
            if len(j20[0]) < 2:
                raise ValueError(f"{len(j20[0])} frame at 20 fps: too short")
            reports = None
            if ref is not None:
                (ja20, rep_a), (jb20, rep_b) = (retarget_joints(j, ref) for j in j20)
                j20, reports = [ja20, jb20], {"a": rep_a, "b": rep_b}
            f263 = [motion_features(j, HUMANML3D_FPS)[:, :HUMANML3D_DIM] for j in j20]
        except ValueError as e:
            skipped[sid] = str(e)
            continue
        seq_split = manifest["sequences"][sid].get("split")
        for p, f in zip(PERSONS, f263):
            name = f"{sid}_{p}"
            _save(dest / "new_joint_vecs" / f"{name}.npy", f)
            _save(dest / "new_joints" / f"{name}.npy", recover_joints(f, world=False)[:-1])
            _write_lines(dest / "texts" / f"{name}.txt", lines)
            split_of[name], vecs[name] = seq_split, f
        sequences[sid] = {"split": seq_split, "frames": len(j20[0]), "text_source": source,
                          "motions": [f"{sid}_{p}" for p in PERSONS]}  # fmt: skip
        if reports is not None:
            sequences[sid]["retarget"] = reports
    if not sequences:
        raise ValueError(f"no sequence of {root} could be converted: {skipped}")
    for name, names in _split_lists(split_of).items():
        _write_lines(dest / f"{name}.txt", names)
    train = [vecs[n] for n in sorted(vecs) if split_of[n] == "train"]
    mean, std = feature_stats(train or [vecs[n] for n in sorted(vecs)])
    _save(dest / "Mean.npy", mean)
    _save(dest / "Std.npy", std)
    extra = {"stats_over": "train" if train else "all converted (no train sequence)", "motions": len(vecs),
             "outside_t2m_length": sorted(n for n, f in vecs.items() if not T2M_MIN_ROWS <= len(f) < T2M_MAX_ROWS),
             "retarget": _retarget_doc(retarget, ref, sequences)}  # fmt: skip
    return _finish(dest, "humanml3d", root, manifest, split, HUMANML3D_FPS, split_of, sequences, skipped, extra)


__all__ = ["to_interhuman", "to_humanml3d", "read_interhuman", "humanml3d_tokens", "rotations_6d_rows",
           "rotations_from_6d_rows", "CONVERSION", "INTERHUMAN_RAW_DIM", "TO_Z_UP"]  # fmt: skip

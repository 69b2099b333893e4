"""Writing an export folder: :func:`export_dataset`.

Writing is crash-safe and resumable: every file goes to a temporary name and is renamed; a file
whose bytes would not change is not rewritten; a sequence folder whose ``sequence.json`` records
the same inputs (:func:`_fingerprint`) and whose files still match their SHA-256 is kept without
recomputation; ``manifest.json`` comes last, so a folder without it is an unfinished export that
re-running completes. The layout it writes is documented in :mod:`dualhuman_builder.export.card`.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from dualhuman_builder import __version__
from dualhuman_builder.export.card import dataset_card
from dualhuman_builder.export.features import FEATURE_DIM, feature_stats, motion_features
from dualhuman_builder.export.files import (FORMAT, FORMAT_VERSION, LABELS_JSON, MANIFEST, OWN_FOLDERS, PERSONS,
                                            SEQUENCE_JSON, check_seq_id, file_matches, json_bytes, json_clean,
                                            load_motion, npy_bytes, npz_bytes, put_bytes, put_copy,
                                            sha256_bytes)  # fmt: skip
from dualhuman_builder.export.items import ExportItem, PreparedItem, prepare_item
from dualhuman_builder.export.schema import build_schema
from dualhuman_builder.export.splits import make_splits
from dualhuman_builder.fileio import remove_partials
from dualhuman_builder.labels import Vocabulary, load_vocabulary
from dualhuman_builder.tracks import InteractionSequence

#: The stages a sequence can have; ``expect`` of :func:`export_dataset` names some of them.
STAGES = ("motion", "contacts", "text", "renders")
#: Version of the image targets' definition (``renders/targets.npz``): part of a rendered sequence's fingerprint.
TARGETS_VERSION = 1
#: Arrays of ``renders/targets.npz`` (shapes in :func:`~dualhuman_builder.export.schema.build_schema`).
TARGET_ARRAYS = ("joints_cam", "transl", "prob", "box", "frames", "views")
#: Largest distance (pixels) between a render's keypoints and its joints projected by its cameras.
KEYPOINT_TOLERANCE_PX = 0.5


def _fingerprint(p: PreparedItem, fps: float) -> str:
    """Hex SHA-256 of everything a sequence folder is computed from: the format and toolkit
    versions, ``fps``, the prepared labels, texts and metadata, the tracks' arrays, the contacts,
    and each render file's path, size, mtime and inode (render files are linked, not read)."""
    h = hashlib.sha256()

    def add(x):
        h.update(x if isinstance(x, bytes) else json.dumps(x, sort_keys=True, default=str).encode())
        h.update(b"\0")

    seq = p.item.sequence
    add([FORMAT_VERSION, __version__, fps, p.subjects, p.labels, p.multi_hot, p.symmetric, p.item.annotations, p.texts,
         p.roles, json_clean(p.item.meta),
         json_clean(seq.meta), seq.take, list(seq.frame_range)])  # fmt: skip
    for track in seq.actors:
        add([track.model, track.model_version, list(track.bone_names), list(track.shape_names)])
        for arr in (track.pose, track.transl, track.shape):
            add(np.ascontiguousarray(arr).tobytes())
    if p.contacts is not None:
        for k in ("labels", "distances", "frame_contact"):
            add(np.ascontiguousarray(p.contacts[k]).tobytes())
        add(p.contacts["events"])
    for rel, src in p.render_files:
        st = src.stat()
        add([rel, st.st_size, st.st_mtime_ns, st.st_ino])
    if p.render_files:
        add(["targets", TARGETS_VERSION])
    return h.hexdigest()


# --------------------------------------------------------------------------------------------- image targets
def normalised_root(root_cam: np.ndarray, K: np.ndarray, width: float, height: float) -> np.ndarray:
    """The paper's translation target of camera-frame roots ``root_cam (..., 3)`` (metres) seen by
    intrinsics ``K (..., 3, 3)`` in a ``width`` x ``height`` image: ``(u_n, v_n, z_n)`` with
    ``u_n = 2 u / width - 1``, ``v_n = 2 v / height - 1`` (the root's pixel ``(u, v) = K root``,
    so -1 and 1 are the image edges) and ``z_n = z width / fx = z 2 tan(fov_x / 2)`` (the depth
    scaled by the horizontal field of view, independent of the focal length). A root at or behind
    the camera gets ``u_n = v_n = 0``. Inverse: :func:`root_from_normalised`."""
    r = np.asarray(root_cam, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    z = r[..., 2]
    ok = z > 1e-6
    zs = np.where(ok, z, 1.0)
    u = (K[..., 0, 0] * r[..., 0] + K[..., 0, 1] * r[..., 1]) / zs + K[..., 0, 2]
    v = K[..., 1, 1] * r[..., 1] / zs + K[..., 1, 2]
    out = np.stack([np.where(ok, 2.0 * u / width - 1.0, 0.0), np.where(ok, 2.0 * v / height - 1.0, 0.0),
                    z * width / K[..., 0, 0]], axis=-1)  # fmt: skip
    return out


def root_from_normalised(transl: np.ndarray, K: np.ndarray, width: float, height: float) -> np.ndarray:
    """Camera-frame roots ``(..., 3)`` metres of translation targets ``transl (..., 3)`` (the
    inverse of :func:`normalised_root` for intrinsics without skew)."""
    t = np.asarray(transl, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    z = t[..., 2] * K[..., 0, 0] / width
    u, v = (t[..., 0] + 1.0) * width / 2.0, (t[..., 1] + 1.0) * height / 2.0
    return np.stack([(u - K[..., 0, 2]) * z / K[..., 0, 0], (v - K[..., 1, 2]) * z / K[..., 1, 1], z], axis=-1)


def mask_boxes(mask: np.ndarray, labels=(1, 2)) -> np.ndarray:
    """Each actor's box ``(len(labels), 4)`` float32 ``x0, y0, x1, y1`` in pixels (pixel edges: the
    actor covers columns ``x0 .. x1 - 1``) of an instance mask ``(H, W)``; zeros for an actor
    covering no pixel."""
    out = np.zeros((len(labels), 4), np.float32)
    for k, label in enumerate(labels):
        hit = mask == label
        cols, rows = np.flatnonzero(hit.any(axis=0)), np.flatnonzero(hit.any(axis=1))
        if len(cols):
            out[k] = (cols[0], rows[0], cols[-1] + 1, rows[-1] + 1)
    return out


def render_targets(joints: np.ndarray, cameras: list[dict], keypoints: np.ndarray, frames: np.ndarray, views,
                   read_mask: Callable[[str, int], np.ndarray | None] | None = None) -> dict[str, np.ndarray]:  # fmt: skip
    """The image-model targets of one render (``renders/targets.npz``): for every camera of
    ``views`` and rendered frame of ``frames``, both persons' ``joints (2, T, 22, 3)`` (world
    metres) in that camera's frame (``joints_cam (C, R, 2, 22, 3)``), the root's
    :func:`normalised_root` over the full image (``transl (C, R, 2, 3)``), the share of the 22
    joints ``keypoints (C, R, 2, 22, 3)`` marks visible (``prob (C, R, 2)``), and each actor's box
    in pixels (``box (C, R, 2, 4)``, :func:`mask_boxes` of ``read_mask(view, frame)``; zeros without
    a mask). ``cameras``: ``cameras.json`` entries (``name``, ``K``, ``R``, ``t``, ``width``,
    ``height``). ValueError when a view has no camera, a frame is outside the sequence, or the
    keypoints are not the joints projected by the cameras (within :data:`KEYPOINT_TOLERANCE_PX`):
    the render is then not of this motion."""
    joints = np.asarray(joints, dtype=np.float64)
    frames = np.asarray(frames, dtype=np.int64)
    views = [str(v) for v in views]
    keypoints = np.asarray(keypoints, dtype=np.float64)
    T = joints.shape[1]
    if keypoints.shape != (len(views), len(frames), 2, 22, 3):
        raise ValueError(f"renders/keypoints.npz joints have shape {keypoints.shape}, expected "
                         f"({len(views)}, {len(frames)}, 2, 22, 3) for its views and frames")  # fmt: skip
    if len(frames) and (frames.min() < 0 or frames.max() >= T):
        raise ValueError(f"the render has frames {frames.min()}..{frames.max()}, the motion has {T} frames: the render "
                         "is not of this motion (render it again)")  # fmt: skip
    by_name = {c.get("name"): c for c in cameras if isinstance(c, dict)}
    missing = [v for v in views if v not in by_name]
    if missing:
        raise ValueError(f"rendered views {missing} have no camera in cameras.json")
    C, R = len(views), len(frames)
    joints_cam = np.zeros((C, R, 2, 22, 3))
    transl = np.zeros((C, R, 2, 3))
    box = np.zeros((C, R, 2, 4), np.float32)
    worst = 0.0
    for c, name in enumerate(views):
        cam = by_name[name]
        try:
            K, Rm, t = (np.asarray(cam[k], dtype=np.float64) for k in ("K", "R", "t"))
            w, h = float(cam["width"]), float(cam["height"])
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"cameras.json: camera {name!r} lacks a usable K, R, t, width or height ({e})") from None
        if K.shape != (3, 3) or Rm.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"cameras.json: camera {name!r} has K {K.shape}, R {Rm.shape}, t {t.shape}")
        pc = joints[:, frames].transpose(1, 0, 2, 3) @ Rm.T + t  # (R, 2, 22, 3)
        joints_cam[c] = pc
        transl[c] = normalised_root(pc[:, :, 0], K, w, h)
        worst = max(worst, projection_error(pc, K, keypoints[c]))
        if read_mask is not None:
            for r, f in enumerate(frames):
                mask = read_mask(name, int(f))
                if mask is not None:
                    box[c, r] = mask_boxes(mask)
    if worst > KEYPOINT_TOLERANCE_PX:
        raise ValueError(f"renders/keypoints.npz is {worst:.2f} px from the motion's joints projected by cameras.json "
                         "(more than 0.5 px): the render is not of this motion (render it again)")  # fmt: skip
    prob = (keypoints[..., 2] > 0.5).mean(axis=-1)
    return {"joints_cam": joints_cam.astype(np.float32), "transl": transl.astype(np.float32),
            "prob": prob.astype(np.float32), "box": box, "frames": frames, "views": np.array(views)}  # fmt: skip


def projection_error(joints_cam: np.ndarray, K: np.ndarray, keypoints: np.ndarray) -> float:
    """Largest distance (pixels) between ``joints_cam (..., 3)`` projected by ``K (3, 3)`` and the
    ``u, v`` of ``keypoints (..., 3)``, over the joints in front of the camera with finite keypoints
    (0.0 when there are none)."""
    pc = np.asarray(joints_cam, dtype=np.float64)
    kp = np.asarray(keypoints, dtype=np.float64)
    z = pc[..., 2]
    ok = (z > 1e-6) & np.isfinite(kp[..., :2]).all(-1)
    if not ok.any():
        return 0.0
    uvw = pc[ok] @ np.asarray(K, dtype=np.float64).T
    d = np.linalg.norm(uvw[:, :2] / uvw[:, 2:3] - kp[ok][:, :2], axis=-1)
    return float(d.max()) if np.isfinite(d).all() else float("inf")


def _targets_bytes(p: PreparedItem, joints: np.ndarray) -> bytes | None:
    """``renders/targets.npz`` of a sequence whose render has ``cameras.json`` and ``keypoints.npz``
    (None otherwise); ``joints (2, T, 22, 3)`` world metres. ValueError for a render that is not of
    this motion or unreadable render files."""
    from PIL import Image

    src = dict(p.render_files)
    if "cameras.json" not in src or "renders/keypoints.npz" not in src:
        return None
    try:
        cams = json.loads(src["cameras.json"].read_text(encoding="utf-8")).get("cameras", [])
        with np.load(src["renders/keypoints.npz"], allow_pickle=False) as z:
            keypoints, frames, views = z["joints"], z["frames"], z["views"]
    except (OSError, ValueError, KeyError, AttributeError) as e:
        raise ValueError(f"render files unreadable ({type(e).__name__}: {e})") from None

    def read_mask(view: str, frame: int):
        path = src.get(f"renders/views/{view}/mask/{frame:05d}.png")
        if path is None:
            return None
        try:
            with Image.open(path) as im:
                return np.asarray(im)
        except OSError as e:
            raise ValueError(f"mask {path} unreadable ({e})") from None

    return npz_bytes(render_targets(joints, cams if isinstance(cams, list) else [], keypoints, frames, views, read_mask))



def _body_model_info(seqs: list[InteractionSequence], num_vertices: int) -> dict[str, Any]:
    """The manifest's ``body_model``: name, version, bone and phenotype names of the sequences'
    tracks and ``num_vertices``; ValueError when the sequences use more than one body model."""
    kinds = {(t.model, t.model_version, t.bone_names, t.shape_names) for s in seqs for t in s.actors}
    if len(kinds) > 1:
        raise ValueError(
            f"sequences use different body models/versions: {sorted({(k[0], k[1], len(k[2])) for k in kinds})}; "
            "export them separately"
        )
    model, version, bones, shapes = kinds.pop()
    return {"name": model, "version": version, "num_bones": len(bones), "num_shape_params": len(shapes),
            "num_vertices": int(num_vertices), "bone_names": list(bones), "shape_names": list(shapes)}  # fmt: skip


def _num_vertices(seqs: list[InteractionSequence]) -> int:
    """The body model's vertex count; 0 when every track is known only by its joints (no bones, no
    phenotype values: an imported dataset), which has no mesh, so the body model is not loaded."""
    if all(not t.bone_names and not t.shape_names for s in seqs for t in s.actors):
        return 0
    from dualhuman_builder.body.model import get_body_model

    return get_body_model().num_vertices


def _clean_folder(folder: Path, keep: set[str]) -> None:
    """Delete files under ``folder`` whose relative path is not in ``keep``, then empty folders."""
    for p in sorted(folder.rglob("*"), reverse=True):
        rel = p.relative_to(folder).as_posix()
        if p.is_file() or p.is_symlink():
            if rel not in keep:
                p.unlink()
        elif p.is_dir() and not any(p.iterdir()):
            p.rmdir()


def _sequence_done(folder: Path, fingerprint: str) -> dict | None:
    """The recorded ``sequence.json`` when it matches ``fingerprint`` and every file it lists is intact."""
    try:
        doc = json.loads((folder / SEQUENCE_JSON).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("fingerprint") != fingerprint or not isinstance(doc.get("files"), dict):
        return None
    for rel, rec in doc["files"].items():
        if not file_matches(folder / rel, rec.get("bytes", -1), rec.get("sha256", "")):
            return None
    return doc


def _write_sequence(p: PreparedItem, folder: Path, fps: float, fingerprint: str) -> tuple[dict, np.ndarray, np.ndarray, int]:
    """Compute and write one sequence folder. Returns ``(sequence.json doc, features a, features b,
    files rewritten)``; ValueError when the motion cannot be turned into features."""
    seq = p.item.sequence
    motion: dict[str, np.ndarray] = {}
    feats = []
    for name, track in zip(PERSONS, seq.actors):
        joints = np.asarray(track.joints(), dtype=np.float32)
        if not np.isfinite(joints).all():
            raise ValueError(f"person {name} joints hold NaN (frames {np.flatnonzero(~np.isfinite(joints).all(axis=(1, 2)))[:5].tolist()})")
        try:
            f = motion_features(joints, fps)
        except ValueError as e:
            raise ValueError(f"person {name} motion features: {e}") from None
        motion.update({f"{name}.pose": track.pose, f"{name}.transl": track.transl, f"{name}.shape": track.shape,
                       f"{name}.joints": joints, f"{name}.features": f})  # fmt: skip
        feats.append(f)
    payload: dict[str, bytes] = {"motion.npz": npz_bytes(motion)}
    if p.contacts is not None:
        c = p.contacts
        payload["contacts.npz"] = npz_bytes({
            "labels_packed": np.packbits(c["labels"], axis=2), "num_vertices": np.int64(c["labels"].shape[2]),
            "distances": c["distances"], "frame_contact": c["frame_contact"]})  # fmt: skip
        payload["contact_events.json"] = json_bytes(c["events"])
    payload["text.json"] = json_bytes({"labels": p.labels, "multi_hot": p.multi_hot, "symmetric": p.symmetric,
                                       "texts": p.texts, "roles": p.roles, "annotations": p.item.annotations})  # fmt: skip
    files: dict[str, dict] = {}
    written = 0
    for rel, data in payload.items():
        files[rel], w = put_bytes(folder / rel, data)
        written += w
    for rel, src in p.render_files:
        if rel == "renders/targets.npz":
            continue  # computed below from the motion, never copied
        files[rel], w = put_copy(src, folder / rel)
        written += w
    try:
        targets, note = _targets_bytes(p, np.stack([motion[f"{n}.joints"] for n in PERSONS])), None
    except ValueError as e:  # the render is kept as it is, without targets: its motion and images stay usable
        targets, note = None, f"no image targets: {e}"
    if targets is not None:
        files["renders/targets.npz"], w = put_bytes(folder / "renders/targets.npz", targets)
        written += w
    doc = _sequence_doc(p, seq, fps, files, fingerprint)
    if note is not None:
        doc["targets_problem"] = note
    _clean_folder(folder, set(files) | {SEQUENCE_JSON})
    written += put_bytes(folder / SEQUENCE_JSON, json_bytes(doc))[1]
    return doc, feats[0], feats[1], written


def _sequence_doc(p: PreparedItem, seq: InteractionSequence, fps: float, files: dict, fingerprint: str) -> dict:
    """The sequence's ``sequence.json``: its description, what it has, the ``fingerprint`` of its
    inputs and ``files`` (relative path -> ``{sha256, bytes}``)."""
    views = sorted({rel.split("/")[2] for rel in files if rel.startswith("renders/views/") and rel.count("/") >= 3})
    has = {"motion": True, "contacts": p.contacts is not None, "text": bool(p.texts),
           "cameras": "cameras.json" in files, "renders": bool(views), "keypoints": "renders/keypoints.npz" in files,
           "targets": "renders/targets.npz" in files}  # fmt: skip
    return {
        "seq_id": p.item.seq_id,
        "frames": seq.num_frames,
        "fps": fps,
        "subjects": list(p.subjects),
        "roles": p.roles,
        "take": seq.take,
        "frame_range": list(seq.frame_range),
        "has": has,
        "render_views": views,
        "num_texts": len(p.texts),
        "labels": p.labels,
        "symmetric": p.symmetric,
        "meta": json_clean({**seq.meta, **p.item.meta}),
        "fingerprint": fingerprint,
        "files": dict(sorted(files.items())),
    }


def _missing_stages(has: Mapping[str, bool], expect: Iterable[str]) -> list[str]:
    """The stages of ``expect`` that ``has`` does not mark present, in ``expect``'s order."""
    return [s for s in expect if not has.get(s, False)]


def export_dataset(
    items: Iterable[ExportItem],
    out_dir: str | Path,
    split_ratio: float = 0.75,
    subject_disjoint: bool = False,
    seed: int = 0,
    strict: bool = False,
    progress: Callable[[str], None] | None = None,
    expect: Iterable[str] = STAGES,
    vocabulary: Vocabulary | None = None,
    splits: Mapping[str, str] | None = None,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Export ``items`` into the folder layout (:mod:`~dualhuman_builder.export.card`) under ``out_dir``;
    returns the manifest.

    ``split_ratio``: share of sequences in train (0 < r <= 1); ``subject_disjoint``: no subject in
    both splits; ``seed``: the split's seed. ``expect``: stages every sequence should have (of
    ``motion``, ``contacts``, ``text``, ``renders``); a sequence lacking one is exported with what
    it has and listed under ``incomplete``. A sequence without motion or with NaN motion is left out
    and listed under ``skipped``. ``strict=True`` turns both into a ValueError. ``progress`` gets one
    line per sequence. ``vocabulary``: the interaction labels (default: the built-in one,
    :func:`~dualhuman_builder.labels.load_vocabulary`). ``splits``: seq_id -> ``"train"`` or ``"test"``, a
    split given from elsewhere (an imported dataset's own lists); those sequences keep it, the others
    are drawn as above among themselves (``subject_disjoint`` holds among the drawn ones only), and the
    manifest's ``split.given`` counts them. ``extra``: further top-level manifest entries (JSON values; e.g. the
    workspace export's ``quality``), written with the rest. Re-running completes a partial export and rewrites only what
    changed. Errors (ValueError): duplicate or unsafe ``seq_id``, text that is not UTF-8, a label outside
    the vocabulary, malformed contacts, a missing ``render_dir``, mixed fps or body models, an
    ``out_dir`` that is a non-empty folder but no export, ``splits`` naming an unknown sequence or split,
    a train split left empty, nothing exportable.
    """
    say = progress or (lambda _msg: None)
    expect = tuple(expect)
    unknown = sorted(set(expect) - set(STAGES))
    if unknown:
        raise ValueError(f"expect names unknown stages {unknown}; choose from {list(STAGES)}")
    if not (isinstance(split_ratio, (int, float)) and 0.0 < float(split_ratio) <= 1.0):
        raise ValueError(f"split_ratio must be in (0, 1], got {split_ratio!r}")
    items = list(items)
    if not items:
        raise ValueError("nothing to export: no items given")
    ids = [check_seq_id(getattr(it, "seq_id", None)) for it in items]
    dup = sorted({s for s in ids if ids.count(s) > 1})
    if dup:
        raise ValueError(f"duplicate seq_id {dup}: every sequence needs its own id")
    splits = dict(splits or {})
    unknown = sorted(str(s) for s in set(splits) - set(ids))
    if unknown:
        raise ValueError(f"splits names sequences that are not exported: {unknown[:5]}")
    wrong = {s: v for s, v in splits.items() if v not in ("train", "test")}
    if wrong:
        raise ValueError(f"splits must map each sequence to 'train' or 'test', got {dict(list(wrong.items())[:5])}")
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not ((out / MANIFEST).exists() or (out / "sequences").is_dir()):
        raise ValueError(f"{out} is a non-empty folder that is not a dataset export; choose an empty or new folder")

    vocabulary = vocabulary or load_vocabulary()
    prepared = [prepare_item(it, vocabulary) for it in items]  # every input error surfaces before anything is written
    skipped: dict[str, str] = {p.item.seq_id: p.problem for p in prepared if p.problem}
    good = [p for p in prepared if not p.problem]
    fps_set = sorted({p.item.sequence.fps for p in good})
    if len(fps_set) > 1:
        by = {f: [p.item.seq_id for p in good if p.item.sequence.fps == f][:3] for f in fps_set}
        raise ValueError(f"sequences have different fps {by}; resample them to one rate before exporting")
    if strict:
        lacking = {p.item.seq_id: _missing_stages({"motion": True, "contacts": p.contacts is not None,
                   "text": bool(p.texts), "renders": any(r.startswith("renders/views/") for r, _ in p.render_files)},
                   expect) for p in good}  # fmt: skip
        lacking = {k: v for k, v in lacking.items() if v}
        if skipped or lacking:
            raise ValueError(f"strict export: sequences skipped {skipped}, incomplete {lacking}")
    if not good:
        raise ValueError(f"no sequence can be exported: {skipped}")
    fps = float(fps_set[0])

    body = _body_model_info([p.item.sequence for p in good], _num_vertices([p.item.sequence for p in good]))
    for p in good:
        if p.contacts is not None and p.contacts["labels"].shape[2] != body["num_vertices"]:
            raise ValueError(f"sequence {p.item.seq_id!r}: contacts have {p.contacts['labels'].shape[2]} vertices, "
                             f"the body model {body['num_vertices']}")  # fmt: skip

    out.mkdir(parents=True, exist_ok=True)
    remove_partials(out)
    seq_root = out / "sequences"
    seq_root.mkdir(exist_ok=True)
    docs: dict[str, dict] = {}
    features: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    rewritten = 0
    for k, p in enumerate(good, 1):
        sid = p.item.seq_id
        folder = seq_root / sid
        fp = _fingerprint(p, fps)
        doc = _sequence_done(folder, fp)
        if doc is not None:
            m = load_motion(folder / "motion.npz")
            features[sid] = (m["a.features"], m["b.features"])
            _clean_folder(folder, set(doc["files"]) | {SEQUENCE_JSON})
            docs[sid] = doc
            say(f"[{k}/{len(good)}] {sid}: up to date")
            continue
        try:
            doc, fa, fb, n = _write_sequence(p, folder, fps, fp)
        except ValueError as e:
            if strict:
                raise ValueError(f"strict export: sequence {sid!r}: {e}") from e
            skipped[sid] = str(e)
            shutil.rmtree(folder, ignore_errors=True)
            say(f"[{k}/{len(good)}] {sid}: skipped ({e})")
            continue
        docs[sid], features[sid] = doc, (fa, fb)
        rewritten += n
        say(f"[{k}/{len(good)}] {sid}: {doc['frames']} frames, {n} files written"
            + (f"; WARNING: {doc['targets_problem']}" if doc.get("targets_problem") else ""))  # fmt: skip
    for stale in sorted(seq_root.iterdir()):
        if stale.name not in docs:
            if stale.is_dir() and not stale.is_symlink():
                shutil.rmtree(stale)
            else:
                stale.unlink()
    if not docs:
        raise ValueError(f"no sequence could be exported: {skipped}")

    given = {sid: s for sid, s in splits.items() if sid in docs}
    subjects = {sid: tuple(d["subjects"]) for sid, d in docs.items() if sid not in given}
    train, test = make_splits(subjects, split_ratio, subject_disjoint, seed)
    train = sorted(train + [sid for sid, s in given.items() if s == "train"])
    test = sorted(test + [sid for sid, s in given.items() if s == "test"])
    if not train:
        raise ValueError("the train split is empty; nothing to compute feature statistics from")
    mean, std = feature_stats([f for sid in train for f in features[sid]])

    files: dict[str, dict] = {}

    def put(rel: str, data: bytes) -> None:
        nonlocal rewritten
        files[rel], w = put_bytes(out / rel, data)
        rewritten += w

    put("splits/train.txt", "".join(f"{s}\n" for s in train).encode())
    put("splits/test.txt", "".join(f"{s}\n" for s in test).encode())
    put("stats/mean.npy", npy_bytes(mean))
    put("stats/std.npy", npy_bytes(std))
    schema = build_schema(body)
    put("schema.json", json_bytes(schema))
    put(LABELS_JSON, json_bytes(vocabulary.as_dict()))
    for sid in sorted(docs):
        d = docs[sid]
        for rel, rec in d["files"].items():
            files[f"sequences/{sid}/{rel}"] = rec
        data = (seq_root / sid / SEQUENCE_JSON).read_bytes()
        files[f"sequences/{sid}/{SEQUENCE_JSON}"] = {"sha256": sha256_bytes(data), "bytes": len(data)}

    split_of = {**{s: "train" for s in train}, **{s: "test" for s in test}}
    incomplete = {sid: miss for sid in sorted(docs) if (miss := _missing_stages(docs[sid]["has"], expect))}
    manifest = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "toolkit_version": __version__,
        "body_model": body,
        "fps": fps,
        "units": {"length": "m", "time": "s", "angle": "rad", "frame_index": "frame at fps"},
        "axes": "Y-up, metres",
        "world_frame": "right-handed, +Y up, floor y = 0; a body at identity faces +Z, its left towards +X",
        "persons": {"a": "actor 0", "b": "actor 1"},
        "feature_dim": FEATURE_DIM,
        "vocabulary": {"file": LABELS_JSON, "size": len(vocabulary)},
        "split": {"ratio": float(split_ratio), "seed": int(seed), "subject_disjoint": bool(subject_disjoint),
                  "given": len(given), "files": {"train": "splits/train.txt", "test": "splits/test.txt"}},  # fmt: skip
        "stats": {"mean": "stats/mean.npy", "std": "stats/std.npy", "over": "train features, both persons"},
        "counts": {
            "sequences": len(docs), "train": len(train), "test": len(test),
            "frames": int(sum(d["frames"] for d in docs.values())),
            "subjects": len({s for d in docs.values() for s in d["subjects"] if s}),
            "texts": int(sum(d["num_texts"] for d in docs.values())),
            **{f"with_{k}": sum(bool(d["has"].get(k)) for d in docs.values())
               for k in ("contacts", "text", "cameras", "renders", "keypoints", "targets")},
            "skipped": len(skipped), "incomplete": len(incomplete), "files": 0,
        },  # fmt: skip
        "expect": list(expect),
        "sequences": {sid: {"frames": docs[sid]["frames"], "subjects": docs[sid]["subjects"], "split": split_of[sid],
                            "has": docs[sid]["has"], "render_views": docs[sid]["render_views"],
                            "num_texts": docs[sid]["num_texts"], "labels": docs[sid]["labels"],
                            "symmetric": docs[sid].get("symmetric")}
                      for sid in sorted(docs)},  # fmt: skip
        "incomplete": incomplete,
        **({"targets_problems": no_targets} if (no_targets := {sid: docs[sid]["targets_problem"] for sid in sorted(docs)
                                                                if docs[sid].get("targets_problem")}) else {}),
        "skipped": dict(sorted(skipped.items())),
        "files": {},
        **dict(extra or {}),
    }
    put("README.md", dataset_card(manifest).encode("utf-8"))
    manifest["files"] = dict(sorted(files.items()))
    manifest["counts"]["files"] = len(files)
    for sub in OWN_FOLDERS[1:]:
        _clean_folder(out / sub, {r.split("/", 1)[1] for r in files if r.startswith(sub + "/")})
    rewritten += put_bytes(out / MANIFEST, json_bytes(manifest))[1]
    say(f"export: {len(docs)} sequences ({len(train)} train, {len(test)} test), {len(skipped)} skipped, "
        f"{rewritten} files written, {out}")  # fmt: skip
    return manifest


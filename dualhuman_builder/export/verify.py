"""``dualhuman export verify OUT``: check a dataset export against its own manifest and schema.

:func:`verify_export` returns a list of problems (empty: the export is intact). It checks that
``manifest.json`` is present and parseable; every file it lists exists with its size and SHA-256 and
no unlisted files sit in the export's own folders; every array matches ``schema.json`` (names,
shapes with the symbolic dims resolved per sequence, dtypes); motion arrays hold no NaN/inf and the
stored features are those of the stored joints; contacts are consistent (vertex count, per-frame
flags); the JSON files parse (text as UTF-8); labels are in ``labels.json`` and each multi-hot
vector matches its labels; the splits are disjoint, cover every sequence and
agree with the manifest (and share no subject when the export says subject-disjoint); the feature
statistics are finite; each sequence has every file the manifest promises. Nothing is unpickled:
arrays are read with ``allow_pickle=False``.
"""

from __future__ import annotations

import json
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from dualhuman_builder.export.features import FEATURE_DIM, motion_features
from dualhuman_builder.labels import Vocabulary
from dualhuman_builder.export.files import (
    LABELS_JSON,
    MANIFEST,
    OWN_FOLDERS,
    PERSONS,
    SEQUENCE_JSON,
    check_seq_id,
    read_manifest,
    read_npz,
)
from dualhuman_builder.fileio import sha256_file

#: Largest difference (feature units) between stored features and those recomputed from the joints.
FEATURE_TOLERANCE = 1e-4


def _safe_rel(rel: str) -> bool:
    p = PurePosixPath(rel)
    return bool(rel) and not p.is_absolute() and ".." not in p.parts and "\\" not in rel


def _dim_value(sym, dims: dict, bound: dict[str, int]) -> int | None:
    """Size of a schema dim: an int, a known symbol, ``T-1``, or a symbol bound on first use (None)."""
    if isinstance(sym, int):
        return sym
    if sym in bound:
        return bound[sym]
    if isinstance(dims.get(sym), int):
        return dims[sym]
    if isinstance(sym, str) and sym.endswith("-1") and sym[:-2] in bound:
        return bound[sym[:-2]] - 1
    return None


def _check_array(name: str, arr: np.ndarray, entry: dict, dims: dict, bound: dict[str, int]) -> str | None:
    want_dtype = entry.get("dtype")
    if want_dtype == "str":
        if arr.dtype.kind != "U":
            return f"{name} has dtype {arr.dtype}, schema says str"
    elif arr.dtype != np.dtype(want_dtype):
        return f"{name} has dtype {arr.dtype}, schema says {want_dtype}"
    shape = entry.get("shape", [])
    if arr.ndim != len(shape):
        return f"{name} has shape {arr.shape}, schema says {shape}"
    for sym, n in zip(shape, arr.shape):
        want = _dim_value(sym, dims, bound)
        if want is None:
            bound[sym] = n
        elif want != n:
            return f"{name} has shape {arr.shape}, schema says {shape} (= {[_dim_value(s, dims, bound) for s in shape]})"
    return None


def _load_json(path: Path, problems: list[str], what: str):
    try:
        return json.loads(path.read_bytes().decode("utf-8"))
    except FileNotFoundError:
        problems.append(f"{what}: missing")
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        problems.append(f"{what}: not valid UTF-8 JSON ({e})")
    return None


def verify_export(out_dir: str | Path, check_features: bool = True) -> list[str]:
    """Problems found in the export under ``out_dir`` (empty list: OK). ``check_features``:
    recompute each sequence's motion features from its joints and compare (cheap: numpy only)."""
    out = Path(out_dir)
    try:
        manifest = read_manifest(out)
    except ValueError as e:
        return [str(e)]
    problems: list[str] = []
    files = manifest.get("files")
    sequences = manifest.get("sequences")
    if not isinstance(files, dict) or not isinstance(sequences, dict):
        return [f"{out / MANIFEST}: lacks the 'files' or 'sequences' table"]

    # ---- checksums
    for rel, rec in sorted(files.items()):
        if not _safe_rel(rel):
            problems.append(f"manifest lists an unsafe path {rel!r}")
            continue
        path = out / rel
        if not path.is_file():
            problems.append(f"{rel}: missing (listed in the manifest)")
        elif path.stat().st_size != rec.get("bytes"):
            problems.append(f"{rel}: {path.stat().st_size} bytes, manifest says {rec.get('bytes')}")
        elif sha256_file(path) != rec.get("sha256"):
            problems.append(f"{rel}: sha256 differs from the manifest (corrupted or modified)")
    for sub in OWN_FOLDERS:
        if (out / sub).is_dir():
            for p in sorted((out / sub).rglob("*")):
                rel = p.relative_to(out).as_posix()
                if (p.is_file() or p.is_symlink()) and rel not in files:
                    problems.append(f"{rel}: not listed in the manifest")

    # ---- schema and per-sequence contents
    schema = _load_json(out / "schema.json", problems, "schema.json")
    entries = schema.get("arrays", []) if isinstance(schema, dict) else []
    dims = schema.get("dims", {}) if isinstance(schema, dict) else {}
    fps = manifest.get("fps")
    vocab = None
    if "vocabulary" in manifest:
        rel = manifest["vocabulary"].get("file", LABELS_JSON) if isinstance(manifest["vocabulary"], dict) else LABELS_JSON
        doc = _load_json(out / rel, problems, rel) if _safe_rel(rel) else None
        try:
            vocab = Vocabulary.from_dict(doc) if doc is not None else None
        except ValueError as e:
            problems.append(f"{rel}: {e}")
        if vocab is not None and manifest["vocabulary"].get("size") != len(vocab):
            problems.append(f"{rel}: {len(vocab)} labels, manifest says {manifest['vocabulary'].get('size')}")
    for sid, info in sorted(sequences.items()):
        try:
            check_seq_id(sid)
        except ValueError as e:
            problems.append(str(e))
            continue
        problems += _verify_sequence(out, sid, info, files, entries, dims, fps, check_features, vocab)

    # ---- splits
    split_files = manifest.get("split", {}).get("files", {"train": "splits/train.txt", "test": "splits/test.txt"})
    splits: dict[str, list[str]] = {}
    for name, rel in split_files.items():
        try:
            splits[name] = [s for s in (out / rel).read_text(encoding="utf-8").splitlines() if s.strip()]
        except (OSError, UnicodeDecodeError) as e:
            problems.append(f"{rel}: unreadable ({e})")
            splits[name] = []
        dups = sorted({s for s in splits[name] if splits[name].count(s) > 1})
        if dups:
            problems.append(f"{rel}: lists {dups} more than once")
    names = sorted(splits)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            both = sorted(set(splits[a]) & set(splits[b]))
            if both:
                problems.append(f"splits {a} and {b} overlap: {both[:10]}")
    listed = set().union(*splits.values()) if splits else set()
    if sorted(set(sequences) - listed):
        problems.append(f"sequences in no split: {sorted(set(sequences) - listed)[:10]}")
    if sorted(listed - set(sequences)):
        problems.append(f"splits name sequences the manifest does not have: {sorted(listed - set(sequences))[:10]}")
    for name, ids in splits.items():
        wrong = [s for s in ids if s in sequences and sequences[s].get("split") != name]
        if wrong:
            problems.append(f"sequences {wrong[:10]} are in splits/{name}.txt but the manifest says otherwise")
    if manifest.get("split", {}).get("subject_disjoint") and len(names) >= 2:
        subj = {n: {x for s in ids if s in sequences for x in sequences[s].get("subjects", [])} for n, ids in splits.items()}
        for i, a in enumerate(names):
            for b in names[i + 1 :]:
                shared = sorted(subj[a] & subj[b])
                if shared:
                    problems.append(f"subject-disjoint export, but subjects {shared[:10]} are in both {a} and {b}")

    # ---- statistics and counts
    for stat in ("mean", "std"):
        rel = manifest.get("stats", {}).get(stat, f"stats/{stat}.npy")
        try:
            arr = np.load(out / rel, allow_pickle=False)
        except (OSError, ValueError) as e:
            problems.append(f"{rel}: unreadable ({e})")
            continue
        if arr.shape != (FEATURE_DIM,) or arr.dtype != np.float32:
            problems.append(f"{rel}: shape {arr.shape} dtype {arr.dtype}, expected ({FEATURE_DIM},) float32")
        elif not np.isfinite(arr).all() or (stat == "std" and (arr <= 0).any()):
            problems.append(f"{rel}: holds NaN/inf" + (" or non-positive values" if stat == "std" else ""))
    counts = manifest.get("counts", {})
    if counts.get("sequences") != len(sequences):
        problems.append(f"manifest counts {counts.get('sequences')} sequences but lists {len(sequences)}")
    for name, ids in splits.items():
        if name in counts and counts[name] != len(ids):
            problems.append(f"manifest counts {counts[name]} {name} sequences, splits/{name}.txt lists {len(ids)}")
    return problems


def _verify_sequence(out: Path, sid: str, info: dict[str, Any], files: dict, entries: list, dims: dict, fps,
                     check_features: bool, vocab: Vocabulary | None = None) -> list[str]:  # fmt: skip
    problems: list[str] = []
    base = f"sequences/{sid}"
    has = info.get("has", {})
    T = info.get("frames")
    if not isinstance(T, int) or T < 2:
        return [f"{base}: manifest gives {T!r} frames"]
    promised = {"motion": ["motion.npz"], "contacts": ["contacts.npz", "contact_events.json"], "text": ["text.json"],
                "cameras": ["cameras.json"], "keypoints": ["renders/keypoints.npz"]}  # fmt: skip
    needed = [SEQUENCE_JSON, "text.json"] + [f for stage, fs in promised.items() if has.get(stage) for f in fs]
    for view in info.get("render_views", []):
        if not any(r.startswith(f"{base}/renders/views/{view}/") for r in files):
            problems.append(f"{base}: the manifest promises renders of view {view!r}, none are listed")
    if has.get("renders") and not info.get("render_views"):
        problems.append(f"{base}: has renders but names no views")
    for rel in needed:
        if f"{base}/{rel}" not in files:
            problems.append(f"{base}/{rel}: promised by the manifest but not in its file list")
    if not has.get("motion"):
        problems.append(f"{base}: the manifest says it has no motion")

    bound: dict[str, int] = {"T": T}
    loaded: dict[str, dict[str, np.ndarray] | None] = {}
    for entry in entries:
        stage = entry.get("stage", "motion")
        rel = entry["file"].format(seq_id=sid)
        if not has.get(stage) or rel not in files:
            continue
        if rel not in loaded:
            try:
                loaded[rel] = read_npz(out / rel)
            except (ValueError, FileNotFoundError) as e:
                problems.append(f"{rel}: {e}")
                loaded[rel] = None
        arrays = loaded[rel]
        if arrays is None:
            continue
        if entry["name"] not in arrays:
            problems.append(f"{rel}: lacks array {entry['name']!r} (schema)")
            continue
        msg = _check_array(entry["name"], arrays[entry["name"]], entry, dims, bound)
        if msg:
            problems.append(f"{rel}: {msg}")

    motion = loaded.get(f"{base}/motion.npz")
    if motion:
        for name, arr in motion.items():
            if arr.dtype.kind == "f" and not np.isfinite(arr).all():
                problems.append(f"{base}/motion.npz: {name} holds NaN or inf")
        if check_features and isinstance(fps, (int, float)) and fps > 0:
            for p in PERSONS:
                j, f = motion.get(f"{p}.joints"), motion.get(f"{p}.features")
                if j is None or f is None or j.shape != (T, 22, 3) or f.shape != (T - 1, FEATURE_DIM):
                    continue
                if not (np.isfinite(j).all() and np.isfinite(f).all()):
                    continue
                try:
                    err = float(np.abs(motion_features(j, fps) - f).max())
                except ValueError as e:
                    problems.append(f"{base}/motion.npz: features of {p}.joints cannot be recomputed ({e})")
                    continue
                if err > FEATURE_TOLERANCE:
                    problems.append(f"{base}/motion.npz: {p}.features differ from those of {p}.joints by {err:.3g}")
    contacts = loaded.get(f"{base}/contacts.npz")
    if contacts and all(k in contacts for k in ("labels_packed", "num_vertices", "frame_contact")):
        V = dims.get("V")
        if isinstance(V, int) and int(contacts["num_vertices"]) != V:
            problems.append(f"{base}/contacts.npz: num_vertices {int(contacts['num_vertices'])}, body model has {V}")
        elif contacts["labels_packed"].ndim == 3 and contacts["frame_contact"].shape == (T,):
            any_contact = np.unpackbits(contacts["labels_packed"], axis=2).any(axis=(0, 2))
            if not np.array_equal(any_contact, contacts["frame_contact"]):
                problems.append(f"{base}/contacts.npz: frame_contact disagrees with the labels")
    if has.get("contacts") and f"{base}/contact_events.json" in files:
        events = _load_json(out / base / "contact_events.json", problems, f"{base}/contact_events.json")
        if events is not None and not (isinstance(events, list) and all(isinstance(e, dict) for e in events)):
            problems.append(f"{base}/contact_events.json: not a list of events")
    if f"{base}/text.json" in files:
        text = _load_json(out / base / "text.json", problems, f"{base}/text.json")
        if text is not None:
            ok = isinstance(text, dict) and all(
                isinstance(text.get(k), list) and all(isinstance(t, str) for t in text[k]) for k in ("labels", "texts")
            )
            if not ok:
                problems.append(f"{base}/text.json: needs lists of strings 'labels' and 'texts'")
            elif bool(text["texts"]) != bool(has.get("text")):
                problems.append(f"{base}/text.json: {len(text['texts'])} texts, manifest says has text = {has.get('text')}")
            elif vocab is not None:
                unknown = [x for x in text["labels"] if x not in vocab]
                if unknown:
                    problems.append(f"{base}/text.json: labels {unknown} are not in labels.json")
                elif text.get("multi_hot") != vocab.multi_hot(text["labels"]).tolist():
                    problems.append(f"{base}/text.json: multi_hot disagrees with its labels")
    if has.get("cameras") and f"{base}/cameras.json" in files:
        cams = _load_json(out / base / "cameras.json", problems, f"{base}/cameras.json")
        if cams is not None:
            names = {c.get("name") for c in cams.get("cameras", []) if isinstance(c, dict)} if isinstance(cams, dict) else set()
            missing = sorted(set(info.get("render_views", [])) - names)
            if not names:
                problems.append(f"{base}/cameras.json: no cameras")
            elif missing:
                problems.append(f"{base}: rendered views {missing} have no camera in cameras.json")
    seq_doc = _load_json(out / base / SEQUENCE_JSON, problems, f"{base}/{SEQUENCE_JSON}")
    if isinstance(seq_doc, dict) and seq_doc.get("frames") != T:
        problems.append(f"{base}/{SEQUENCE_JSON}: {seq_doc.get('frames')} frames, manifest says {T}")
    return problems


__all__ = ["verify_export", "FEATURE_TOLERANCE"]

"""Dataset export: folder layout, manifest and schema, splits, verify, resumable re-runs, WebDataset
shards and the PyTorch loaders, on small anny-posed sequences (no scene generation)."""

from __future__ import annotations

import io
import json
import os
import shutil
import tarfile

import numpy as np
import pytest
import torch
from PIL import Image

from dualhuman_builder import __version__
from dualhuman_builder.export.features import FEATURE_SCHEMA, feature_stats, mirror_features, mirror_text, motion_features
from dualhuman_builder.export.files import load_contacts, load_motion
from dualhuman_builder.export.items import ExportItem
from dualhuman_builder.export.splits import make_splits
from dualhuman_builder.export.writer import export_dataset
from dualhuman_builder.export.loader import MotionWindows, ShardWindows
from dualhuman_builder.export.shards import decode_sample, iter_shards, write_shards
from dualhuman_builder.export.verify import verify_export
from dualhuman_builder.tracks import BodyTrack, InteractionSequence

FPS = 20.0
FRAMES = {"s0": 24, "s1": 30, "s2": 36, "s3": 40}
SUBJECTS = {"s0": ("alice", "bob"), "s1": ("bob", "alice"), "s2": ("carol", "dave"), "s3": ("erin", "frank")}
TEXT = "The person on the left pushes the other with the right hand."


def _track(model, T: int, seed: int, x: float, yaw: float, actor: str) -> BodyTrack:
    rng = np.random.default_rng(seed)
    J = model.num_bones
    pose = np.cumsum(rng.normal(0.0, 0.01, (T, J, 3)), axis=0)  # smooth random motion
    pose[:, 0] = [0.0, yaw, 0.0] + np.cumsum(rng.normal(0.0, 0.02, (T, 3)), axis=0) * [0.2, 1.0, 0.2]
    transl = np.stack([np.full(T, x), np.full(T, 0.95), np.linspace(0.0, 0.01 * T, T)], axis=1)
    return BodyTrack.from_model(model, pose, transl, rng.uniform(0.3, 0.7, len(model.shape_names)), FPS, actor=actor)


def _contacts(T: int, V: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    labels = np.zeros((2, T, V), bool)
    labels[:, 3:7, rng.integers(0, V, 50)] = True
    dist = np.full((2, T, V), np.nan, np.float16)
    dist[labels] = -0.004
    events = [{"region_a": "right_hand", "region_b": "left_arm", "start": 3, "end": 7, "contact_frames": 4,
               "peak_vertices": 50, "min_distance_m": float("-inf")}]  # fmt: skip
    return {"labels": labels, "distances": dist, "frame_contact": labels.any(axis=(0, 2)), "events": events}


def _render_dir(root, T: int):
    root.mkdir(parents=True)
    cams = [{"name": n, "width": 8, "height": 8, "K": np.eye(3).tolist(), "R": np.eye(3).tolist(), "t": [0, 0, 3]}
            for n in ("cam0", "cam1")]  # fmt: skip
    (root / "cameras.json").write_text(json.dumps({"convention": "OpenCV", "cameras": cams}))
    (root / "visibility.json").write_text("{}")
    frames = np.arange(0, T, 2)
    np.savez(root / "keypoints.npz", joints=np.zeros((2, len(frames), 2, 22, 3), np.float32),
             coco=np.zeros((2, len(frames), 2, 17, 3), np.float32), frames=frames.astype(np.int64),
             views=np.array(["cam0", "cam1"]))  # fmt: skip
    for v, cam in enumerate(("cam0", "cam1")):
        for f in frames:
            for kind in ("rgb", "mask"):
                (root / "views" / cam / kind).mkdir(parents=True, exist_ok=True)
                img = np.full((8, 8, 3) if kind == "rgb" else (8, 8), 10 * v + f, np.uint8)
                Image.fromarray(img).save(root / "views" / cam / kind / f"{f:05d}.png")
    (root / ".progress").mkdir()
    (root / ".progress" / "00000.npz").write_bytes(b"resume marker")
    return root


@pytest.fixture(scope="module")
def items(body_model, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("inputs")
    V = body_model.num_vertices
    out = []
    for k, (sid, T) in enumerate(FRAMES.items()):
        a = _track(body_model, T, 10 * k, 0.0, 0.3 * k, SUBJECTS[sid][0])
        b = _track(body_model, T, 10 * k + 1, 0.9, np.pi - 0.2 * k, SUBJECTS[sid][1])
        seq = InteractionSequence((a, b), take=f"take{k}", labels=("push",), text=(TEXT, f"Two people, clip {sid}."))
        out.append(ExportItem(sid, seq, subjects=SUBJECTS[sid], roles=("actor", "reactor"),
                              contacts=None if sid == "s3" else _contacts(T, V, k),
                              render_dir=None if sid == "s3" else _render_dir(tmp / f"render_{sid}", T)))  # fmt: skip
    return out


def _extra_items(items):
    """A sequence whose motion holds NaN and one without motion: both left out with a reason."""
    a, b = items[0].sequence.actors
    bad = BodyTrack(a.pose, a.transl, a.shape, FPS, a.bone_names, a.shape_names, a.model, a.model_version)
    bad.pose = np.where(np.arange(len(a.pose))[:, None, None] == 5, np.nan, a.pose)  # bypasses the constructor check
    return [ExportItem("nan_seq", InteractionSequence((bad, b))), ExportItem("unfitted", None, subjects=("x", "y"))]


@pytest.fixture(scope="module")
def exported(items, tmp_path_factory):
    out = tmp_path_factory.mktemp("export") / "ds"
    lines = []
    manifest = export_dataset(items + _extra_items(items), out, seed=3, progress=lines.append)
    return out, manifest, lines


def _copy(exported, tmp_path):
    dst = tmp_path / "copy"
    shutil.copytree(exported[0], dst)
    return dst


def _mtimes(folder):
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in sorted(folder.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------------------------ layout
def test_layout_manifest_schema_and_contents(exported, items, body_model):
    out, manifest, lines = exported
    assert manifest["format_version"] == 2 and manifest["toolkit_version"] == __version__
    assert manifest["body_model"]["name"] == "anny" and manifest["body_model"]["version"] == body_model.version
    assert manifest["body_model"]["num_vertices"] == 13718 and manifest["fps"] == FPS
    assert manifest["axes"] == "Y-up, metres" and manifest["units"]["length"] == "m"
    c = manifest["counts"]
    assert (c["sequences"], c["train"], c["test"], c["frames"]) == (4, 3, 1, sum(FRAMES.values()))
    assert (c["with_contacts"], c["with_renders"], c["skipped"]) == (3, 3, 2)
    assert "NaN" in manifest["skipped"]["nan_seq"] and "fit stage" in manifest["skipped"]["unfitted"]
    assert manifest["incomplete"] == {"s3": ["contacts", "renders"]}
    assert json.loads((out / "manifest.json").read_text()) == manifest
    # every file on disk except the manifest is listed with its true sha256 and size
    on_disk = {str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()} - {"manifest.json"}
    assert on_disk == set(manifest["files"])
    import hashlib

    for rel in ("sequences/s1/motion.npz", "README.md", "stats/std.npy"):
        data = (out / rel).read_bytes()
        assert manifest["files"][rel] == {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
    # renders: copied (hard-linked, same filesystem), the render's hidden resume markers are not
    src = items[1].render_dir
    assert os.path.samefile(src / "views/cam1/rgb/00004.png", out / "sequences/s1/renders/views/cam1/rgb/00004.png")
    assert not any(".progress" in r for r in manifest["files"]) and (out / "sequences/s1/cameras.json").is_file()
    assert manifest["sequences"]["s1"]["render_views"] == ["cam0", "cam1"]
    # schema: symbolic shapes, feature slices from FEATURE_SCHEMA
    schema = json.loads((out / "schema.json").read_text())
    feat = next(e for e in schema["arrays"] if e["name"] == "b.features")
    assert feat["shape"] == ["T-1", 269] and feat["dtype"] == "float32" and feat["fields"] == FEATURE_SCHEMA
    assert schema["dims"]["J"] == body_model.num_bones and schema["dims"]["V8"] == 1715
    # arrays: the tracks' parameters, their joints and the features of those joints
    m = load_motion(out / "sequences/s2/motion.npz")
    a, b = items[2].sequence.actors
    assert np.array_equal(m["a.pose"], a.pose) and np.array_equal(m["b.transl"], b.transl)
    assert m["b.joints"].shape == (36, 22, 3) and np.allclose(m["b.joints"], b.joints())
    assert np.array_equal(m["a.features"], motion_features(a.joints(), FPS)) and m["a.features"].shape == (35, 269)
    cts = load_contacts(out / "sequences/s2/contacts.npz")
    assert np.array_equal(cts["labels"], items[2].contacts["labels"]) and cts["distances"].dtype == np.float16
    assert json.loads((out / "sequences/s2/contact_events.json").read_text())[0]["min_distance_m"] is None
    text = json.loads((out / "sequences/s2/text.json").read_text(encoding="utf-8"))
    vocab = json.loads((out / "labels.json").read_text())
    assert vocab["size"] == len(vocab["labels"]) == 30 and manifest["vocabulary"] == {"file": "labels.json", "size": vocab["size"]}
    push = next(e["index"] for e in vocab["labels"] if e["name"] == "push")
    assert text == {"labels": ["push"], "multi_hot": [int(i == push) for i in range(vocab["size"])], "symmetric": False,
                    "texts": [TEXT, "Two people, clip s2."], "roles": ["actor", "reactor"], "annotations": []}  # fmt: skip
    # splits 3:1, stats over the train features of both persons
    train = (out / "splits/train.txt").read_text().split()
    test = (out / "splits/test.txt").read_text().split()
    assert len(train) == 3 and len(test) == 1 and sorted(train + test) == sorted(FRAMES)
    feats = [load_motion(out / f"sequences/{s}/motion.npz")[f"{p}.features"] for s in train for p in "ab"]
    mean, std = feature_stats(feats)
    assert np.array_equal(np.load(out / "stats/mean.npy"), mean) and np.array_equal(np.load(out / "stats/std.npy"), std)
    card = (out / "README.md").read_text()
    assert "| sequences | 4 (3 train, 1 test) |" in card and "sequences/<seq_id>/" in card and "`nan_seq`" in card
    assert any("s2: 36 frames" in line for line in lines)


# ------------------------------------------------------------------------------------ verify
def test_verify_passes_and_catches_damage(exported, tmp_path):
    assert verify_export(exported[0]) == []
    out = _copy(exported, tmp_path)
    path = out / "sequences/s0/motion.npz"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    (out / "sequences/s1/text.json").unlink()
    test = (out / "splits/test.txt").read_text().split()
    train = (out / "splits/train.txt").read_text().split()
    (out / "splits/test.txt").write_text("\n".join(test + train[:1]) + "\n")
    problems = verify_export(out)
    text = "\n".join(problems)
    assert "sequences/s0/motion.npz: sha256 differs" in text
    assert "sequences/s1/text.json: missing" in text
    assert f"splits test and train overlap: ['{train[0]}']" in text or f"splits train and test overlap: ['{train[0]}']" in text
    (out / "manifest.json").write_text("{not json")
    assert "not valid UTF-8 JSON" in verify_export(out)[0]
    shutil.rmtree(out)
    assert "does not exist" in verify_export(out)[0]


def test_verify_checks_schema_and_nan(exported, tmp_path):
    import hashlib

    from dualhuman_builder.export.files import npz_bytes

    out = _copy(exported, tmp_path)
    manifest = json.loads((out / "manifest.json").read_text())

    def replace(rel, arrays):
        data = npz_bytes(arrays)
        (out / rel).write_bytes(data)
        manifest["files"][rel] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}

    m = load_motion(out / "sequences/s2/motion.npz")
    replace("sequences/s2/motion.npz", {**m, "a.features": m["a.features"].astype(np.float64),
                                        "b.joints": m["b.joints"][:-1]})  # fmt: skip
    m = load_motion(out / "sequences/s0/motion.npz")
    m["a.transl"] = m["a.transl"].copy()
    m["a.transl"][4, 1] = np.nan
    replace("sequences/s0/motion.npz", m)
    (out / "manifest.json").write_text(json.dumps(manifest))
    problems = verify_export(out)
    assert "sequences/s2/motion.npz: a.features has dtype float64, schema says float32" in problems
    assert any(p.startswith("sequences/s2/motion.npz: b.joints has shape (35, 22, 3)") for p in problems)
    assert "sequences/s0/motion.npz: a.transl holds NaN or inf" in problems
    assert not any("sha256" in p for p in problems)


# ------------------------------------------------------------------------------------ splits
def test_subject_disjoint_splits(items, tmp_path):
    train, test = make_splits(SUBJECTS, 0.75, subject_disjoint=True, seed=0)
    assert sorted(train + test) == sorted(SUBJECTS) and train and test
    subj = [{x for s in side for x in SUBJECTS[s]} for side in (train, test)]
    assert not subj[0] & subj[1]
    assert {"s0", "s1"} <= set(train) or {"s0", "s1"} <= set(test)  # they share alice and bob
    for seed in range(5):  # seeded: the same answer every time
        assert make_splits(SUBJECTS, 0.75, True, seed) == make_splits(SUBJECTS, 0.75, True, seed)
    with pytest.raises(ValueError, match="subject-disjoint split is impossible: all 3 sequences are linked"):
        make_splits({"x": ("ann", "ben"), "y": ("ben", "cy"), "z": ("cy", "ann")}, subject_disjoint=True)
    manifest = export_dataset(items, tmp_path / "ds", subject_disjoint=True, seed=1)
    assert manifest["split"]["subject_disjoint"] and verify_export(tmp_path / "ds") == []


# ------------------------------------------------------------------------------------ re-runs
def test_rerun_completes_and_rewrites_nothing(exported, items, tmp_path):
    out = _copy(exported, tmp_path)
    before = _mtimes(out)
    lines = []
    again = export_dataset(items + _extra_items(items), out, seed=3, progress=lines.append)
    assert again == exported[1] and _mtimes(out) == before
    assert sum("up to date" in line for line in lines) == 4 and "0 files written" in lines[-1]
    # an interrupted export: one sequence folder gone, no manifest, a partial write left behind
    shutil.rmtree(out / "sequences/s1")
    (out / "manifest.json").unlink()
    (out / "sequences/s2/.motion.npz.123-abcd.partial").write_bytes(b"half")
    lines.clear()
    again = export_dataset(items + _extra_items(items), out, seed=3, progress=lines.append)
    assert again == exported[1] and verify_export(out) == []
    after = _mtimes(out)
    changed = sorted(k for k in after if after[k] != before.get(k))
    assert changed and all(k.startswith("sequences/s1/") or k == "manifest.json" for k in changed)
    assert sum("up to date" in line for line in lines) == 3


# ------------------------------------------------------------------------------------ bad input
def test_bad_input_is_rejected_before_writing(items, tmp_path):
    out = tmp_path / "ds"
    with pytest.raises(ValueError, match=r"duplicate seq_id \['s0'\]"):
        export_dataset([items[0], items[0]], out)
    bad_text = ExportItem("s9", items[0].sequence, texts=["fine", b"caf\xe9 au lait"])
    with pytest.raises(ValueError, match=r"sequence 's9': texts\[1\] is not valid UTF-8"):
        export_dataset([items[1], bad_text], out)
    with pytest.raises(ValueError, match="invalid seq_id 'a/b'"):
        export_dataset([ExportItem("a/b", items[0].sequence)], out)
    with pytest.raises(ValueError, match=r"contacts labels must have shape \(2, 24, V\)"):
        export_dataset([ExportItem("s0", items[0].sequence, contacts={**items[0].contacts,
                                   "labels": items[0].contacts["labels"][:, :5]})], out)  # fmt: skip
    with pytest.raises(ValueError, match="split_ratio must be in"):
        export_dataset(items, out, split_ratio=0.0)
    with pytest.raises(ValueError, match="strict export: sequences skipped.*nan_seq.*incomplete.*s3"):
        export_dataset(items + _extra_items(items), out, strict=True)
    assert not out.exists()  # every input error surfaced before anything was written
    foreign = tmp_path / "home"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="not a dataset export"):
        export_dataset(items, foreign)
    # contacts may come as an object with the same attributes (a ContactResult); everything in train
    from types import SimpleNamespace

    one = ExportItem("s0", items[0].sequence, contacts=SimpleNamespace(**items[0].contacts), texts=[b"caf\xc3\xa9"])
    manifest = export_dataset([one, items[1]], out, split_ratio=1.0)
    assert (manifest["counts"]["train"], manifest["counts"]["test"]) == (2, 0) and verify_export(out) == []
    assert json.loads((out / "sequences/s0/text.json").read_text(encoding="utf-8"))["texts"] == ["caf\u00e9"]
    assert np.array_equal(load_contacts(out / "sequences/s0/contacts.npz")["labels"], items[0].contacts["labels"])


# ------------------------------------------------------------------------------------ shards
def test_shards_round_trip_and_reject_malicious_members(exported, tmp_path):
    out = exported[0]
    paths = write_shards(out, tmp_path / "shards", max_bytes=400_000, split="all")
    assert len(paths) >= 2 and [p.name for p in paths][:2] == ["all-000000.tar", "all-000001.tar"]
    assert all(p.stat().st_size <= 400_000 for p in paths)
    samples = list(iter_shards(paths))
    only = list(iter_shards(paths, members=("text.json",)))  # the others are skipped, not read
    assert [set(x) for x in only] == [{"__key__", "__url__", "text.json"}] * len(samples)
    assert [x["text.json"] for x in only] == [x["text.json"] for x in samples]
    assert [s["__key__"] for s in samples] == sorted(FRAMES)
    s2 = samples[2]
    assert s2["motion.npz"] == (out / "sequences/s2/motion.npz").read_bytes()
    assert set(s2) >= {"sequence.json", "contacts.npz", "contact_events.json", "text.json", "cameras.json", "keypoints.npz"}
    assert "contacts.npz" not in samples[3]  # s3 has no contacts
    dec = decode_sample(s2)
    assert np.array_equal(dec["motion.npz"]["b.features"], load_motion(out / "sequences/s2/motion.npz")["b.features"])
    assert dec["text.json"]["texts"][0] == TEXT
    index = json.loads((tmp_path / "shards/all.json").read_text())
    assert sum(s["samples"] for s in index["shards"]) == 4 and index["pattern"].startswith("all-{000000..")
    again = write_shards(out, tmp_path / "again", max_bytes=400_000, split="all")
    assert [p.read_bytes() for p in again] == [p.read_bytes() for p in paths]  # byte-deterministic

    def tar_with(name, kind=tarfile.REGTYPE):
        path = tmp_path / f"evil{abs(hash((name, kind)))}.tar"
        with tarfile.open(path, "w") as tf:
            ok = tarfile.TarInfo("s0.text.json")
            ok.size = 2
            tf.addfile(ok, io.BytesIO(b"{}"))
            info = tarfile.TarInfo(name)
            info.type = kind
            if kind == tarfile.SYMTYPE:
                info.linkname = "/etc/passwd"
            else:
                info.size = 1
            tf.addfile(info, io.BytesIO(b"x") if kind == tarfile.REGTYPE else None)
        return path

    with pytest.raises(ValueError, match=r"member '\.\./x\.motion\.npz' contains '\.\.'"):
        list(iter_shards([tar_with("../x.motion.npz")]))
    with pytest.raises(ValueError, match="member '/abs.motion.npz' has an absolute path"):
        list(iter_shards([tar_with("/abs.motion.npz")]))
    with pytest.raises(ValueError, match="is a link"):
        list(iter_shards([tar_with("s1.motion.npz", tarfile.SYMTYPE)]))
    with pytest.raises(ValueError, match="not a regular file"):
        list(iter_shards([tar_with("s1.dir", tarfile.DIRTYPE)]))


# ------------------------------------------------------------------------------------ loader
def test_loader_windows_values_and_mirroring(exported):
    out = exported[0]
    L = 8
    ds = MotionWindows(out, window=L, split="all")
    assert len(ds) == sum((T - 1 - L) // (L // 2) + 1 for T in FRAMES.values())  # 4 + 6 + 7 + 8
    feats = {s: load_motion(out / f"sequences/{s}/motion.npz") for s in FRAMES}
    starts = {s: [st for sid, st in ds.index if sid == s] for s in FRAMES}
    assert starts["s1"] == [0, 4, 8, 12, 16, 20]  # 29 rows
    for i in (0, 5, len(ds) - 1):
        item = ds[i]
        f = feats[item["seq_id"]]
        st = item["start"]
        assert item["a"].dtype == torch.float32 and item["a"].shape == (L, 269)
        assert np.array_equal(item["a"].numpy(), f["a.features"][st : st + L])
        assert np.array_equal(item["b"].numpy(), f["b.features"][st : st + L])
        assert item["text"] in (TEXT, f"Two people, clip {item['seq_id']}.") and not item["mirrored"]
    for i in reversed(range(len(ds))):
        ds[i]
    assert sorted(ds._cache) == ["s0", "s1", "s2", "s3"]  # the default budget keeps the split: each file read once
    tiny = MotionWindows(out, window=L, split="all", cache_mb=0)  # keeps only the sequence in use
    for i in (0, len(tiny) - 1, 5):
        assert np.array_equal(tiny[i]["b"].numpy(), ds[i]["b"].numpy()) and len(tiny._cache) == 1
    norm = MotionWindows(out, window=L, split="train", normalize=True)
    mean, std = np.load(out / "stats/mean.npy"), np.load(out / "stats/std.npy")
    it = norm[3]
    raw = feats[it["seq_id"]]["b.features"][it["start"] : it["start"] + L]
    assert np.allclose(it["b"].numpy(), (raw - mean) / std, atol=1e-6)
    assert len(MotionWindows(out, window=30, split="all").too_short) == 2  # s0 (23 rows) and s1 (29)

    mirrored = MotionWindows(out, window=L, split="all", mirror_p=1.0, seed=5)
    texts = set()
    for i in range(len(mirrored)):
        item = mirrored[i]
        f = feats[item["seq_id"]]
        st = item["start"]
        assert item["mirrored"]
        assert np.array_equal(item["a"].numpy(), mirror_features(f["a.features"][st : st + L]))
        assert np.array_equal(item["b"].numpy(), mirror_features(f["b.features"][st : st + L]))
        texts.add(item["text"])
    assert mirror_text(TEXT) in texts and "on the right pushes the other with the left hand" in mirror_text(TEXT)
    half = MotionWindows(out, window=L, split="all", mirror_p=0.5, seed=5)
    flags = [half[i]["mirrored"] for i in range(len(half))]
    assert 0 < sum(flags) < len(flags) and flags == [half[i]["mirrored"] for i in range(len(half))]
    half.set_epoch(1)
    flags1 = [half[i]["mirrored"] for i in range(len(half))]
    assert flags != flags1
    # set_epoch reaches DataLoader workers that persist across epochs (the epoch is in shared memory)
    dl = torch.utils.data.DataLoader(half, batch_size=None, num_workers=2, persistent_workers=True)
    half.set_epoch(0)
    assert [it["mirrored"] for it in dl] == flags
    half.set_epoch(1)
    assert [it["mirrored"] for it in dl] == flags1
    del dl
    with pytest.raises(ValueError, match="window must be a positive"):
        MotionWindows(out, window=0)
    with pytest.raises(ValueError, match="mirrored motion would not match the images"):
        MotionWindows(out, window=L, renders=True, mirror_p=0.5)


def test_loader_renders_shards_and_workers(exported, tmp_path):
    out = exported[0]
    L = 8
    ds = MotionWindows(out, window=L, split="all", renders=True)
    i = next(k for k, (sid, st) in enumerate(ds.index) if sid == "s1" and st == 4)
    item = ds[i]
    assert item["rgb"].shape == (2, L, 8, 8, 3) and item["rendered"].tolist() == [True, False] * 4
    assert int(item["rgb"][1, 2, 0, 0, 0]) == 10 + 6  # cam1, frame 6
    assert int(item["rgb"][0, 1].max()) == 0  # frame 5 was not rendered

    shards = write_shards(out, tmp_path / "shards", max_bytes=400_000, split="train")
    from_folder = MotionWindows(out, window=L, split="train", normalize=True, mirror_p=0.5, seed=2)
    from_shards = MotionWindows(shards, window=L, normalize=True, mirror_p=0.5, seed=2)
    assert from_shards.index == from_folder.index
    for k in range(0, len(from_folder), 3):
        x, y = from_folder[k], from_shards[k]
        assert torch.equal(x["a"], y["a"]) and torch.equal(x["b"], y["b"]) and x["text"] == y["text"]

    for workers in (0, 2):
        seen = []
        for batch in torch.utils.data.DataLoader(from_folder, batch_size=4, num_workers=workers, shuffle=True):
            assert batch["a"].shape[1:] == (L, 269) and batch["a"].dtype == torch.float32
            assert len(batch["text"]) == len(batch["a"])
            seen += list(zip(batch["seq_id"], batch["start"].tolist()))
        assert sorted(seen) == sorted(from_folder.index)
    stream = ShardWindows(shards, window=L, buffer=5, seed=1)
    seen = [(w["seq_id"], w["start"]) for w in torch.utils.data.DataLoader(stream, batch_size=None, num_workers=2)]
    assert sorted(seen) == sorted(from_folder.index)

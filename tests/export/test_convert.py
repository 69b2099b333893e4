"""Converters from a dataset export to InterGen's InterHuman layout and HumanML3D's layout: file tree,
shapes, dtypes, values recomputed from the exported joints, texts, splits, errors and the CLI."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dualhuman_builder.errors import FormatError
from dualhuman_builder.export.convert import (
    HAND_JOINTS,
    TO_Z_UP,
    humanml3d_tokens,
    read_interhuman,
    to_humanml3d,
    to_interhuman,
)
from dualhuman_builder.export.features import canonicalize, feature_stats, motion_features, recover_joints, resample_joints
from dualhuman_builder.export.interhuman import PairTransform, interhuman_features, recover_interhuman
from dualhuman_builder.export.files import load_motion
from dualhuman_builder.export.items import ExportItem
from dualhuman_builder.export.writer import export_dataset
from dualhuman_builder.tracks import BodyTrack, InteractionSequence

FPS = 10.0
MM = 1e-3
TEXT = "The person on the left pushes the other with the right hand."
SEQS = {  # id: (frames, texts, labels)
    "s0": (21, (TEXT, "They push,\nthen  step back #2."), ("push",)),
    "s1": (17, (), ("high_five",)),
    "s2": (15, (), ()),
    "s3": (19, ("Two people shake hands.",), ("handshake",)),
}


def _track(model, T: int, seed: int, x: float, yaw: float) -> BodyTrack:
    rng = np.random.default_rng(seed)
    pose = np.cumsum(rng.normal(0.0, 0.02, (T, model.num_bones, 3)), axis=0)
    pose[:, 0] = [0.0, yaw, 0.0] + np.cumsum(rng.normal(0.0, 0.04, (T, 3)), axis=0) * [0.2, 1.0, 0.2]
    transl = np.stack([np.full(T, x), np.full(T, 0.95), np.linspace(0.0, 0.03 * T, T)], axis=1)
    return BodyTrack.from_model(model, pose, transl, rng.uniform(0.3, 0.7, len(model.shape_names)), FPS)


@pytest.fixture(scope="module")
def export(body_model, tmp_path_factory):
    """A small export (4 sequences at 10 fps, s2 without any text or label) and its manifest."""
    out = tmp_path_factory.mktemp("export") / "ds"
    items = []
    for k, (sid, (T, texts, labels)) in enumerate(SEQS.items()):
        a = _track(body_model, T, 10 * k, 0.0, 0.4 * k)
        b = _track(body_model, T, 10 * k + 1, 0.9, np.pi - 0.3 * k)
        items.append(ExportItem(sid, InteractionSequence((a, b), labels=labels, text=texts), subjects=(f"x{k}", f"y{k}")))
    manifest = export_dataset(items, out, seed=1, expect=("motion",))
    return out, manifest


@pytest.fixture(scope="module")
def converted(export, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("converted")
    return to_interhuman(export[0], tmp / "ih"), to_humanml3d(export[0], tmp / "hml")


def _joints(export, sid):
    m = load_motion(export[0] / f"sequences/{sid}/motion.npz")
    return m["a.joints"], m["b.joints"]


def _lines(path):
    text = path.read_text(encoding="utf-8")
    assert text == "" or text.endswith("\n")  # InterGen compares names as name + "\n"
    return text.splitlines()


def _export_split(export, name, ids):
    return sorted(s for s in ids if export[1]["sequences"][s]["split"] == name)


# ----------------------------------------------------------------------------- InterHuman
def test_interhuman_tree_shapes_and_world_recovery(export, converted):
    doc = converted[0]
    dest = Path(doc["dest"])
    good = ["s0", "s1", "s3"]
    assert sorted(doc["sequences"]) == good and doc["sequences_converted"] == 3 and doc["fps"] == 30.0
    assert doc["skipped"] == {"s2": "no text and no labels"} and doc["texts_from_labels"] == ["s1"]
    assert _lines(dest / "ignore_list.txt") == ["s2"]
    assert sorted(p.name for p in (dest / "motions_processed/person1").iterdir()) == [f"{s}.npy" for s in good]
    assert not (dest / "annots/s2.txt").exists()
    for sid in good:
        ja, jb = _joints(export, sid)
        a30, b30 = resample_joints(ja, FPS, 30.0), resample_joints(jb, FPS, 30.0)
        T30 = (SEQS[sid][0] - 1) * 3 + 1
        assert len(a30) == T30 and doc["sequences"][sid]["frames"] == T30
        tr = doc["sequences"][sid]["transform"]
        transform = PairTransform(tr["yaw0"], tuple(tr["translation"]))
        ref = interhuman_features(ja, jb, FPS)
        assert transform == ref.transform
        for k, (f_ref, j30) in enumerate(((ref.person1, a30), (ref.person2, b30)), 1):
            raw = np.load(dest / f"motions_processed/person{k}/{sid}.npy", allow_pickle=False)
            feat = np.load(dest / f"features/p{k}/{sid}.npy", allow_pickle=False)
            assert raw.dtype == feat.dtype == np.float32 and raw.shape == (T30, 492) and feat.shape == (T30 - 1, 262)
            rot = np.s_[132:258]  # InterHuman's row layout there, checked against the raw rotations below
            np.testing.assert_allclose(np.delete(feat, rot, 1), np.delete(f_ref, rot, 1), atol=1e-6)
            assert np.abs(recover_interhuman(feat, transform) - j30).max() < MM
            # what InterGen reads: [:66] positions (Z up -> Y up is (x, z, -y)) and [186:312] rotations
            pos = raw[:, :66].reshape(T30, 22, 3)
            np.testing.assert_allclose(np.stack([pos[..., 0], pos[..., 2], -pos[..., 1]], -1),
                                       transform.to_canonical(j30), atol=1e-5)  # fmt: skip
            np.testing.assert_array_equal(raw[:-1, 186:312], feat[:, 132:258])
            hands = raw[:, :186].reshape(T30, 62, 3)
            for wrist, joints in HAND_JOINTS.items():
                assert np.array_equal(hands[:, joints], np.repeat(hands[:, wrist : wrist + 1], len(joints), 1))
            assert np.array_equal(raw[:, 312:].reshape(T30, 30, 6), np.tile([1, 0, 0, 1, 0, 0], (T30, 30, 1)))
        canon_a = transform.to_canonical(a30)  # person 1's canonical frame: floor 0, root XZ at the origin
        assert abs(canon_a[..., 1].min()) < 1e-6 and np.abs(canon_a[0, 0, [0, 2]]).max() < 1e-6
        assert np.abs(read_interhuman(dest, sid) - np.stack([a30, b30])).max() < MM
    assert np.allclose(TO_Z_UP @ [0.0, 1.0, 0.0], [0.0, 0.0, 1.0])  # our up is InterHuman's +Z
    mean, std = np.load(dest / "global_mean.npy"), np.load(dest / "global_std.npy")
    train = _export_split(export, "train", good)
    feats = np.concatenate([np.load(dest / f"features/p{k}/{s}.npy") for s in train for k in (1, 2)]).astype(np.float64)
    assert mean.shape == std.shape == (262,) and doc["stats_over"] == "train"
    np.testing.assert_allclose(mean, feats.mean(0), atol=1e-5)
    assert (std > 0).all() and np.all(std[feats.std(0) < 1e-6] == 1.0)


def test_interhuman_texts_and_splits(export, converted):
    doc = converted[0]
    dest = Path(doc["dest"])
    assert _lines(dest / "annots/s0.txt") == [TEXT, "They push, then step back #2.", TEXT]
    assert _lines(dest / "annots/s1.txt") == ["two people interact: high five."] * 3
    assert _lines(dest / "annots/s3.txt") == ["Two people shake hands."] * 3
    assert doc["sequences"]["s1"]["text_source"] == "labels" and doc["sequences"]["s0"]["text_source"] == "texts"
    good = ["s0", "s1", "s3"]
    train, test = _export_split(export, "train", good), _export_split(export, "test", good)
    assert train and sorted(train + test) == good
    for folder in (dest, dest / "split"):
        assert _lines(folder / "train.txt") == train and _lines(folder / "test.txt") == test
        assert _lines(folder / "val.txt") == test
    assert doc["counts"] == {"train": len(train), "val": len(test), "test": len(test), "all": 3}
    on_disk = json.loads((dest / "conversion.json").read_text())
    assert on_disk == doc and on_disk["source"]["export"] == str(export[0].resolve())


# ----------------------------------------------------------------------------- HumanML3D
def test_humanml3d_tree_shapes_and_recovery(export, converted):
    doc = converted[1]
    dest = Path(doc["dest"])
    good = ["s0", "s1", "s3"]
    names = [f"{s}_{p}" for s in good for p in "ab"]
    assert doc["motions"] == 6 and doc["fps"] == 20.0 and sorted(doc["skipped"]) == ["s2"]
    assert sorted(p.stem for p in (dest / "new_joint_vecs").iterdir()) == names
    assert doc["outside_t2m_length"] == names[2:]  # s0 has 40 rows (2 s), the T2M minimum; s1, s3 fewer
    vecs = {}
    for sid in good:
        for p, j in zip("ab", _joints(export, sid)):
            j20 = resample_joints(j, FPS, 20.0)
            T20 = (SEQS[sid][0] - 1) * 2 + 1
            assert len(j20) == T20
            v = np.load(dest / f"new_joint_vecs/{sid}_{p}.npy", allow_pickle=False)
            nj = np.load(dest / f"new_joints/{sid}_{p}.npy", allow_pickle=False)
            assert v.dtype == nj.dtype == np.float32 and v.shape == (T20 - 1, 263) and nj.shape == (T20 - 1, 22, 3)
            np.testing.assert_allclose(v, motion_features(j20, 20.0)[:, :263], atol=1e-6)
            canon = canonicalize(j20)[0]  # world joints up to HumanML3D's canonicalisation
            assert np.abs(recover_joints(v, world=False) - canon).max() < MM
            assert np.abs(nj - canon[:-1]).max() < MM
            vecs[f"{sid}_{p}"] = v
    train = [f"{s}_{p}" for s in _export_split(export, "train", good) for p in "ab"]
    test = [f"{s}_{p}" for s in _export_split(export, "test", good) for p in "ab"]
    mean, std = feature_stats([vecs[n] for n in train])
    assert np.array_equal(np.load(dest / "Mean.npy"), mean) and np.array_equal(np.load(dest / "Std.npy"), std)
    assert np.load(dest / "Mean.npy").shape == (263,)
    assert _lines(dest / "train.txt") == train and _lines(dest / "test.txt") == test
    assert _lines(dest / "val.txt") == test and _lines(dest / "all.txt") == names


def test_humanml3d_texts_and_tokens(export, converted, tmp_path):
    dest = Path(converted[1]["dest"])
    toks = "the person on the left pushes the other with the right hand"
    want = [f"{TEXT}#{' '.join(w + '/OTHER' for w in toks.split())}#0.0#0.0",
            "They push, then step back 2.#they/OTHER push/OTHER then/OTHER step/OTHER back/OTHER#0.0#0.0"]  # fmt: skip
    assert _lines(dest / "texts/s0_a.txt") == want and _lines(dest / "texts/s0_b.txt") == want
    assert _lines(dest / "texts/s1_b.txt") == ["two people interact: high five.#two/OTHER people/OTHER "
                                               "interact/OTHER high/OTHER five/OTHER#0.0#0.0"]  # fmt: skip
    for line in _lines(dest / "texts/s3_a.txt"):  # parses as the T2M loaders do
        caption, tokens, start, end = line.strip().split("#")
        assert all(len(t.split("/")) == 2 for t in tokens.split(" ")) and float(start) == float(end) == 0.0
    assert humanml3d_tokens("A well-known person's T-pose, 3 times!") == ["a/OTHER", "wellknown/OTHER", "person/OTHER",
                                                                          "tpose/OTHER", "times/OTHER"]  # fmt: skip
    doc = to_humanml3d(export[0], tmp_path / "h", split="test", tokenize=lambda s: [f"{w}/NOUN" for w in s.split()[:1]])
    test = _export_split(export, "test", ["s0", "s1", "s3"])
    assert sorted(doc["sequences"]) == test and doc["stats_over"].startswith("all")
    assert doc["filled_splits"] == ["train"] and doc["counts"]["train"] == 2 * len(test)  # no empty list
    line = _lines(tmp_path / f"h/texts/{test[0]}_a.txt")[0]
    assert line.split("#")[1].endswith("/NOUN") and " " not in line.split("#")[1]
    with pytest.raises(ValueError, match="tokens must be 'word/POS'"):
        to_humanml3d(export[0], tmp_path / "h", tokenize=lambda s: ["no slash"])


# ----------------------------------------------------------------------------- options, errors
def test_split_option_rerun_and_label_texts(export, tmp_path):
    dest = tmp_path / "ih"
    to_interhuman(export[0], dest)
    doc = to_interhuman(export[0], dest, split="train", label_texts=False)  # re-run replaces the earlier one
    train = _export_split(export, "train", list(SEQS))
    assert sorted(doc["sequences"]) == sorted(set(train) - {"s1", "s2"})
    assert all(doc["skipped"][s].startswith("no text") for s in set(train) & {"s1", "s2"})
    assert sorted(p.stem for p in (dest / "annots").iterdir()) == sorted(doc["sequences"])
    assert _lines(dest / "test.txt") == sorted(doc["sequences"]) and doc["filled_splits"] == ["test", "val"]
    assert _lines(dest / "ignore_list.txt") == sorted(doc["skipped"])
    with pytest.raises(ValueError, match=r"unknown split 'val'; this export has \['test', 'train'\] or 'all'"):
        to_interhuman(export[0], dest, split="val")
    (tmp_path / "other").mkdir()
    (tmp_path / "other/keep.txt").write_text("mine")
    with pytest.raises(ValueError, match="non-empty folder that is not an earlier humanml3d conversion"):
        to_humanml3d(export[0], tmp_path / "other")
    with pytest.raises(ValueError, match="non-empty folder that is not an earlier humanml3d conversion"):
        to_humanml3d(export[0], dest)  # an InterHuman conversion is not overwritten by HumanML3D
    with pytest.raises(ValueError, match=r"the path contains \['person1'\]"):
        to_interhuman(export[0], tmp_path / "person1_data")
    assert (tmp_path / "other/keep.txt").read_text() == "mine"


def test_not_an_export_and_corrupted_export(export, tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(FormatError, match="does not exist: not a \\(finished\\) dataset export") as e:
        to_interhuman(tmp_path / "empty", tmp_path / "d")
    assert "dualhuman export WS OUT" in e.value.fix
    (tmp_path / "file").write_text("x")
    with pytest.raises(FormatError, match="is not a folder"):
        to_humanml3d(tmp_path / "file", tmp_path / "d")
    bad = tmp_path / "bad"
    shutil.copytree(export[0], bad)
    path = bad / "sequences/s1/motion.npz"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(FormatError, match="sequences/s1/motion.npz: sha256 differs from the manifest"):
        to_humanml3d(bad, tmp_path / "d")
    assert json.loads((tmp_path / "d/conversion.json").read_text())["complete"] is False
    assert to_humanml3d(export[0], tmp_path / "d")["complete"]  # an unfinished conversion is taken over


def test_cli_convert_commands(export, tmp_path):
    from dualhuman_builder.cli import main

    runner = CliRunner()
    r = runner.invoke(main, ["export", "interhuman", str(export[0]), str(tmp_path / "ih")])
    assert r.exit_code == 0, r.output
    assert "interhuman: 3 sequence(s) (" in r.output and "1 skipped, 1 captioned from labels" in r.output
    assert (tmp_path / "ih/motions_processed/person2/s0.npy").is_file()
    r = runner.invoke(main, ["export", "humanml3d", str(export[0]), str(tmp_path / "h"), "--split", "train"])
    assert r.exit_code == 0, r.output
    assert "humanml3d: " in r.output and "motions (" in r.output
    assert (tmp_path / "h/Mean.npy").is_file()
    (tmp_path / "empty").mkdir()
    r = runner.invoke(main, ["export", "humanml3d", str(tmp_path / "empty"), str(tmp_path / "h2")])
    assert r.exit_code == 2 and "not a (finished) dataset export" in r.output and "fix:" in r.output
    r = runner.invoke(main, ["export", "interhuman", str(export[0]), str(tmp_path / "h")])
    assert r.exit_code == 2 and "not an earlier interhuman conversion; choose an empty or new folder" in r.output
    r = runner.invoke(main, ["export", "--help"])
    assert "export interhuman OUT DEST" in r.output and "export humanml3d OUT DEST" in r.output
    for cmd in ("interhuman", "humanml3d"):
        r = runner.invoke(main, ["export", cmd, "--help"])
        assert r.exit_code == 0 and f"Example:  dualhuman export {cmd} WS/export" in r.output

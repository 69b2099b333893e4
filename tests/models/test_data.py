"""The models' data: ring visibility of both people, and windows of a real export with roles resolved."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st
from tiny_export import make_tiny_export

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.export.files import load_motion
from dualhuman_builder.models.base import BATCH_KEYS
from dualhuman_builder.export.files import read_manifest
from dualhuman_builder.models.data import VALIDATION_SHARE, InteractionWindows, collate, split_ids, validation_subjects
from dualhuman_builder.models.visibility import joint_visibility, ring_cameras

HEAD, PELVIS, R_WRIST, R_ELBOW = 15, 0, 21, 19


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    return make_tiny_export(tmp_path_factory.mktemp("models-data"))


@pytest.fixture(scope="module")
def standing(export):
    """One person's 22 joints at rest-ish (frame 0 of a tiny sequence), facing +x, pelvis at the origin."""
    j = load_motion(export / "sequences/tiny00/motion.npz")["a.joints"][:1].astype(np.float64)
    return j - j[:, :1] * [1.0, 0.0, 1.0]


def _turned(joints, yaw, shift):
    """``joints`` turned by ``yaw`` about +Y at the origin, then moved by ``shift``."""
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return joints @ R.T + np.asarray(shift)


def test_ring_is_around_the_pair(standing):
    b = _turned(standing, np.pi, [2.0, 0.0, 0.0])
    cams = ring_cameras(standing, b, cameras=4, radius=3.0, height=1.5)
    assert cams.shape == (1, 4, 3)
    np.testing.assert_allclose(cams[0, :, 1], 1.5)
    np.testing.assert_allclose(np.linalg.norm(cams[0, :, [0, 2]].T - [1.0, 0.0], axis=1), 3.0)
    np.testing.assert_allclose(cams[0, 0], [4.0, 1.5, 0.0], atol=1e-9)


def test_isolated_person_is_seen_except_self_occlusion(standing):
    far_below = standing - [0.0, 100.0, 0.0]  # no ray from the ring to the person passes it
    far_side = _turned(standing, 1.0, [0.0, -200.0, 0.0])
    vis, _ = joint_visibility(standing, far_below, cameras=16)
    vis2, _ = joint_visibility(standing, far_side, cameras=16)
    np.testing.assert_array_equal(vis, vis2)  # the other person plays no part
    assert vis.shape == (1, 22) and vis.dtype == np.float32
    assert vis[0, HEAD] == 1.0 and vis[0, R_WRIST] >= 0.75
    # self-occlusion: the right hand put behind the back is hidden from cameras in front
    hidden = standing.copy()
    hidden[0, R_WRIST] = hidden[0, 3] + [-0.2, 0.0, 0.0]  # 0.2 m behind spine1 (the person faces +x)
    vis3, _ = joint_visibility(hidden, far_below, cameras=16)
    assert vis3[0, R_WRIST] <= 0.75 and vis3[0, R_WRIST] < vis[0, R_WRIST] and vis3[0, HEAD] == 1.0


def test_joint_behind_the_other_person_is_less_visible_than_an_exposed_head(standing):
    b = _turned(standing, np.pi, [0.6, 0.0, 0.0])  # face to face, 0.6 m apart
    a = standing.copy()
    a[0, R_WRIST] = b[0, 3] + [0.15, 0.0, 0.0]  # a reaches round b: its hand is on b's back
    vis_a, vis_b = joint_visibility(a, b, cameras=8)
    assert vis_a[0, R_WRIST] <= 0.625  # hidden by b's body from the cameras on a's side (seen from b's sides)
    assert vis_a[0, HEAD] > vis_a[0, R_WRIST]
    assert vis_b[0, HEAD] >= 0.75
    # the same hand with b gone is seen from more cameras
    alone, _ = joint_visibility(a, b - [0.0, 100.0, 0.0], cameras=8)
    assert alone[0, R_WRIST] > vis_a[0, R_WRIST]


def test_visibility_of_a_real_sequence(export):
    m = load_motion(export / "sequences/tiny00/motion.npz")
    va, vb = joint_visibility(m["a.joints"], m["b.joints"], cameras=6)
    assert va.shape == vb.shape == (80, 22)
    assert ((va >= 0) & (va <= 1)).all() and ((vb >= 0) & (vb <= 1)).all()
    assert np.isin(np.round(va * 6), np.arange(7)).all()  # shares of 6 cameras
    assert va.mean() > 0.5 and va.min() < 1.0


@given(st.integers(1, 3), st.floats(-2.0, 2.0), st.floats(0.2, 3.0), st.integers(1, 9))
def test_visibility_is_a_share_and_never_fails_on_finite_input(T, dx, scale, cams):
    rng = np.random.default_rng(T * 7 + cams)
    a = rng.normal(0.0, scale, (T, 22, 3))
    b = rng.normal(0.0, scale, (T, 22, 3)) + [dx, 0.0, 0.0]
    a[:, 3] = a[:, 0]  # a degenerate (zero-length) capsule
    va, _ = joint_visibility(a, b, cameras=cams)
    assert va.shape == (T, 22) and np.isfinite(va).all() and ((va >= 0) & (va <= 1)).all()


def test_visibility_rejects_bad_input(standing):
    with pytest.raises(DualhumanError, match=r"\(T, 22, 3\)"):
        joint_visibility(standing[:, :21], standing)
    with pytest.raises(DualhumanError, match="NaN"):
        joint_visibility(standing * np.nan, standing)
    with pytest.raises(DualhumanError, match="camera ring"):
        joint_visibility(standing, standing, cameras=0)


def test_windows_have_the_batch_keys_and_roles(export):
    ds = InteractionWindows(export, "train", window=32)
    test = InteractionWindows(export, "test", window=32, visibility=False)
    assert set(ds.ids).isdisjoint(test.ids) and len(ds.ids) + len(test.ids) == 4
    assert len(ds) == len(ds.ids) * 4  # 80 frames: starts 0, 16, 32, 48
    item = ds[0]
    assert set(item) == set(BATCH_KEYS)
    assert item["joints_actor"].shape == (32, 22, 3) and item["visibility_actor"].shape == (32, 22)
    assert item["labels"].shape == (30,) and item["start"].dtype == torch.int64
    batch = collate([ds[i] for i in range(3)])
    assert set(batch) == set(BATCH_KEYS)
    fast = ds.batch([0, 1, 2])  # the loop's gather path gives the very same batch
    for key, value in batch.items():
        assert torch.equal(value, fast[key]) if isinstance(value, torch.Tensor) else value == fast[key], key
    ds.set_epoch(1)
    mixed = ds.batch([len(ds) - 1, 0, -1])
    assert torch.equal(mixed["joints_actor"][0], ds[len(ds) - 1]["joints_actor"]) and mixed["seq_id"][2] == ds.ids[-1]
    with pytest.raises(IndexError):
        ds.batch([len(ds)])
    assert batch["joints_reactor"].shape == (3, 32, 22, 3) and batch["labels"].shape == (3, 30)
    assert isinstance(batch["text"], list) and len(batch["seq_id"]) == 3
    assert (test[0]["visibility_actor"] == 1).all()  # visibility=False: ones
    # roles: tiny01 names person b the actor (it walks towards a): the actor's pelvis moves towards the reactor
    every = InteractionWindows(export, "all", window=80, visibility=False)
    assert every.swapped == ["tiny01"]
    for i in range(len(every)):
        it = every[i]
        ja, jr = it["joints_actor"].numpy(), it["joints_reactor"].numpy()
        gap = np.linalg.norm(ja[:, 0] - jr[:, 0], axis=1)
        moved_a = np.linalg.norm(ja[-1, 0] - ja[0, 0])
        moved_r = np.linalg.norm(jr[-1, 0] - jr[0, 0])
        assert gap[-1] < gap[0] and moved_a > moved_r, it["seq_id"]
        m = load_motion(export / f"sequences/{it['seq_id']}/motion.npz")
        src = "b" if it["seq_id"] == "tiny01" else "a"
        np.testing.assert_array_equal(ja, m[f"{src}.joints"])
    labels = json.loads((export / "sequences/tiny01/text.json").read_text())
    assert labels["roles"] == ["reactor", "actor"]


def test_visibility_sees_the_interaction(export):
    ds = InteractionWindows(export, "all", window=80, cameras=8)
    assert ds[0]["visibility_actor"].min() < 1.0  # the two bodies hide joints of each other and themselves
    from dualhuman_builder.models import data

    cached = len(data._VIS_CACHE)
    again = InteractionWindows(export, "all", window=80, cameras=8)  # computed once per sequence and process
    assert len(data._VIS_CACHE) == cached
    np.testing.assert_array_equal(again.sequence(0)["vis_actor"], ds.sequence(0)["vis_actor"])


def test_windows_errors_are_clear(export, tmp_path):
    with pytest.raises(DualhumanError, match="manifest.json") as e:
        InteractionWindows(tmp_path)
    assert e.value.fix and "dualhuman export" in e.value.fix
    with pytest.raises(DualhumanError, match="not a folder"):
        InteractionWindows(tmp_path / "missing")
    with pytest.raises(DualhumanError, match="no window of 500 frames") as e:
        InteractionWindows(export, "train", window=500)
    assert "shorter window" in e.value.fix
    with pytest.raises(DualhumanError, match="unknown split"):
        InteractionWindows(export, "val")
    with pytest.raises(DualhumanError, match="window"):
        InteractionWindows(export, window=0)


def test_fit_and_validation_divide_the_train_split_by_people(export):
    m = read_manifest(export)
    train, fit, val = (split_ids(export, m, s) for s in ("train", "fit", "validation"))
    assert fit and val and sorted(fit + val) == sorted(train) and not set(fit) & set(val)

    def people(ids):
        return {x for sid in ids for x in m["sequences"][sid]["subjects"]}

    held = set(validation_subjects(m, train))
    assert held and held <= people(val) and not held & people(fit)  # the fit never sees a validation person
    assert len(val) >= VALIDATION_SHARE * len(train)
    assert split_ids(export, m, "validation") == val and not set(val) & set(split_ids(export, m, "test"))
    assert InteractionWindows(export, "fit", visibility=False).ids == fit


def test_validation_takes_people_until_its_share_is_reached(export):
    seqs = {f"S{i:02d}": {"subjects": [f"p{i % 10}", f"p{(i + 1) % 10}"]} for i in range(40)}
    chosen = validation_subjects({"sequences": seqs}, sorted(seqs))

    def held(names):
        return sum(1 for d in seqs.values() if set(d["subjects"]) & set(names))

    assert held(chosen) >= VALIDATION_SHARE * 40 > held(chosen[:-1])  # enough people, and no one more
    m = read_manifest(export)
    for subjects, why in (([], "names no subjects"), (["p0", "p1"], "shares a person")):
        bad = {**m, "sequences": {sid: {**d, "subjects": subjects} for sid, d in m["sequences"].items()}}
        with pytest.raises(DualhumanError, match=why) as e:
            split_ids(export, bad, "fit")
        assert "train split" in e.value.fix


json_values = st.recursive(st.none() | st.booleans() | st.integers() | st.text(max_size=8),
                           lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=8), c, max_size=3), max_leaves=8)  # fmt: skip


@given(json_values, st.one_of(st.none(), st.lists(st.sampled_from(["actor", "reactor", "", "x"]), max_size=3)))
def test_roles_of_any_text_json_resolve_without_error(doc, roles):
    from dualhuman_builder.models.data import actor_is_b

    if isinstance(doc, dict) and roles is not None:
        doc["roles"] = roles
    swap = actor_is_b(doc)
    assert swap is (isinstance(doc, dict) and doc.get("symmetric") is not True and roles == ["reactor", "actor"]) or (
        swap is False and roles != ["reactor", "actor"])


@pytest.mark.parametrize("damage", ["motion", "text", "labels", "split"])
def test_a_damaged_export_gives_a_clear_error(tmp_path, damage):
    ds = make_tiny_export(tmp_path)
    target = {"motion": "sequences/tiny00/motion.npz", "text": "sequences/tiny00/text.json", "labels": "labels.json",
              "split": "splits/train.txt"}[damage]  # fmt: skip
    (ds / target).write_bytes(b"\x00garbage" if damage != "split" else b"tiny00\n../../etc\n")
    with pytest.raises(DualhumanError) as e:
        InteractionWindows(ds, "train", window=32)
    assert e.value.fix

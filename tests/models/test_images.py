"""The image dataset of the pose estimator (dualhuman_builder.models.images.ImageFrames) on a real tiny
rendered export: batch keys, shapes and dtypes; targets that agree with the export's; flips and crop
jitter that keep every target consistent with the image and the intrinsics; clear errors for exports
without renders and for damaged files; a bounded cache."""

from __future__ import annotations

import hashlib
import json
import shutil

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tiny_render_export import make_tiny_render_export

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.export.features import MIRROR_PERM
from dualhuman_builder.export.files import read_npz
from dualhuman_builder.export.writer import normalised_root, root_from_normalised
from dualhuman_builder.models.images import ImageFrames

S = 32


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    return make_tiny_render_export(tmp_path_factory.mktemp("images"))


@pytest.fixture(scope="module")
def frames(export):
    return ImageFrames(export, "train", size=S)


@pytest.fixture(scope="module")
def augmented(export):
    return ImageFrames(export, "all", size=S, augment=True, seed=1)


def _project(item) -> tuple[np.ndarray, np.ndarray]:
    """``(pixels (2, 22, 2) of K joints_cam, the item's keypoints2d u, v)``."""
    j = item["joints_cam"].double().numpy()
    uvw = j @ item["K"].double().numpy().T
    return uvw[..., :2] / uvw[..., 2:], item["keypoints2d"][..., :2].double().numpy()


def test_batch_keys_shapes_and_dtypes(frames):
    assert len(frames) == 8 and frames.views == ["view00", "view01"] and frames.ids == ["tiny00"]
    b = frames.batch([0, 3, 5])
    want = {"image": ((3, 3, S, S), torch.float32), "K": ((3, 3, 3), torch.float32),
            "joints_cam": ((3, 2, 22, 3), torch.float32), "transl": ((3, 2, 3), torch.float32),
            "prob": ((3, 2), torch.float32), "keypoints2d": ((3, 2, 22, 3), torch.float32),
            "prev_root": ((3, 2, 3), torch.float32), "has_prev": ((3,), torch.bool), "frame": ((3,), torch.int64)}  # fmt: skip
    assert set(b) == set(want) | {"seq_id", "camera"}
    for k, (shape, dtype) in want.items():
        assert tuple(b[k].shape) == shape and b[k].dtype == dtype, k
    assert b["seq_id"] == ["tiny00"] * 3 and b["camera"] == ["view00", "view00", "view01"]
    assert b["frame"].tolist() == [0, 9, 3] and b["has_prev"].tolist() == [False, True, True]
    assert 0.0 <= b["image"].min() and b["image"].max() <= 1.0 and b["image"].std() > 0.05
    assert set(np.unique(b["keypoints2d"][..., 2].numpy())) <= {0.0, 1.0}
    one = frames.item(3)
    for k in want:
        assert torch.equal(one[k], b[k][1]), k
    assert torch.equal(frames[3]["image"], one["image"])
    with pytest.raises(IndexError):
        frames.item(8)


def test_targets_are_the_exports_in_the_crop(frames, export):
    t = read_npz(export / "sequences/tiny00/renders/targets.npz")
    for i in range(len(frames)):
        it = frames.item(i)
        c, r = int(frames.index[i][1]), int(frames.index[i][2])
        np.testing.assert_allclose(it["joints_cam"].numpy(), t["joints_cam"][c, r], atol=1e-6)
        np.testing.assert_allclose(it["prob"].numpy(), t["prob"][c, r])
        proj, kp = _project(it)
        assert np.abs(proj - kp).max() < 0.5
        np.testing.assert_allclose(it["transl"].numpy(), normalised_root(it["joints_cam"][:, 0].double().numpy(),
                                                                         it["K"].double().numpy(), S, S), atol=1e-4)  # fmt: skip
        assert (it["transl"][:, :2].abs() < 1.0).all()  # both roots inside the crop
        # the previous rendered frame's roots, in this crop
        if it["has_prev"]:
            before = frames.item(i - 1)
            back = root_from_normalised(it["prev_root"].double().numpy(), it["K"].double().numpy(), S, S)
            np.testing.assert_allclose(back, before["joints_cam"][:, 0].double().numpy(), atol=1e-4)
        else:
            assert r == 0 and not it["prev_root"].any()


@given(i=st.integers(0, 15), scale=st.floats(0.7, 1.4), sx=st.floats(-0.25, 0.25), sy=st.floats(-0.25, 0.25),
       drop=st.booleans())  # fmt: skip
def test_flip_and_jitter_keep_every_target_consistent(augmented, i, scale, sx, sy, drop):
    a = augmented.augmented(i, False, scale, sx, sy, drop)
    b = augmented.augmented(i, True, scale, sx, sy, drop)
    for it in (a, b):
        proj, kp = _project(it)
        assert np.abs(proj - kp).max() < 0.5
        np.testing.assert_allclose(it["transl"].numpy(), normalised_root(it["joints_cam"][:, 0].double().numpy(),
                                                                         it["K"].double().numpy(), S, S), atol=1e-4)  # fmt: skip
        assert it["K"][0, 0] > 0 and it["K"][1, 1] > 0
    assert torch.equal(b["image"], a["image"].flip(-1))
    # left and right swap, x is mirrored, the persons keep their order
    np.testing.assert_allclose(b["joints_cam"].numpy(), a["joints_cam"][:, MIRROR_PERM].numpy() * [-1, 1, 1], atol=1e-6)
    np.testing.assert_allclose(b["keypoints2d"][..., 0].numpy(), S - a["keypoints2d"][:, MIRROR_PERM, 0].numpy(), atol=1e-4)
    assert torch.equal(b["keypoints2d"][..., 1:], a["keypoints2d"][:, MIRROR_PERM, 1:])
    np.testing.assert_allclose(b["transl"].numpy(), a["transl"].numpy() * [-1, 1, 1], atol=1e-5)  # u mirrored
    np.testing.assert_allclose(b["prev_root"].numpy(), a["prev_root"].numpy() * [-1, 1, 1], atol=1e-5)
    assert torch.equal(b["prob"], a["prob"]) and bool(b["has_prev"]) == bool(a["has_prev"]) == (
        not drop and int(augmented.index[i][2]) > 0)


def test_augmentation_draws_are_seeded_per_epoch(export, augmented):
    idx = np.arange(len(augmented))
    augmented.set_epoch(0)
    first = augmented.batch(idx)
    again = ImageFrames(export, "all", size=S, augment=True, seed=1).batch(idx)
    assert torch.equal(first["image"], again["image"]) and torch.equal(first["K"], again["K"])
    augmented.set_epoch(1)
    other = augmented.batch(idx)
    assert not torch.equal(first["K"], other["K"])
    flips = [bool(augmented._draws(i)[0]) for i in range(len(augmented))]
    assert 0 < sum(flips) < len(flips)
    for b in (first, other):
        for k in range(len(idx)):
            proj = b["joints_cam"][k].double() @ b["K"][k].double().T
            assert (proj[..., :2] / proj[..., 2:] - b["keypoints2d"][k, ..., :2]).abs().max() < 0.5


def test_views_and_the_cache_budget(export):
    one = ImageFrames(export, "test", size=S, views=["view01"], cache_mb=0.004)
    assert len(one) == 4 and set(one.batch(range(4))["camera"]) == {"view01"} and one.ids == ["tiny01"]
    assert one._cached <= 0.004 * (1 << 20) and len(one._cache) < 4
    none = ImageFrames(export, "test", size=S, cache_mb=0)
    none.batch(range(len(none)))
    assert not none._cache
    full = ImageFrames(export, "test", size=S)
    b1 = full.batch(range(len(full)))
    assert len(full._cache) == len(full)
    assert torch.equal(full.batch(range(len(full)))["image"], b1["image"])  # from the cache, the same pixels
    with pytest.raises(DualhumanError, match="no views"):
        ImageFrames(export, "test", views=["view07"])


def _drop_targets(ds):
    manifest = json.loads((ds / "manifest.json").read_text())
    for rel in [r for r in manifest["files"] if r.endswith("targets.npz")]:
        del manifest["files"][rel]
    (ds / "manifest.json").write_text(json.dumps(manifest))


def test_clear_errors_for_exports_without_renders(export, tmp_path):
    ds = shutil.copytree(export, tmp_path / "ds")
    _drop_targets(ds)
    with pytest.raises(DualhumanError, match="no rendered targets") as e:
        ImageFrames(ds, "train")
    assert "--render" in e.value.fix and "dualhuman render" in e.value.fix
    with pytest.raises(DualhumanError, match="not a folder"):
        ImageFrames(tmp_path / "missing")
    with pytest.raises(DualhumanError, match="unknown split"):
        ImageFrames(export, "val")
    with pytest.raises(DualhumanError, match="image size"):
        ImageFrames(export, size=4)
    (ds / "sequences/tiny00/renders/views/view01/rgb/00003.png").unlink()
    manifest = json.loads((export / "manifest.json").read_text())
    (ds / "manifest.json").write_text(json.dumps(manifest))  # the targets back: a listed image is missing
    frames = ImageFrames(ds, "train")
    with pytest.raises(DualhumanError, match="00003.png.*missing") as e:
        frames.batch(range(len(frames)))
    assert e.value.fix


def _damage(ds, rel: str, data: bytes) -> None:
    (ds / rel).write_bytes(data)
    manifest = json.loads((ds / "manifest.json").read_text())
    manifest["files"][rel] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
    (ds / "manifest.json").write_text(json.dumps(manifest))


@pytest.fixture(scope="module")
def to_damage(export, tmp_path_factory):
    """One copy of the export; each example damages one file and puts it back."""
    return shutil.copytree(export, tmp_path_factory.mktemp("damaged") / "ds")


@settings(max_examples=30)
@given(data=st.data(), which=st.sampled_from(["renders/targets.npz", "renders/keypoints.npz",
                                              "renders/views/view00/rgb/00000.png", "cameras.json"]))  # fmt: skip
def test_damaged_files_give_clear_errors(to_damage, data, which):
    ds, rel = to_damage, f"sequences/tiny01/{which}"
    original, manifest = (ds / rel).read_bytes(), (ds / "manifest.json").read_bytes()
    raw = bytearray(original)
    if data.draw(st.booleans()):
        raw = raw[: data.draw(st.integers(0, len(raw)))]
    for _ in range(data.draw(st.integers(0, 6))):
        if raw:
            raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    _damage(ds, rel, bytes(raw))
    try:
        frames = ImageFrames(ds, "test", size=16, cache_mb=0)
        frames.batch(range(len(frames)))
    except DualhumanError as e:  # anything else fails the test
        assert e.fix
    finally:
        (ds / rel).write_bytes(original)
        (ds / "manifest.json").write_bytes(manifest)

"""Image targets of a rendered export (``renders/targets.npz``): written by the export writer from the
motion, the cameras and the render, consistent with the render's keypoints and masks, described by the
schema and checked by `export verify`, which rejects a damaged file. Built on one real tiny render."""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

sys.path.insert(0, str(Path(__file__).parents[1] / "models"))
from tiny_render_export import build_tiny_render_export, make_tiny_render_export  # noqa: E402

from dualhuman_builder.export.files import npz_bytes, read_npz  # noqa: E402
from dualhuman_builder.export.verify import verify_export  # noqa: E402
from dualhuman_builder.export.writer import normalised_root, root_from_normalised  # noqa: E402


@pytest.fixture(scope="module")
def export(tmp_path_factory) -> Path:
    out = make_tiny_render_export(tmp_path_factory.mktemp("render-targets"))
    assert verify_export(out) == []
    return out


@pytest.fixture
def ds(export, tmp_path) -> Path:
    """A fresh copy of the export to damage."""
    return Path(shutil.copytree(export, tmp_path / "ds"))


def _read(out: Path, sid: str) -> tuple[dict, dict, dict, dict]:
    base = out / "sequences" / sid
    return (read_npz(base / "renders/targets.npz"), read_npz(base / "renders/keypoints.npz"),
            read_npz(base / "motion.npz"), {c["name"]: c for c in json.loads((base / "cameras.json").read_text())["cameras"]})  # fmt: skip


def test_targets_agree_with_motion_cameras_keypoints_and_masks(export):
    manifest = json.loads((export / "manifest.json").read_text())
    schema = json.loads((export / "schema.json").read_text())
    assert {e["name"] for e in schema["arrays"] if e["file"].endswith("targets.npz")} == {
        "joints_cam", "transl", "prob", "box", "frames", "views"}  # fmt: skip
    assert manifest["counts"]["with_targets"] == 2
    for sid in ("tiny00", "tiny01"):
        assert manifest["sequences"][sid]["has"]["targets"]
        t, kp, motion, cams = _read(export, sid)
        C, R = len(kp["views"]), len(kp["frames"])
        assert t["joints_cam"].shape == (C, R, 2, 22, 3) and t["transl"].shape == (C, R, 2, 3)
        assert t["prob"].shape == (C, R, 2) and t["box"].shape == (C, R, 2, 4)
        assert t["views"].tolist() == kp["views"].tolist() and np.array_equal(t["frames"], kp["frames"])
        world = np.stack([motion["a.joints"], motion["b.joints"]])[:, kp["frames"]]  # (2, R, 22, 3)
        for c, view in enumerate(kp["views"].tolist()):
            cam = cams[view]
            K, Rm, tv = (np.asarray(cam[k]) for k in ("K", "R", "t"))
            jc = t["joints_cam"][c].astype(np.float64)
            np.testing.assert_allclose(jc, (world @ Rm.T + tv).transpose(1, 0, 2, 3), atol=1e-5)
            uvw = jc @ K.T
            assert np.abs(uvw[..., :2] / uvw[..., 2:] - kp["joints"][c, ..., :2]).max() < 0.5
            # transl: the root over the full image, and back
            root = jc[:, :, 0]
            uv = root @ K.T
            uv = uv[..., :2] / uv[..., 2:]
            want = np.stack([2 * uv[..., 0] / cam["width"] - 1, 2 * uv[..., 1] / cam["height"] - 1,
                             root[..., 2] * 2 * np.tan(np.radians(cam["fov_x_deg"]) / 2)], axis=-1)  # fmt: skip
            np.testing.assert_allclose(t["transl"][c], want, atol=1e-4)
            np.testing.assert_allclose(root_from_normalised(t["transl"][c], K, cam["width"], cam["height"]), root, atol=1e-4)
            # saliency: share of visible joints; every visible joint lies in its person's mask box
            np.testing.assert_allclose(t["prob"][c], (kp["joints"][c, ..., 2] > 0.5).mean(-1), atol=1e-6)
            for r, f in enumerate(kp["frames"]):
                mask = np.asarray(Image.open(export / "sequences" / sid / f"renders/views/{view}/mask/{f:05d}.png"))
                for p in range(2):
                    x0, y0, x1, y1 = t["box"][c, r, p]
                    ys, xs = np.nonzero(mask == p + 1)
                    assert (x0, y0, x1, y1) == (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1)
                    vis = kp["joints"][c, r, p][kp["joints"][c, r, p, :, 2] > 0.5]
                    assert ((vis[:, 0] >= x0) & (vis[:, 0] < x1) & (vis[:, 1] >= y0) & (vis[:, 1] < y1)).all()
        assert 0.0 < t["prob"].mean() < 1.0  # some joints hidden, most seen


def test_shards_carry_the_targets(export, tmp_path):
    from dualhuman_builder.export.shards import iter_shards, write_shards

    samples = list(iter_shards(write_shards(export, tmp_path / "shards", split="all")))
    assert samples and all(s["targets.npz"] == (export / "sequences" / s["__key__"] / "renders/targets.npz").read_bytes()
                           for s in samples)  # fmt: skip


@given(st.floats(-2, 2), st.floats(-2, 2), st.floats(0.2, 30), st.floats(20, 2000), st.floats(-50, 300))
def test_normalised_root_inverts(x, y, z, f, cx):
    K = np.array([[f, 0.0, cx], [0.0, f, 0.7 * cx], [0.0, 0.0, 1.0]])
    root = np.array([x, y, z])
    t = normalised_root(root, K, 256, 200)
    np.testing.assert_allclose(root_from_normalised(t, K, 256, 200), root, atol=1e-9 * max(1.0, f))
    assert t[2] == pytest.approx(z * 256 / f)


def _rewrite(ds: Path, sid: str, change) -> None:
    """Rewrite ``sid``'s targets.npz with ``change(arrays)`` applied, and its manifest checksum, so that only
    the consistency checks can catch it."""
    rel = f"sequences/{sid}/renders/targets.npz"
    arrays = read_npz(ds / rel)
    change(arrays)
    data = npz_bytes(arrays)
    (ds / rel).write_bytes(data)
    manifest = json.loads((ds / "manifest.json").read_text())
    manifest["files"][rel] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
    (ds / "manifest.json").write_text(json.dumps(manifest))


def _shift(a):
    a["joints_cam"][0, 1, 0, :, 0] += 0.1  # 10 cm: a few pixels at 48 px


def _nan(a):
    a["transl"][1, 0, 1, 2] = np.nan


def _transl(a):
    a["transl"][0, 2, 0, 0] += 0.05


def _prob(a):
    a["prob"][0, 0, 0] = 1.5


def _prob_share(a):
    a["prob"][1, 3, 1] = 0.5 if a["prob"][1, 3, 1] != 0.5 else 0.25


def _box(a):
    a["box"][0, 0, 1] = [30.0, 5.0, 20.0, 40.0]


def _frames(a):
    a["frames"] = a["frames"] + 1


def _shape(a):
    a["prob"] = a["prob"][:, :-1]


@pytest.mark.parametrize("change, says", [(_shift, "px from"), (_nan, "NaN"), (_transl, "normalised root"),
                                          (_prob, "outside [0, 1]"), (_prob_share, "share of visible"),
                                          (_box, "not inside"), (_frames, "views or frames"),
                                          (_shape, "schema says")])  # fmt: skip
def test_verify_rejects_damaged_targets(ds, change, says):
    _rewrite(ds, "tiny01", change)
    problems = verify_export(ds)
    assert problems and all("tiny01/renders/targets.npz" in p for p in problems), problems
    assert any(says in p for p in problems), problems


def test_verify_wants_the_targets_the_manifest_promises(ds):
    (ds / "sequences/tiny00/renders/targets.npz").unlink()
    manifest = json.loads((ds / "manifest.json").read_text())
    del manifest["files"]["sequences/tiny00/renders/targets.npz"]
    (ds / "manifest.json").write_text(json.dumps(manifest))
    assert any("targets.npz: promised by the manifest" in p for p in verify_export(ds))


@settings(max_examples=25)
@given(st.data())
def test_verify_reports_corrupt_targets_bytes_and_never_raises(ds, data):
    rel = "sequences/tiny00/renders/targets.npz"
    original, manifest = (ds / rel).read_bytes(), (ds / "manifest.json").read_bytes()
    raw = bytearray(original)
    for _ in range(data.draw(st.integers(1, 8))):
        raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
    doc = json.loads(manifest)
    doc["files"][rel] = {"sha256": hashlib.sha256(raw).hexdigest(), "bytes": len(raw)}
    (ds / rel).write_bytes(bytes(raw))
    (ds / "manifest.json").write_text(json.dumps(doc))
    try:
        problems = verify_export(ds)  # never raises
    finally:
        (ds / rel).write_bytes(original)
        (ds / "manifest.json").write_bytes(manifest)
    assert problems or _same_arrays(bytes(raw), original)


def _same_arrays(raw: bytes, original: bytes) -> bool:
    """Whether corrupted bytes still hold the original arrays (a changed byte in a zip field nobody reads)."""
    try:
        got, want = read_npz(raw), read_npz(original)
    except ValueError:
        return False
    return got.keys() == want.keys() and all(np.array_equal(got[k], want[k]) for k in want)


def test_writer_gives_no_targets_for_a_render_of_other_motion(tmp_path):
    from tiny_export import _sequence

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.export.writer import export_dataset

    renders = build_tiny_render_export().parent / "renders"
    model = get_body_model()
    right, wrong = _sequence(model, 12, 0, 0), _sequence(model, 12, 1, 0)
    right.render_dir, wrong.render_dir = renders / "tiny00", renders / "tiny00"  # tiny01's motion, tiny00's render
    lines = []
    manifest = export_dataset([right, wrong], tmp_path / "out", expect=("motion", "renders"), progress=lines.append)
    assert list(manifest["sequences"]) == ["tiny00", "tiny01"]  # the motion and the render are kept
    assert [manifest["sequences"][s]["has"]["targets"] for s in ("tiny00", "tiny01")] == [True, False]
    assert "not of this motion" in manifest["targets_problems"]["tiny01"] and list(manifest["targets_problems"]) == ["tiny01"]
    assert any("tiny01" in x and "WARNING: no image targets" in x for x in lines)
    assert verify_export(tmp_path / "out") == []

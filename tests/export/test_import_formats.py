"""Importing HumanML3D- and InterHuman-layout folders into the export layout: our export -> their layout
(the converters) -> ours again, within 1 mm of the joints, through ``dualhuman export verify``; folders
that are not in the layout and hostile files give a clear error or a counted skip. Exports are written
by hand from synthetic joints (no fit)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import event, given, settings
from hypothesis import strategies as st

from synthetic_pairs import FPS, TEXT, face_to_face, write_export
from dualhuman_builder.cli.app import main
from dualhuman_builder.errors import FormatError
from dualhuman_builder.export.convert import to_humanml3d, to_interhuman
from dualhuman_builder.export.features import (
    HUMANML3D_FPS,
    resample_joints,
)
from dualhuman_builder.export.files import load_motion
from dualhuman_builder.export.importers import (
    JOINTS_ONLY,
    import_humanml3d,
    import_interhuman,
)
from dualhuman_builder.export.interhuman import INTERHUMAN_FPS
from dualhuman_builder.export.loader import MotionWindows
from dualhuman_builder.export.verify import verify_export

MM = 1e-3


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """A two-sequence export (a face-to-face pair, and one that turns in place) and the original joints."""
    tmp = tmp_path_factory.mktemp("import")
    hug, turn = face_to_face(T=30, seed=3), face_to_face(T=30, seed=5, turns=1.0)
    export = write_export(tmp / "ds", {"hug": (*hug, "train"), "turn": (*turn, "test")})
    return tmp, export, {"hug": hug, "turn": turn}


def _joints(out: Path, sid: str) -> tuple[np.ndarray, np.ndarray]:
    m = load_motion(out / "sequences" / sid / "motion.npz")
    return m["a.joints"], m["b.joints"]


def _verify_ok(out: Path) -> None:
    problems = verify_export(out)
    assert not problems, problems


def _align_yaw(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``x (T, 22, 3)`` turned about +Y and shifted onto ``ref`` (least squares: 2-D Kabsch, mean height)."""
    p, q = x[..., [0, 2]].reshape(-1, 2), ref[..., [0, 2]].reshape(-1, 2)
    pc, qc = p - p.mean(0), q - q.mean(0)
    u, _, vt = np.linalg.svd(pc.T @ qc)
    r = u @ vt
    if np.linalg.det(r) < 0:  # a turn, not a reflection
        u[:, -1] *= -1
        r = u @ vt
    xz = pc @ r + q.mean(0)
    out = x.astype(np.float64).copy()
    out[..., 0], out[..., 2] = xz[:, 0].reshape(x.shape[:-1]), xz[:, 1].reshape(x.shape[:-1])
    out[..., 1] += (ref[..., 1] - out[..., 1]).mean()
    return out


def test_interhuman_round_trip_within_1mm(source):
    tmp, export, orig = source
    to_interhuman(export, tmp / "ih")
    res = import_interhuman(tmp / "ih", tmp / "from_ih")
    assert res["imported"] == 2 and res["skipped"] == {}
    out = tmp / "from_ih"
    _verify_ok(out)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["fps"] == INTERHUMAN_FPS and manifest["body_model"]["name"] == JOINTS_ONLY
    for sid, (a, b) in orig.items():
        ja, jb = _joints(out, sid)
        # the world frame comes back through conversion.json's transform: no alignment needed
        assert np.abs(ja - resample_joints(a, FPS, INTERHUMAN_FPS)).max() < MM
        assert np.abs(jb - resample_joints(b, FPS, INTERHUMAN_FPS)).max() < MM
        doc = json.loads((out / "sequences" / sid / "sequence.json").read_text())
        assert doc["meta"]["imported_from"]["split"] == {"hug": "train", "turn": "test"}[sid]
    texts = json.loads((out / "sequences" / "hug" / "text.json").read_text())["texts"]
    assert texts == [TEXT]
    windows = MotionWindows(out, window=16, split="all", normalize=True)  # what the toolkit's models train on
    assert len(windows) > 0 and np.isfinite(np.asarray(windows[0]["a"])).all()


def test_interhuman_without_conversion_json_keeps_the_relative_placement(source, tmp_path):
    tmp, export, orig = source
    ih = tmp / "ih_plain"
    to_interhuman(export, ih)
    (ih / "conversion.json").unlink()  # InterHuman as downloaded: no transform back to our world
    import_interhuman(ih, tmp_path / "out")
    a, b = orig["hug"]
    ja, jb = _joints(tmp_path / "out", "hug")
    ra, rb = resample_joints(a, FPS, INTERHUMAN_FPS), resample_joints(b, FPS, INTERHUMAN_FPS)
    assert (ja[:, 15, 1] > ja[:, 0, 1]).all() and (jb[:, 15, 1] > jb[:, 0, 1]).all()  # Z up became Y up
    # InterHuman's frame is person a's canonical one (turned, moved, floored): one rigid motion for the pair
    ref = np.concatenate([ra, rb])
    both = _align_yaw(np.concatenate([ja, jb]), ref)
    assert np.abs(both - ref).max() < MM


def test_humanml3d_round_trip_within_1mm(source):
    tmp, export, orig = source
    to_humanml3d(export, tmp / "hml")
    res = import_humanml3d(tmp / "hml", tmp / "from_hml")
    assert res["imported"] == 2 and res["skipped"] == {}
    out = tmp / "from_hml"
    _verify_ok(out)
    assert json.loads((out / "manifest.json").read_text())["fps"] == HUMANML3D_FPS
    for sid, pair in orig.items():
        for got, want in zip(_joints(out, sid), pair):
            want = resample_joints(want, FPS, HUMANML3D_FPS)[: len(got)]  # new_joints drops the last frame
            assert len(got) == len(want) >= 2
            # HumanML3D keeps each person in its own canonical frame: equal up to a turn and a shift (floored)
            assert np.abs(_align_yaw(got, want) - want).max() < MM
    texts = json.loads((out / "sequences" / "turn" / "text.json").read_text())["texts"]
    assert texts == [TEXT]


def test_humanml3d_unpaired_motion_is_skipped_with_reason(source, tmp_path):
    _, export, _ = source
    hml = tmp_path / "hml"
    to_humanml3d(export, hml)
    (hml / "new_joints" / "turn_b.npy").unlink()
    (hml / "new_joints" / "solo.npy").write_bytes((hml / "new_joints" / "hug_a.npy").read_bytes())
    res = import_humanml3d(hml, tmp_path / "out")
    assert res["imported"] == 1
    assert set(res["skipped"]) == {"turn_a", "solo"} and all(r.startswith("unpaired") for r in res["skipped"].values())


def test_not_in_the_layout_is_a_clear_error(tmp_path):
    (tmp_path / "empty").mkdir()
    for fn, need in ((import_humanml3d, "new_joints"), (import_interhuman, "motions_processed/person1")):
        with pytest.raises(FormatError, match=need) as e:
            fn(tmp_path / "empty", tmp_path / "out")
        assert e.value.fix
        with pytest.raises(FormatError, match="is not a folder"):
            fn(tmp_path / "missing", tmp_path / "out")


def test_symlink_out_of_the_folder_is_refused(tmp_path):
    src = tmp_path / "hml"
    (src / "new_joints").mkdir(parents=True)
    outside = tmp_path / "secret.npy"
    np.save(outside, np.zeros((5, 22, 3), np.float32))
    for p in ("a", "b"):
        (src / "new_joints" / f"x_{p}.npy").symlink_to(outside)
    with pytest.raises(FormatError, match="no HumanML3D sequence") as e:
        import_humanml3d(src, tmp_path / "out")
    assert "leads out of the folder" in str(e.value)


@settings(max_examples=40, deadline=None)
@given(data=st.one_of(st.binary(max_size=300), st.sampled_from([b"\x93NUMPY", b""])),
       shape=st.sampled_from([(4, 22, 3), (4, 492), (1, 22, 3), (4, 21, 3)]), poison=st.booleans())  # fmt: skip
def test_hostile_motion_files_are_counted_skips(tmp_path_factory, data, shape, poison):
    tmp = tmp_path_factory.mktemp("hostile")
    ih, hml = tmp / "ih", tmp / "hml"
    for k in (1, 2):
        (ih / "motions_processed" / f"person{k}").mkdir(parents=True)
    (hml / "new_joints").mkdir(parents=True)
    arr = np.zeros(shape, np.float32)
    if poison:
        arr.flat[0] = np.nan
    np.save(ih / "motions_processed" / "person1" / "s.npy", arr)
    (ih / "motions_processed" / "person2" / "s.npy").write_bytes(data)
    np.save(hml / "new_joints" / "s_a.npy", arr)
    (hml / "new_joints" / "s_b.npy").write_bytes(data)
    for fn, src in ((import_interhuman, ih), (import_humanml3d, hml)):
        with pytest.raises(FormatError, match="could be imported") as e:
            fn(src, tmp / "out")
        assert "1 skipped" in str(e.value)


def test_oversized_file_is_a_counted_skip(tmp_path, monkeypatch):
    from dualhuman_builder.export import importers

    monkeypatch.setattr(importers, "MAX_MOTION_BYTES", 1000)
    (tmp_path / "hml" / "new_joints").mkdir(parents=True)
    for p in ("a", "b"):
        np.save(tmp_path / "hml" / "new_joints" / f"s_{p}.npy", np.zeros((30, 22, 3), np.float32))
    with pytest.raises(FormatError, match="more than the 1000 allowed"):
        import_humanml3d(tmp_path / "hml", tmp_path / "out")


def test_cli_import_commands(source, tmp_path):
    _, export, _ = source
    to_humanml3d(export, tmp_path / "hml")
    to_interhuman(export, tmp_path / "ih")
    runner = CliRunner()
    for cmd, src in (("import-humanml3d", "hml"), ("import-interhuman", "ih")):
        r = runner.invoke(main, ["export", cmd, str(tmp_path / src), str(tmp_path / f"out_{src}")])
        assert r.exit_code == 0, r.output
        assert "2 sequence(s) imported" in r.output
        assert not verify_export(tmp_path / f"out_{src}")
        h = runner.invoke(main, ["export", cmd, "--help"])
        assert "Example:" in h.output
    r = runner.invoke(main, ["export", "import-humanml3d", str(tmp_path / "ih"), str(tmp_path / "x")])
    assert r.exit_code != 0 and "new_joints" in r.output


def test_npy_header_claiming_a_huge_array_is_a_counted_skip(tmp_path):
    src = tmp_path / "hml" / "new_joints"
    src.mkdir(parents=True)
    np.save(src / "s_a.npy", np.zeros((30, 22, 3), np.float32))
    header = "{'descr': '<f4', 'fortran_order': False, 'shape': (10000000000, 22, 3), }"
    (src / "s_b.npy").write_bytes(b"\x93NUMPY\x01\x00" + len(header.ljust(118) + "\n").to_bytes(2, "little")
                                  + (header.ljust(118) + "\n").encode() + b"\0" * 64)  # fmt: skip
    with pytest.raises(FormatError, match="could be imported") as e:
        import_humanml3d(tmp_path / "hml", tmp_path / "out")
    assert "header claims" in str(e.value)


BAD_TRANSFORM = b'{"layout": "interhuman", "sequences": {"s": {"transform": {"yaw0": "x", "translation": 5}}}}'


@settings(max_examples=30, deadline=None)
@given(which=st.sampled_from(["conversion.json", "annots/s.txt", "train.txt", "ignore_list.txt"]),
       data=st.one_of(st.binary(max_size=200), st.sampled_from([b"[" * 100_000, BAD_TRANSFORM, b"\xff\xfe s"]),
       st.text(max_size=100).map(str.encode)))  # fmt: skip
def test_hostile_side_files_import_or_fail_clearly(tmp_path_factory, which, data):
    tmp = tmp_path_factory.mktemp("side")
    ih = tmp / "ih"
    a, b = face_to_face(T=6, seed=1)
    for k, j in ((1, a), (2, b)):
        (ih / "motions_processed" / f"person{k}").mkdir(parents=True)
        raw = np.zeros((len(j), 492), np.float32)
        raw[:, :66] = (j @ np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]).T).reshape(len(j), 66)
        np.save(ih / "motions_processed" / f"person{k}" / "s.npy", raw)
    (ih / which).parent.mkdir(parents=True, exist_ok=True)
    (ih / which).write_bytes(data)
    try:
        res = import_interhuman(ih, tmp / "out")
        event("imported" if res["imported"] else "skipped")
    except FormatError as e:
        assert e.fix or "could be imported" in str(e)
        event("refused")
        return
    assert res["imported"] + len(res["skipped"]) == 1
    if res["imported"]:
        _verify_ok(tmp / "out")

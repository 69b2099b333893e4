"""Retargeting to a format's reference skeleton (``retarget=`` of the converters, ``--retarget``): bone
lengths equal to the reference on every frame, bone directions unchanged, feet on the floor, HumanML3D's
recovery paths (recomputed here from its published formulas, and run from a HumanML3D checkout when
one is present) rebuilding the retargeted joints, ``none`` byte for byte unchanged, and a clear refusal
where no reference skeleton is published (InterHuman)."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st
from synthetic_pairs import body, face_to_face, write_export
from test_humanml3d_upstream import _body, _recover_from_rot

from dualhuman_builder.body.joints import JOINT22_PARENTS
from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.export.convert import (
    read_interhuman,
    to_humanml3d,
    to_interhuman,
)
from dualhuman_builder.export.features import REST_DIRECTIONS
from dualhuman_builder.export.retarget import (
    HUMANML3D_BONE_LENGTHS,
    bone_lengths,
    reference_lengths,
    retarget_joints,
)

MM = 1e-3
PARENTS = np.asarray(JOINT22_PARENTS)
#: A HumanML3D checkout (EricGuo5513/HumanML3D): the tests that run its own code skip without one.
HUMANML3D_CHECKOUT = Path(os.environ.get("DUALHUMAN_HUMANML3D_CHECKOUT", "/work/scratch/HumanML3D"))


def _directions(j: np.ndarray) -> np.ndarray:
    bones = j[:, 1:] - j[:, PARENTS[1:]]
    return bones / np.linalg.norm(bones, axis=-1, keepdims=True)


def _turning_pair(T: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Two rigid-limbed bodies (HumanML3D-like proportions, not its lengths) turning in place through
    360 degrees, the second facing the first."""
    yaw = np.linspace(0.0, 2 * np.pi, T)
    return _body(T, yaw, np.zeros((T, 3)), seed=1), _body(T, np.pi - yaw, np.tile([0.0, 0.0, 0.8], (T, 1)), seed=2)


@pytest.fixture(scope="module")
def export(tmp_path_factory):
    root = tmp_path_factory.mktemp("rt")
    a, b = _turning_pair()
    c, d = face_to_face(T=40, turns=0.5)
    return write_export(root / "ex", {"turn": (a, b, "train"), "f2f": (c, d, "test")}, fps=20.0)


@given(seed=st.integers(0, 10_000), turns=st.floats(-2.0, 2.0), scale=st.floats(0.4, 2.5))
def test_lengths_equal_the_reference_and_directions_are_kept(seed, turns, scale):
    j = body(12, seed, turns) * scale
    out, rep = retarget_joints(j, HUMANML3D_BONE_LENGTHS)
    assert np.abs(bone_lengths(out) - HUMANML3D_BONE_LENGTHS[1:]).max() < 1e-9
    assert np.abs(_directions(out) - _directions(j)).max() < 1e-9
    assert abs(out[..., 1].min() - j[..., 1].min()) < 1e-9  # the lowest joint stays on the floor
    assert rep["ratio_min"] <= rep["ratio_mean"] <= rep["ratio_max"] and len(rep["ratios"]) == 21


def test_a_scaled_reference_body_comes_back_exactly():
    """A body with the reference's proportions at another size: retargeting scales the whole motion,
    root path included, about its frame-0 floor point, so planted feet stay planted."""
    rest = np.zeros((22, 3))
    rest[0] = [0.0, 0.93, 0.0]
    for k in range(1, 22):
        rest[k] = rest[PARENTS[k]] + HUMANML3D_BONE_LENGTHS[k] * REST_DIRECTIONS[k]
    T = 30
    walk = rest + np.linspace(0, 1.2, T)[:, None, None] * [0.0, 0.0, 1.0] + [0.5, 0.0, -1.0]
    walk[..., 1] -= walk[..., 1].min()
    big = (walk - walk[0, 0] * [1, 0, 1]) * 1.3 + walk[0, 0] * [1, 0, 1]
    out, rep = retarget_joints(big, HUMANML3D_BONE_LENGTHS)
    assert abs(rep["root_scale"] - 1 / 1.3) < 1e-12 and abs(rep["ratio_max"] - 1 / 1.3) < 1e-12
    np.testing.assert_allclose(out, walk, atol=1e-12)


def test_humanml3d_output_has_reference_lengths_and_recovers(export, tmp_path):
    doc = to_humanml3d(export, tmp_path / "h", retarget="humanml3d")
    dest = Path(doc["dest"])
    for name in ("turn_a", "turn_b", "f2f_a", "f2f_b"):
        joints = np.load(dest / "new_joints" / f"{name}.npy").astype(np.float64)
        assert np.abs(bone_lengths(joints) - HUMANML3D_BONE_LENGTHS[1:]).max() < 1e-6
        f = np.load(dest / "new_joint_vecs" / f"{name}.npy").astype(np.float64)
        rot = _recover_from_rot(f, np.repeat(joints[:1], len(f), axis=0))  # offsets from frame 0, as HumanML3D
        assert np.linalg.norm(rot - joints, axis=-1).max() < 3 * MM
        # recover_from_ric: root from the integrated yaw and velocity, joints 1..21 rotated back
        psi = np.concatenate([[0.0], -2.0 * np.cumsum(f[:-1, 0])])
        vel = np.zeros((len(f), 3))
        vel[1:, [0, 2]] = f[:-1, 1:3]
        c, s = np.cos(psi), np.sin(psi)
        root = np.cumsum(np.stack([c * vel[:, 0] + s * vel[:, 2], 0 * c, -s * vel[:, 0] + c * vel[:, 2]], -1), axis=0)
        ric = f[:, 4:67].reshape(-1, 21, 3)
        cc, ss = c[:, None], s[:, None]
        rel = np.stack([cc * ric[..., 0] + ss * ric[..., 2], ric[..., 1], -ss * ric[..., 0] + cc * ric[..., 2]], -1)
        assert np.abs(rel + root[:, None] - joints[:, 1:]).max() < 0.1 * MM
    rt = doc["retarget"]
    assert rt["skeleton"] == "humanml3d" and rt["persons"] == 4 and len(rt["per_bone"]) == 21
    assert rt["bone_lengths"] == HUMANML3D_BONE_LENGTHS[1:].tolist()
    per = doc["sequences"]["turn"]["retarget"]["a"]
    assert per["ratio_min"] <= per["ratio_mean"] <= per["ratio_max"] and per["root_scale"] > 0
    assert json.loads((dest / "conversion.json").read_text())["retarget"]["ratio_max"] == rt["ratio_max"]


def test_interhuman_output_has_reference_lengths_and_keeps_directions(export, tmp_path):
    doc = to_interhuman(export, tmp_path / "i", retarget="humanml3d")
    plain = to_interhuman(export, tmp_path / "i0")
    for sid in ("turn", "f2f"):
        new, old = read_interhuman(doc["dest"], sid), read_interhuman(plain["dest"], sid)
        for p in range(2):
            assert np.abs(bone_lengths(new[p]) - HUMANML3D_BONE_LENGTHS[1:]).max() < 1e-5  # float32 world metres
            assert np.abs(_directions(new[p]) - _directions(old[p])).max() < 1e-4
        assert doc["sequences"][sid]["retarget"]["b"]["ratio_max"] > 0
    assert doc["retarget"]["skeleton"] == "humanml3d" and plain["retarget"] == {"skeleton": "none"}


@pytest.mark.parametrize("convert", [to_humanml3d, to_interhuman])
def test_retarget_none_is_byte_for_byte_unchanged(export, tmp_path, convert):
    convert(export, tmp_path / "default")
    convert(export, tmp_path / "none", retarget="none")
    files = sorted(p.relative_to(tmp_path / "default") for p in (tmp_path / "default").rglob("*.npy"))
    assert files and files == sorted(p.relative_to(tmp_path / "none") for p in (tmp_path / "none").rglob("*.npy"))
    for rel in files:
        assert (tmp_path / "default" / rel).read_bytes() == (tmp_path / "none" / rel).read_bytes(), rel


@pytest.mark.parametrize("convert", [to_humanml3d, to_interhuman])
def test_interhuman_skeleton_is_refused_before_anything_is_written(export, tmp_path, convert):
    with pytest.raises(DualhumanError, match="no reference skeleton for InterHuman") as e:
        convert(export, tmp_path / "x", retarget="interhuman")
    assert e.value.fix and "humanml3d" in e.value.fix and not (tmp_path / "x").exists()
    with pytest.raises(DualhumanError, match="unknown retarget"):
        convert(export, tmp_path / "x", retarget="smpl")
    with pytest.raises(DualhumanError, match="21 .* positive"):
        convert(export, tmp_path / "x", retarget=np.ones(20))


def test_own_lengths_can_be_given(export, tmp_path):
    lengths = HUMANML3D_BONE_LENGTHS[1:] * 1.1
    assert np.array_equal(reference_lengths(lengths)[1:], lengths)
    doc = to_humanml3d(export, tmp_path / "h", retarget=lengths)
    joints = np.load(Path(doc["dest"]) / "new_joints" / "turn_b.npy").astype(np.float64)
    assert doc["retarget"]["skeleton"] == "custom" and np.abs(bone_lengths(joints) - lengths).max() < 1e-6


def test_cli_retarget_prints_the_bone_length_change(export, tmp_path):
    from dualhuman_builder.cli import main

    runner = CliRunner()
    r = runner.invoke(main, ["export", "humanml3d", str(export), str(tmp_path / "h"), "--retarget", "humanml3d"])
    assert r.exit_code == 0, r.output
    assert "retargeted 4 person(s) to the humanml3d skeleton: bone length x" in r.output and "right_knee" in r.output
    r = runner.invoke(main, ["export", "interhuman", str(export), str(tmp_path / "i"), "--retarget", "interhuman"])
    assert r.exit_code != 0 and "no reference skeleton for InterHuman" in r.output
    r = runner.invoke(main, ["export", "interhuman", str(export), str(tmp_path / "i2")])
    assert r.exit_code == 0 and "retargeted" not in r.output


# --- HumanML3D's own files and code, from a checkout (skipped without one)
needs_checkout = pytest.mark.skipif(not (HUMANML3D_CHECKOUT / "HumanML3D/new_joints/012314.npy").is_file(),
                                    reason=f"no HumanML3D checkout at {HUMANML3D_CHECKOUT} "
                                           "(set DUALHUMAN_HUMANML3D_CHECKOUT)")  # fmt: skip


@needs_checkout
def test_reference_lengths_are_humanml3d_shipped_skeleton():
    joints = np.load(HUMANML3D_CHECKOUT / "HumanML3D/new_joints/012314.npy").astype(np.float64)
    assert np.abs(bone_lengths(joints) - HUMANML3D_BONE_LENGTHS[1:]).max() < 2e-6


@needs_checkout
def test_upstream_recover_from_rot_and_ric_on_retargeted_output(export, tmp_path):
    torch = pytest.importorskip("torch")
    np.float = float  # the upstream code predates NumPy 1.24
    saved = list(sys.path)
    sys.path.insert(0, str(HUMANML3D_CHECKOUT))
    try:
        from common.quaternion import qinv, qrot, quaternion_to_cont6d
        from common.skeleton import Skeleton
        from paramUtil import t2m_kinematic_chain, t2m_raw_offsets
    finally:  # the checkout's top-level names (common, paramUtil) must not shadow anything later
        sys.path[:] = saved
        for name in [m for m in sys.modules if m.split(".")[0] in ("common", "paramUtil")]:
            del sys.modules[name]
    nb = json.loads((HUMANML3D_CHECKOUT / "motion_representation.ipynb").read_text())
    code = next("".join(c["source"]) for c in nb["cells"] if "def recover_from_rot" in "".join(c["source"]))
    ns = {"torch": torch, "qinv": qinv, "qrot": qrot, "quaternion_to_cont6d": quaternion_to_cont6d}
    exec(code, ns)  # noqa: S102 - the notebook's recover_from_ric / recover_from_rot, run as they are
    dest = Path(to_humanml3d(export, tmp_path / "h", retarget="humanml3d")["dest"])
    for f in sorted((dest / "new_joint_vecs").glob("*.npy")):
        vec = torch.from_numpy(np.load(f)).float()
        joints = np.load(dest / "new_joints" / f.name)
        skel = Skeleton(torch.from_numpy(t2m_raw_offsets).float(), t2m_kinematic_chain, "cpu")
        skel.get_offsets_joints(torch.from_numpy(joints[0]).float())
        rot = ns["recover_from_rot"](vec, 22, skel).numpy()
        ric = ns["recover_from_ric"](vec, 22).numpy()
        assert np.linalg.norm(rot - joints, axis=-1).max() < 3 * MM, f.name
        assert np.linalg.norm(ric - joints, axis=-1).max() < 0.1 * MM, f.name

"""The InterHuman conversion as InterGen's own code reads it (tr3e/InterGen ``datasets/interhuman.py``,
``utils/utils.py``, ``common/quaternion.py``), recomputed here from the published formulas: the 6D
layout its ``_swap`` mirroring assumes, its per-person canonicalisation through ``qbetween`` (float32,
NaN for exactly opposite vectors), the relative placement of person 2, read-back, splits of any
size, and the refusal to write non-finite values. Exports are written by hand from synthetic joints
(no body model needed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from synthetic_pairs import FPS, body, write_export
from synthetic_pairs import face_to_face as _face_to_face
from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.export.convert import (
    read_interhuman,
    rotations_6d_rows,
    rotations_from_6d_rows,
    to_humanml3d,
    to_interhuman,
)

MM = 1e-3
# --- InterGen's definitions, written out (utils/utils.py)
RIGHT_CHAIN = np.array([2, 5, 8, 11, 14, 17, 19, 21])
LEFT_CHAIN = np.array([1, 4, 7, 10, 13, 16, 18, 20])
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # trans_matrix


# ----------------------------------------------------------------------------- InterGen, recomputed
def _qbetween32(v0: np.ndarray, v1: np.ndarray) -> np.ndarray:
    """InterGen's ``qbetween_np``: in float32, ``normalize(w = |v0||v1| + v0.v1, v0 x v1)``."""
    v0, v1 = np.float32(v0), np.float32(v1)
    w = np.sqrt((v0**2).sum(-1, keepdims=True) * (v1**2).sum(-1, keepdims=True)) + (v0 * v1).sum(-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = np.concatenate([w, np.cross(v0, v1)], -1)
        return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _qrot(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    u, w = q[..., 1:], q[..., :1]
    uv = np.cross(u, v)
    return v + 2 * (w * uv + np.cross(u, uv))


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w0, x0, y0, z0 = np.moveaxis(a, -1, 0)
    w1, x1, y1, z1 = np.moveaxis(b, -1, 0)
    return np.stack([w0 * w1 - x0 * x1 - y0 * y1 - z0 * z1, w0 * x1 + x0 * w1 + y0 * z1 - z0 * y1,
                     w0 * y1 - x0 * z1 + y0 * w1 + z0 * x1, w0 * z1 + x0 * y1 - y0 * x1 + z0 * w1], -1)  # fmt: skip


def _swap(raw: np.ndarray) -> np.ndarray:
    """InterGen's left/right mirroring of the columns it reads: positions x -> -x with the body chains
    swapped, 6D slots 1, 2, 4 negated with the chains swapped (rotation i is joint i + 1)."""
    T = len(raw)
    pos = raw[:, :66].reshape(T, 22, 3).copy()
    pos[..., 0] *= -1
    pos[:, np.r_[RIGHT_CHAIN, LEFT_CHAIN]] = pos[:, np.r_[LEFT_CHAIN, RIGHT_CHAIN]]
    rot = raw[:, 186:312].reshape(T, 21, 6).copy()
    rot[..., [1, 2, 4]] *= -1
    rot[:, np.r_[RIGHT_CHAIN, LEFT_CHAIN] - 1] = rot[:, np.r_[LEFT_CHAIN, RIGHT_CHAIN] - 1]
    return np.concatenate([pos.reshape(T, -1), rot.reshape(T, -1)], 1)


def _process(motion: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """InterGen's ``process_motion_np`` (positions part): Z up -> Y up, floored, root XZ of frame 0 at
    the origin, turned so the hip facing of frame 0 is +Z. Returns (positions, root quat, root xz)."""
    pos = np.einsum("mn,tjn->tjm", Z_UP_TO_Y_UP, np.float32(motion[:, :66]).reshape(-1, 22, 3)).astype(np.float32)
    pos[..., 1] -= pos.min(axis=(0, 1))[1]
    init_xz = pos[0, 0] * np.array([1, 0, 1], dtype=np.float32)
    pos = pos - init_xz
    across = pos[0, 2] - pos[0, 1]
    across = across / np.sqrt((across**2).sum())
    forward = np.cross(np.array([0, 1, 0]), across)
    forward = forward / np.sqrt((forward**2).sum())
    q = _qbetween32(forward[None], np.array([[0.0, 0.0, 1.0]]))
    return _qrot(np.broadcast_to(q, pos.shape[:-1] + (4,)), pos), q, init_xz[None]


def _intergen_sample(raw1: np.ndarray, raw2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both persons' positions as InterGen's ``__getitem__`` puts them: each canonicalised, then
    person 2 placed back relative to person 1 (``rigid_transform`` of the relative yaw and XZ)."""
    p1, q1, x1 = _process(raw1)
    p2, q2, x2 = _process(raw2)
    r = _qmul(q2, q1 * [1, -1, -1, -1])
    angle = np.arctan2(r[:, 2], r[:, 0])[0]
    xz = _qrot(q1, x2 - x1)[0, [0, 2]]
    back = np.broadcast_to([np.cos(angle), 0.0, -np.sin(angle), 0.0], p2.shape[:-1] + (4,))  # inverse turn
    p2 = _qrot(back, p2)
    p2[..., [0, 2]] += xz
    return p1, p2


def _rotations(raw: np.ndarray) -> np.ndarray:
    """The 21 stored rotations, read as InterHuman stores them (``rot_mat[..., :2]`` flattened by row)."""
    return raw[:, 186:312].reshape(len(raw), 21, 3, 2)


def _orthonormality_error(cols: np.ndarray) -> float:
    gram = np.swapaxes(cols, -1, -2) @ cols
    return float(np.abs(gram - np.eye(2)).max())


def _raws(dest: Path, sid: str) -> list[np.ndarray]:
    return [np.load(dest / f"motions_processed/person{k}/{sid}.npy", allow_pickle=False) for k in (1, 2)]


# ----------------------------------------------------------------------------- tests
@pytest.fixture(scope="module")
def face_to_face(tmp_path_factory):
    """A face-to-face pair (b exactly -Z), a pair turning through 360 degrees, converted to InterHuman."""
    tmp = tmp_path_factory.mktemp("upstream")
    a, b = _face_to_face()
    ta, tb = _face_to_face(T=31, seed=5, turns=1.0)
    export = write_export(tmp / "ds", {"hug": (a, b, "train"), "turn": (ta, tb, "test")})
    return export, to_interhuman(export, tmp / "ih")


def test_mirroring_yields_rotations_and_mirrors_our_rotations(face_to_face):
    _, doc = face_to_face
    dest = Path(doc["dest"])
    for sid in ("hug", "turn"):
        for raw in _raws(dest, sid):
            cols = _rotations(raw)
            assert _orthonormality_error(cols) < 1e-5
            mats = rotations_from_6d_rows(raw[:, 186:312].reshape(-1, 21, 6))
            assert np.allclose(np.linalg.det(mats), 1.0) and np.allclose(mats[..., :2], cols, atol=1e-6)
            assert np.allclose(rotations_6d_rows(mats), raw[:, 186:312].reshape(-1, 21, 6), atol=1e-6)
            swapped = _swap(raw)[:, 66:].reshape(len(raw), 21, 3, 2)
            assert _orthonormality_error(swapped) < 1e-5
            # x-reflection of a rotation is M R M, M = diag(-1, 1, 1): InterGen's sign flips at 1, 2, 4
            m = np.diag([-1.0, 1.0, 1.0])
            full = np.concatenate([cols, np.cross(cols[..., 0], cols[..., 1])[..., None]], -1)
            np.testing.assert_allclose(swapped[:, LEFT_CHAIN - 1], (m @ full @ m)[:, RIGHT_CHAIN - 1, :, :2], atol=1e-6)


def test_face_to_face_pair_gives_finite_intergen_samples(face_to_face):
    _, doc = face_to_face
    dest = Path(doc["dest"])
    feats = [np.load(dest / f"features/p{k}/hug.npy", allow_pickle=False) for k in (1, 2)]
    r1, r2 = _raws(dest, "hug")
    for x, y in ((r1, r2), (r2, r1), (_swap(r1), _swap(r2)), (_swap(r2), _swap(r1))):
        p1, p2 = _intergen_sample(x, y)
        assert np.isfinite(p1).all() and np.isfinite(p2).all()
    assert doc["sequences"]["hug"]["transform"]["raw_yaw"] == pytest.approx(2e-3)
    assert doc["sequences"]["turn"]["transform"]["raw_yaw"] == pytest.approx(2e-3)  # b faces -Z there too
    assert doc["raw_yaw_turned"] == ["hug", "turn"]
    # the turn of the raw files changes nothing InterGen computes: person 2 lands where our features put it
    p1, p2 = _intergen_sample(r1, r2)
    ours = [f[:, :66].reshape(-1, 22, 3) for f in feats]
    assert np.abs(p1[:-1, :, [0, 2]] - ours[0][..., [0, 2]]).max() < 1e-4
    assert np.abs(p2[:-1, :, [0, 2]] - ours[1][..., [0, 2]]).max() < 1e-4
    np.testing.assert_array_equal(feats[0][:, 132:258], r1[:-1, 186:312])  # InterGen passes rotations through


def test_read_back_recovers_our_joints(face_to_face):
    export, doc = face_to_face
    from dualhuman_builder.export.features import resample_joints

    for sid in ("hug", "turn"):
        m = np.load(export / f"sequences/{sid}/motion.npz")
        want = np.stack([resample_joints(m[f"{p}.joints"], FPS, 30.0) for p in "ab"])
        assert np.abs(read_interhuman(doc["dest"], sid) - want).max() < MM


def test_one_sequence_export_writes_loadable_splits(tmp_path):
    a, b = _face_to_face()
    export = write_export(tmp_path / "ds", {"only": (a, b, "train")})
    for convert, name in ((to_interhuman, "only"), (to_humanml3d, "only_a")):
        doc = convert(export, tmp_path / convert.__name__)
        dest = Path(doc["dest"])
        for split in ("train", "val", "test"):  # InterGen keeps names listed as name + "\n"; T2M raises on none
            lines = (dest / f"{split}.txt").read_text(encoding="utf-8")
            assert f"{name}\n" in lines.splitlines(keepends=True)
        assert doc["filled_splits"] == ["test", "val"] and "do not report figures" in doc["notes"][0]
        assert doc["counts"]["test"] == doc["counts"]["val"] == doc["counts"]["train"] > 0
    from click.testing import CliRunner

    from dualhuman_builder.cli import main

    r = CliRunner().invoke(main, ["export", "interhuman", str(export), str(tmp_path / "cli")])
    assert r.exit_code == 0 and "note:" in r.stderr and "do not report figures" in r.stderr, r.output


@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")
@pytest.mark.parametrize("convert, fps, where",
                         [(to_interhuman, 30.0, "p2/wild.npy"), (to_humanml3d, 20.0, "wild_b.npy")])  # fmt: skip
def test_non_finite_output_is_refused(tmp_path, convert, fps, where):
    a, b = _face_to_face(T=20)
    b = b.copy()
    b[:, 15, 0] = np.where(np.arange(20) % 2, 3e38, -3e38)  # finite in float32; its steps are not
    export = write_export(tmp_path / "ds", {"wild": (a, b, "train")}, fps=fps)
    with pytest.raises(DualhumanError, match=rf"refusing to write .*{where}.*NaN or inf") as e:
        convert(export, tmp_path / "out")
    assert e.value.fix


def test_intergen_mirroring_equals_converting_the_mirrored_pair(tmp_path):
    from dualhuman_builder.export.features import mirror_joints

    a, b = _face_to_face(T=31, seed=7, turns=1.0)
    export = write_export(tmp_path / "ds", {"p": (a, b, "train")})
    mirrored = write_export(tmp_path / "dm", {"p": (mirror_joints(a), mirror_joints(b), "train")})
    ours = _raws(Path(to_interhuman(export, tmp_path / "o")["dest"]), "p")
    theirs = _raws(Path(to_interhuman(mirrored, tmp_path / "m")["dest"]), "p")
    for raw, raw_m in zip(ours, theirs):
        np.testing.assert_allclose(_swap(raw)[:, 66:], raw_m[:, 186:312], atol=1e-5)


_BODY = body(3, 11)


@given(st.one_of(st.floats(np.pi - 2e-3, np.pi + 2e-3), st.floats(-4.0, 4.0), st.just(np.pi), st.just(-np.pi)))
def test_no_facing_makes_intergen_non_finite(yaw):
    from dualhuman_builder.export.convert import _intergen_raw, _intergen_yaw_nudge
    from dualhuman_builder.export.features import rot_y

    a = _BODY - _BODY[0, 0] * [1, 0, 1]
    b = (_BODY - _BODY[0, 0] * [1, 0, 1]) @ rot_y(yaw).T + [0.2, 0.0, 0.8]
    nudge = _intergen_yaw_nudge(a, b)
    for c in (a, b):
        raw = _intergen_raw(c, nudge)
        for motion in (raw, _swap(raw)):
            pos, q, _ = _process(motion)
            assert np.isfinite(q).all() and np.isfinite(pos).all()


@given(st.lists(st.floats(-np.pi, np.pi), min_size=3, max_size=3))
def test_6d_rows_round_trip_and_mirror(angles):
    from scipy.spatial.transform import Rotation

    mat = Rotation.from_euler("xyz", angles).as_matrix()
    d6 = rotations_6d_rows(mat)
    np.testing.assert_allclose(rotations_from_6d_rows(d6), mat, atol=1e-9)
    m = np.diag([-1.0, 1.0, 1.0])
    flipped = d6 * [1, -1, -1, 1, -1, 1]  # InterGen's swap_left_right_rot negates slots 1, 2, 4
    np.testing.assert_allclose(flipped, rotations_6d_rows(m @ mat @ m), atol=1e-12)


def test_a_later_frame_facing_minus_z_is_avoided_too(tmp_path):
    """InterGen canonicalises long motions at a random window start: any frame may be the first."""
    a, b = _face_to_face(T=12)
    b = np.repeat(b[:1], 12, axis=0)  # stands still, facing exactly -Z ...
    turn = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # b faces +X on frames 0..5
    b[:6] = (b[:6] - b[:6, :1]) @ turn.T + b[:6, :1]
    doc = to_interhuman(write_export(tmp_path / "ds", {"late": (a, b, "train")}), tmp_path / "ih")
    assert doc["sequences"]["late"]["transform"]["raw_yaw"] != 0.0
    r1, r2 = _raws(Path(doc["dest"]), "late")
    for start in range(len(r1) - 2):
        p1, p2 = _intergen_sample(r1[start:], r2[start:])
        assert np.isfinite(p1).all() and np.isfinite(p2).all(), start

import numpy as np
import pytest

from dualhuman_builder.errors import FormatError, FormatVersionError
from dualhuman_builder.fileio import load_npz, save_npz
from dualhuman_builder.tracks import BodyTrack, InteractionSequence, SkeletonTrack


def _skeleton(T=5, S=3, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(T, S, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return dict(
        segment_names=("Pelvis", "L5", "Head")[:S],
        orientations=q,
        positions=rng.normal(size=(T, S, 3)),
        device_time_ns=np.arange(T) * 4_166_667 + 10**12,
        host_time_ns=np.arange(T) * 4_166_667 + 5 * 10**9,
    )


def test_skeleton_track_round_trip(tmp_path):
    kw = _skeleton()
    valid = np.ones((5, 3), bool)
    valid[2, 1] = False
    kw["orientations"][2, 1] = np.nan  # invalid entries may hold anything
    tr = SkeletonTrack(**kw, orientation_valid=valid, actor="alice", fps=240.0, meta={"source": "mvn"})
    tr.save(tmp_path / "s.npz")
    back = SkeletonTrack.load(tmp_path / "s.npz")
    assert back.segment_names == ("Pelvis", "L5", "Head") and back.actor == "alice" and back.fps == 240.0
    assert back.meta == {"source": "mvn"}
    for name in ("orientations", "positions", "device_time_ns", "host_time_ns", "orientation_valid", "position_valid"):
        np.testing.assert_array_equal(getattr(back, name), getattr(tr, name))
    assert back.device_time_ns.dtype == np.int64 and not back.orientation_valid[2, 1]
    assert back.segment_index("Head") == 2
    with pytest.raises(KeyError, match="no segment 'Foot'"):
        back.segment_index("Foot")
    with pytest.raises(ValueError):
        back.positions[0, 0, 0] = 1.0  # read-only


def test_skeleton_track_rejects_bad_values():
    kw = _skeleton()
    kw["orientations"][3, 2] = np.nan
    with pytest.raises(ValueError, match="'Head' at frame 3 is marked valid but not finite"):
        SkeletonTrack(**kw)
    kw = _skeleton()
    kw["orientations"][1, 0] *= 2.0
    with pytest.raises(ValueError, match="'Pelvis' at frame 1 is not a unit quaternion"):
        SkeletonTrack(**kw)
    kw = _skeleton()
    kw["host_time_ns"][4] = kw["host_time_ns"][3] - 1
    with pytest.raises(ValueError, match="host_time_ns goes backwards at frame 4"):
        SkeletonTrack(**kw)
    kw = _skeleton()
    with pytest.raises(ValueError, match=r"positions must have shape \(5, 3, 3\)"):
        SkeletonTrack(**{**kw, "positions": kw["positions"][:, :2]})


def _body_track(model, T=4, seed=0, actor="a"):
    rng = np.random.default_rng(seed)
    pose = rng.normal(scale=0.15, size=(T, model.num_bones, 3))
    transl = rng.normal(scale=0.5, size=(T, 3))
    return BodyTrack.from_model(model, pose, transl, model.default_shape().numpy(), fps=30.0, actor=actor)


def test_body_track_round_trip_and_derived_data(tmp_path, body_model):
    tr = _body_track(body_model)
    tr.save(tmp_path / "b.npz")
    back = BodyTrack.load(tmp_path / "b.npz")
    np.testing.assert_array_equal(back.pose, tr.pose)
    np.testing.assert_array_equal(back.transl, tr.transl)
    assert back.model == "anny" and back.model_version == body_model.version and back.fps == 30.0
    v, j = back.vertices(), back.joints()
    assert v.shape == (4, body_model.num_vertices, 3) and v.dtype == np.float32
    assert j.shape == (4, 22, 3)
    assert back.vertices() is v  # cached
    np.testing.assert_allclose(back.bone_heads()[:, 0], back.transl, atol=1e-5)  # root head = transl
    # batched computation over a subset agrees with the whole-track cache
    part = back.compute(frames=[1, 3], batch_size=1)
    np.testing.assert_allclose(part["vertices"], v[[1, 3]], atol=1e-5)
    # one frame by the model directly
    out = body_model(tr.pose[2:3], tr.shape, tr.transl[2:3])  # read-only numpy arrays are accepted
    np.testing.assert_allclose(v[2], out.vertices[0].numpy(), atol=1e-5)
    assert back.coco().shape == (4, 17, 3)


def test_body_track_rejects_nan_and_wrong_shapes(body_model):
    tr = _body_track(body_model)
    pose = np.array(tr.pose)
    pose[1, 5, 0] = np.nan
    with pytest.raises(ValueError, match=r"pose holds NaN .* \(1, 5, 0\)"):
        BodyTrack.from_model(body_model, pose, tr.transl, tr.shape, 30.0)
    with pytest.raises(ValueError, match=r"pose must have shape \(\*, 104, 3\)"):
        BodyTrack.from_model(body_model, pose[:, :50], tr.transl, tr.shape, 30.0)
    with pytest.raises(ValueError, match="fps must be positive"):
        BodyTrack.from_model(body_model, tr.pose, tr.transl, tr.shape, 0.0)


def test_interaction_sequence_round_trip(tmp_path, body_model):
    a, b = _body_track(body_model, actor="alice"), _body_track(body_model, seed=1, actor="bob")
    seq = InteractionSequence((a, b), take="T001", frame_range=(100, 104), labels=("hug",),
                              text=("Two people hug.", "A hug."), meta={"seed": 3})
    seq.save(tmp_path / "seq.npz")
    back = InteractionSequence.load(tmp_path / "seq.npz")
    assert back.take == "T001" and back.frame_range == (100, 104) and back.labels == ("hug",)
    assert back.text == ("Two people hug.", "A hug.") and back.meta == {"seed": 3}
    assert [t.actor for t in back.actors] == ["alice", "bob"]
    np.testing.assert_array_equal(back.actors[1].pose, b.pose)
    assert back.num_frames == 4 and back.fps == 30.0
    with pytest.raises(FormatError, match="holds a 'InteractionSequence', expected a 'BodyTrack'"):
        BodyTrack.load(tmp_path / "seq.npz")
    with pytest.raises(ValueError, match="different frame counts"):
        InteractionSequence((a, _body_track(body_model, T=3)))
    with pytest.raises(ValueError, match="frame_range"):
        InteractionSequence((a, b), frame_range=(0, 10))


def test_unknown_format_version_is_a_clear_error(tmp_path, body_model):
    tr = _body_track(body_model)
    tr.save(tmp_path / "b.npz")
    arrays, meta = load_npz(tmp_path / "b.npz", "BodyTrack", 1)
    meta.pop("_format_version")
    save_npz(tmp_path / "future.npz", "BodyTrack", 7, arrays, meta)
    with pytest.raises(FormatVersionError, match="BodyTrack format version 7") as e:
        BodyTrack.load(tmp_path / "future.npz")
    assert "upgrade" in e.value.fix

import numpy as np
import pytest
import roma
import torch

from dualhuman_builder.body import (
    COCO17, JOINT22_NAMES, MVN_SEGMENTS, load_regions, load_segment_mapping, shape_for_stature, stature,
    tpose, tpose_deviations,
)  # fmt: skip
from dualhuman_builder.body.shape import gender_value
from dualhuman_builder.body.topology import collision_faces, mesh_report
from dualhuman_builder.errors import BodyModelError, RigError
from dualhuman_builder.resources import RIGS_DIR


def test_model_facts_and_world_frame(body_model):
    m = body_model
    assert (m.num_vertices, m.faces.shape[0], m.num_bones) == (13718, 27420, 104)
    assert m.shape_names == ["gender", "age", "muscle", "weight", "height", "proportions"]
    rest = m.rest()
    v = rest.vertices[0].numpy()
    extent = v.max(0) - v.min(0)
    assert extent.argmax() == 1 and 1.5 < extent[1] < 1.8  # tallest along +Y: Y-up
    j = dict(zip(JOINT22_NAMES, rest.joints[0].numpy()))
    np.testing.assert_allclose(j["pelvis"], 0.0, atol=1e-6)  # root head at the origin
    assert j["left_hip"][0] > 0.05 and j["right_hip"][0] < -0.05  # left side towards +X
    assert j["head"][1] > j["neck"][1] > j["spine3"][1] > j["spine2"][1] > j["spine1"][1] > 0 > j["left_knee"][1]
    nose = dict(zip(COCO17, m.coco(rest.vertices)[0].numpy()))["nose"]
    assert nose[2] > 0.08  # faces +Z


def test_mesh_is_watertight_with_four_closed_components(body_model):
    rep = mesh_report(body_model.rest().vertices[0].numpy(), body_model.faces.numpy())
    assert rep.watertight and rep.boundary_edges == 0 and rep.nonmanifold_edges == 0
    assert rep.winding_consistent and rep.volume_m3 > 0.03  # outward winding
    assert rep.component_vertex_counts == (13348, 226, 72, 72)
    body = collision_faces(body_model.faces.numpy(), body_model.num_vertices)
    assert len(body) == 26692


def test_root_rotation_and_translation_act_in_world_frame(body_model):
    m = body_model
    rest = m.rest().vertices[0]
    rot = torch.tensor([0.0, np.pi / 2, 0.0])  # +90 degrees about +Y
    pose = torch.zeros(1, m.num_bones, 3)
    pose[0, 0] = rot
    t = torch.tensor([[0.3, 1.0, -2.0]])
    out = m(pose, None, t).vertices[0]
    expected = rest @ roma.rotvec_to_rotmat(rot).T + t
    torch.testing.assert_close(out, expected, atol=1e-5, rtol=0)
    # facing +Z turned by +90 deg about Y faces +X
    nose = m.coco(out[None])[0, 0] - t[0]
    assert nose[0] > 0.08 and abs(nose[2]) < 0.05


def test_local_rotations_are_world_aligned(body_model):
    """A bone's local rotation, with its parents at rest, rotates its subtree about its head in
    world axes: turning upperarm01.L by +90 deg about +Z swings the elbow up and over."""
    m = body_model
    b, child = m.bone_index("upperarm01.L"), m.bone_index("lowerarm01.L")
    rest = m.rest()
    pose = torch.zeros(1, m.num_bones, 3)
    R = roma.rotvec_to_rotmat(torch.tensor([0.0, 0.0, np.pi / 2]))
    pose[0, b] = roma.rotmat_to_rotvec(R)
    out = m(pose)
    h = rest.bone_heads[0]
    expected = h[b] + R @ (h[child] - h[b])
    torch.testing.assert_close(out.bone_heads[0, child], expected, atol=1e-5, rtol=0)
    # and the bone's world orientation is R times its rest orientation
    torch.testing.assert_close(out.bone_rotations[0, b], R @ rest.bone_rotations[0, b], atol=1e-5, rtol=0)


def test_local_global_round_trip(body_model):
    g = torch.Generator().manual_seed(0)
    local = roma.random_rotmat((3, body_model.num_bones), generator=g)
    glob = body_model.local_to_global(local)
    torch.testing.assert_close(body_model.global_to_local(glob), local, atol=1e-5, rtol=0)
    p = body_model.bone_index("lowerarm01.L")
    parent = int(body_model.bone_parents[p])
    torch.testing.assert_close(glob[:, p], glob[:, parent] @ local[:, p], atol=1e-6, rtol=0)


def test_batched_forward_matches_single_and_is_differentiable(body_model):
    m = body_model
    g = torch.Generator().manual_seed(1)
    pose = 0.2 * torch.randn(3, m.num_bones, 3, generator=g)
    shape = torch.rand(3, 6, generator=g)
    transl = torch.randn(3, 3, generator=g)
    batch = m(pose, shape, transl)
    for i in range(3):
        one = m(pose[i : i + 1], shape[i], transl[i : i + 1])
        torch.testing.assert_close(one.vertices[0], batch.vertices[i], atol=1e-5, rtol=0)
    pose.requires_grad_(True)
    shape.requires_grad_(True)
    m(pose, shape, transl).vertices.square().sum().backward()
    assert torch.isfinite(pose.grad).all() and pose.grad.abs().sum() > 0
    assert torch.isfinite(shape.grad).all() and shape.grad.abs().sum() > 0
    with pytest.raises(BodyModelError, match=r"pose must have shape \(B, 104, 3\)"):
        m(torch.zeros(2, 104, 4))
    with pytest.raises(BodyModelError, match="unknown shape parameters"):
        m.shape_tensor({"stature": 1.8})


def test_anny_skinning_reuses_its_kernel_and_skins_each_frame_alike(body_model):
    """anny 0.6.2 defines a new warp kernel at every skinning call; the model makes it reuse one."""
    from anny.skinning import warp_skinning

    assert hasattr(warp_skinning.get_kernel, "cache_info"), "BodyModel did not wrap anny's get_kernel"
    pose = 0.2 * torch.randn(3, body_model.num_bones, 3, generator=torch.Generator().manual_seed(3))
    body_model(pose[:1])
    before = warp_skinning.get_kernel.cache_info()
    batch = body_model(pose).vertices  # another batch size, the same kernel
    after = warp_skinning.get_kernel.cache_info()
    assert after.hits > before.hits and after.currsize == before.currsize
    for i in range(3):  # the reused kernel skins each frame of a batch as a batch of one
        torch.testing.assert_close(body_model(pose[i : i + 1]).vertices[0], batch[i], atol=1e-6, rtol=0)


def test_kinematics_only_bone_heads_equal_the_skinned_forward(body_model):
    torch.manual_seed(3)
    pose = torch.randn(5, body_model.num_bones, 3) * 0.4
    transl = torch.randn(5, 3)
    shape = torch.rand(len(body_model.shape_names))
    with torch.no_grad():
        ref = body_model.forward(pose, shape, transl)
        heads = body_model.bone_heads(pose, shape, transl)
    assert heads.shape == (5, body_model.num_bones, 3)
    assert (heads - ref.bone_heads).abs().max() < 1e-5 and (heads[:, 0] - transl).abs().max() < 1e-6
    with pytest.raises(BodyModelError, match="one shape for the whole batch"):
        body_model.bone_heads(pose, shape.expand(5, -1), transl)


def test_every_mvn_segment_maps_to_a_bone(body_model):
    mapping = load_segment_mapping()
    assert tuple(mapping.segments) == MVN_SEGMENTS and len(MVN_SEGMENTS) == 23
    bones = [b for s in mapping.segments.values() for b in s.bones]
    assert len(bones) == len(set(bones)) and set(bones) <= set(body_model.bone_names)


ADULT_SHAPES = [
    {"age": 0.67},
    {"gender": 0.0, "height": 0.9, "age": 0.67, "weight": 0.8, "muscle": 0.8},
    {"gender": 1.0, "height": 0.1, "age": 0.9, "weight": 0.2, "proportions": 0.8},
    {"gender": 1.0, "height": 0.5, "age": 0.67, "weight": 0.8, "muscle": 0.2, "proportions": 0.2},
]


@pytest.mark.parametrize("shape", ADULT_SHAPES)
def test_tpose_reproduces_mvn_segment_directions(body_model, shape):
    mapping = load_segment_mapping()
    dev = tpose_deviations(body_model, mapping, body_model.shape_tensor(shape))
    over = {s: round(d, 1) for s, d in dev.items() if d > mapping[s].tolerance_deg}
    assert not over, f"segments beyond their stated tolerance: {over}"
    # limbs are tight; left and right are not swapped (a swap would be ~180 degrees)
    assert max(dev[s] for s in MVN_SEGMENTS if "Arm" in s or "Leg" in s) <= 12.0


def test_tpose_arms_are_horizontal_and_symmetric(body_model):
    out = body_model(tpose(body_model)[None])
    h = out.bone_heads[0]
    for side, sign in (("L", 1), ("R", -1)):
        d = h[body_model.bone_index(f"wrist.{side}")] - h[body_model.bone_index(f"upperarm01.{side}")]
        d = d / d.norm()
        torch.testing.assert_close(d, torch.tensor([sign, 0.0, 0.0]), atol=1e-4, rtol=0)


def _write_mapping(tmp_path, edit):
    text = (RIGS_DIR / "mvn_anny.toml").read_text()
    path = tmp_path / "mapping.toml"
    path.write_text(edit(text))
    return path


def test_bad_mapping_files_name_the_problem(tmp_path, body_model):
    cases = [
        (lambda t: t.replace('bone = "wrist.R"', 'bone = "wrist.Right"'), r"unknown anny bone 'wrist.Right'"),
        (lambda t: t.replace("[segments.LeftToe]", "[segments.LeftBigToe]"), r"unknown MVN segment names \['LeftBigToe'\]"),
        (lambda t: t.replace('bone = "spine04"', 'bone = "spine03"'), r"bone 'spine03' is mapped by both L5 and L3"),
        (lambda t: t.replace('end = "vertex:881"', 'end = "vertex:99999"'), r"end vertex '99999'"),
        (lambda t: t + "\n[oops\n", r"not valid TOML"),
    ]
    for edit, message in cases:
        path = _write_mapping(tmp_path, edit)
        with pytest.raises(RigError, match=message) as e:
            load_segment_mapping(path)
        assert e.value.path == path and e.value.fix
    missing = _write_mapping(tmp_path, lambda t: t.split("[segments.LeftToe]")[0])
    with pytest.raises(RigError, match=r"segments not mapped: \['LeftToe'\]"):
        load_segment_mapping(missing)


def test_regions_cover_every_vertex(body_model):
    reg = load_regions(body_model)
    assert len(reg.names) == 22 and reg.vertex_region.shape == (body_model.num_vertices,)
    assert (reg.vertex_region >= 0).all() and set(np.unique(reg.vertex_region)) == set(range(22))
    v = body_model.rest().vertices[0].numpy()
    assert v[reg.vertices_of("left_hand"), 0].min() > 0.3 and v[reg.vertices_of("right_hand"), 0].max() < -0.3
    assert v[reg.vertices_of("chest"), 2].mean() > v[reg.vertices_of("upper_back"), 2].mean() + 0.1
    assert v[reg.vertices_of("head"), 1].min() > v[reg.vertices_of("left_foot"), 1].max() + 1.0


def test_regions_file_errors(tmp_path, body_model):
    text = (RIGS_DIR / "anny_regions.toml").read_text()
    p = tmp_path / "r.toml"
    p.write_text(text.replace('"toe*.L"', '"toes.L"'))
    with pytest.raises(RigError, match="'toes.L' matches no anny bone"):
        load_regions(body_model, p)
    p.write_text(text.replace('bones = ["neck01", "neck02", "neck03"]', 'bones = ["neck01", "neck02", "head"]'))
    with pytest.raises(RigError, match="bone 'head' is in both 'head' and 'neck'"):
        load_regions(body_model, p)


@pytest.mark.slow
def test_shape_for_stature(body_model):
    for height, gender in ((1.68, "female"), (1.82, "male"), (1.55, "neutral")):
        shape = shape_for_stature(body_model, height, gender)
        assert abs(stature(body_model, body_model.shape_tensor(shape)) - height) < 1e-3
        assert shape["gender"] == gender_value(gender)
    with pytest.raises(BodyModelError, match="outside what anny reaches"):
        shape_for_stature(body_model, 2.55, "female")
    with pytest.raises(BodyModelError, match="not a human height in metres"):
        shape_for_stature(body_model, 175.0)
    with pytest.raises(BodyModelError, match="gender must be one of"):
        gender_value("robot")

"""Render stage: real Mitsuba renders at small sizes, checked against independent geometry.

Masks against a numpy z-buffer rasterisation of the projected meshes, depth against the analytic
camera z of the floor plane, keypoints against Mitsuba's own projection (``sample_direction``),
RGB coverage against the mask through an off-centre camera (the OpenCV <-> Mitsuba conversion),
visibility on a constructed occlusion, resume after a simulated full disk, stage errors.
"""

from __future__ import annotations

import errno
import json

import numpy as np
import pytest

from dualhuman_builder.render.annotations import annotate_view, keypoint_visibility, visibility_statistics
from dualhuman_builder.render.cameras import Camera, load_cameras, look_at
from dualhuman_builder.render.renderer import RenderError, SequenceRenderer, body_model_uvs, pixel_rays
from dualhuman_builder.render.stage import read_depth_exr, render_sequence, run_render, select_frames, stage_cameras
from dualhuman_builder.render.template import TemplateError, load_template, sky_latlong, sun_direction


# --------------------------------------------------------------------------------------------- helpers
def make_pair(model, frames: int = 1, gap_m: float = 0.5, drift_m: float = 0.0):
    """Two average bodies in the rest pose facing each other along Z (a at -gap/2 facing +Z, b at
    +gap/2 turned to face -Z), a drifting along +X by ``drift_m`` over the frames."""
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    J, P = len(model.bone_names), len(model.shape_names)
    pose_a = np.zeros((frames, J, 3), np.float32)
    pose_b = np.zeros((frames, J, 3), np.float32)
    pose_b[:, 0, 1] = np.pi
    ta = np.tile([0.0, 0.93, -gap_m / 2], (frames, 1)).astype(np.float32)
    tb = np.tile([0.0, 0.93, gap_m / 2], (frames, 1)).astype(np.float32)
    ta[:, 0] += np.linspace(0.0, drift_m, frames)
    shape = np.full(P, 0.5, np.float32)
    return InteractionSequence((BodyTrack.from_model(model, pose_a, ta, shape, 15.0, actor="alice"),
                                BodyTrack.from_model(model, pose_b, tb, shape, 15.0, actor="bob")))  # fmt: skip


def rasterise(cam: Camera, meshes, faces: np.ndarray, max_span: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """``(labels (H, W) uint8 (0, 1, 2, ...), z (H, W) camera z, inf where empty)`` of ``meshes``
    (list of ``(V, 3)``) by a z-buffer sampled at pixel centres, perspective-correct depth;
    triangles must span <= max_span pixels."""
    H, W = cam.height, cam.width
    pix, zs, labs = [], [], []
    for k, v in enumerate(meshes):
        uv, z = cam.project(v)
        tu, tz = uv[faces], z[faces]
        keep = (tz > cam.near).all(1) & np.isfinite(tu).all((1, 2))
        tu, tz = tu[keep], tz[keep]
        lo = np.ceil(tu.min(1) - 0.5).astype(int)
        hi = np.floor(tu.max(1) - 0.5).astype(int)
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, [W - 1, H - 1])
        assert ((hi - lo) < max_span).all(), "triangles too large for this rasteriser: use a smaller image"
        a, b, c = tu[:, 0], tu[:, 1], tu[:, 2]
        area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
        ok_area = np.abs(area) > 1e-12
        for dy in range(max_span):
            for dx in range(max_span):
                px, py = lo[:, 0] + dx, lo[:, 1] + dy
                sel = ok_area & (px <= hi[:, 0]) & (py <= hi[:, 1])
                if not sel.any():
                    continue
                p = np.stack([px[sel] + 0.5, py[sel] + 0.5], 1)
                A, B, C, ar = a[sel], b[sel], c[sel], area[sel]
                w0 = ((B[:, 0] - p[:, 0]) * (C[:, 1] - p[:, 1]) - (B[:, 1] - p[:, 1]) * (C[:, 0] - p[:, 0])) / ar
                w1 = ((C[:, 0] - p[:, 0]) * (A[:, 1] - p[:, 1]) - (C[:, 1] - p[:, 1]) * (A[:, 0] - p[:, 0])) / ar
                w2 = 1.0 - w0 - w1
                inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
                zt = tz[sel]
                zp = 1.0 / (w0 / zt[:, 0] + w1 / zt[:, 1] + w2 / zt[:, 2])
                pix.append((py[sel] * W + px[sel])[inside])
                zs.append(zp[inside])
                labs.append(np.full(int(inside.sum()), k + 1, np.uint8))
    pix, zs, labs = np.concatenate(pix), np.concatenate(zs), np.concatenate(labs)
    order = np.lexsort((zs, pix))
    first = np.r_[True, pix[order][1:] != pix[order][:-1]]
    out = np.zeros(H * W, np.uint8)
    zbuf = np.full(H * W, np.inf)
    out[pix[order][first]] = labs[order][first]
    zbuf[pix[order][first]] = zs[order][first]
    return out.reshape(H, W), zbuf.reshape(H, W)


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


def centroid(weights: np.ndarray) -> np.ndarray:
    """Weighted mean pixel position ``(u, v)`` of an image (pixel centres at +0.5)."""
    ys, xs = np.mgrid[0 : weights.shape[0], 0 : weights.shape[1]] + 0.5
    return np.array([(weights * xs).sum(), (weights * ys).sum()]) / weights.sum()


def write_template(path, **changes):
    doc = json.loads(load_template("studio").path.read_text())
    doc.update(changes)
    path.write_text(json.dumps(doc))
    return path


# --------------------------------------------------------------------------------------------- one scene, many checks
@pytest.fixture(scope="module")
def scene(body_model, tmp_path_factory):
    """Four views of the pair through a floor-less, directionally lit template (so the RGB alpha is
    the bodies' coverage): behind a (b hidden behind a), from the side, an off-centre principal
    point on a 96x72 image, and a close-up of b (head and feet out of the image)."""
    seq = make_pair(body_model)
    res = seq.actors[0].compute(), seq.actors[1].compute()
    verts = [r["vertices"][0] for r in res]
    joints = np.stack([r["joints"][0] for r in res])
    coco = np.stack([r["coco"][0] for r in res])
    n = 96
    f = n / (2 * np.tan(np.radians(25)))
    K = [[f, 0, n / 2], [0, f, n / 2], [0, 0, 1]]
    cams = [
        Camera("behind_a", K, *look_at([0, 1.1, -3.5], [0, 1.0, 0]), n, n),
        Camera("side", K, *look_at([3.5, 1.1, 0.0], [0, 1.0, 0]), n, n),
        Camera("offcentre", [[f, 0, 0.4 * n], [0, f, 0.6 * 72], [0, 0, 1]], *look_at([2.2, 1.7, 2.6], [0, 0.9, 0]), n, 72),
        Camera("close_b", K, *look_at([0, 1.05, 1.3], [0, 1.05, 0.25]), n, n),
    ]  # fmt: skip
    tpl = write_template(tmp_path_factory.mktemp("tpl") / "plain.json", floor=None,
                         integrator={"type": "path", "max_depth": 2},
                         lights=[{"type": "directional", "direction": [0.3, -1, -0.5], "irradiance": [3, 3, 3]}])  # fmt: skip
    uv = body_model_uvs(body_model)
    r = SequenceRenderer(body_model.faces, body_model.num_vertices, cams, template=tpl, spp=64, uv=uv[0], face_uv=uv[1])
    r.set_frame(verts[0], verts[1])
    views = []
    for i in range(len(cams)):
        rgba = r.render_rgb(i)
        depth, mask = r.render_depth_mask(i)
        views.append({"rgba": rgba, "depth": depth, "mask": mask})
    return {"renderer": r, "cams": cams, "verts": verts, "joints": joints, "coco": coco, "views": views,
            "faces": body_model.faces.numpy()}  # fmt: skip


def test_mask_matches_rasterised_projection(scene):
    for cam, v in zip(scene["cams"], scene["views"]):
        assert v["mask"].dtype == np.uint8 and set(np.unique(v["mask"])) <= {0, 1, 2}
        ref, zref = rasterise(cam, scene["verts"], scene["faces"])
        for label in (1, 2):
            if (ref == label).sum() < 20:  # too few pixels to compare (b hidden behind a)
                assert (v["mask"] == label).sum() < 20
                continue
            assert iou(v["mask"] == label, ref == label) >= 0.98, (cam.name, label)
        # depth on the bodies: the rasterised z of the same surface (camera z, not ray length)
        both = (ref > 0) & (ref == v["mask"])
        assert np.abs(v["depth"][both] - zref[both]).max() < 1e-3, cam.name


def test_rgb_coverage_agrees_with_mask_through_mitsuba_sensor(scene):
    """The RGB goes through Mitsuba's sensor (principal point offsets included), the mask through
    OpenCV rays: their silhouettes coincide, also for an off-centre principal point."""
    for cam, v in zip(scene["cams"], scene["views"]):
        alpha = v["rgba"][..., 3]
        assert np.isfinite(v["rgba"]).all() and v["rgba"][..., :3][v["mask"] > 0].max() > 0.01
        assert iou(alpha > 0.5, v["mask"] > 0) >= 0.95, cam.name
        mk = (v["mask"] > 0).astype(float)
        assert np.abs(centroid(alpha) - centroid(mk)).max() < 0.75, cam.name  # px; a sign error moves it ~10 px
        shifted = np.roll(v["mask"] > 0, 3, axis=1)  # a 3 px error would show
        assert iou(alpha > 0.5, shifted) < 0.8


def test_keypoints_reproject_with_mitsubas_own_projection(scene):
    import drjit as dr
    import mitsuba as mi

    r = scene["renderer"]
    r._activate()
    for i, (cam, v) in enumerate(zip(scene["cams"], scene["views"])):
        kp = annotate_view(cam, scene["joints"], v["depth"], v["mask"])
        assert kp.shape == (2, 22, 3) and kp.dtype == np.float32
        pts = scene["joints"].reshape(-1, 3)
        it = dr.zeros(mi.Interaction3f, len(pts))
        it.p = mi.Point3f(pts[:, 0], pts[:, 1], pts[:, 2])
        ds, _ = r._sensors[i].sample_direction(it, mi.Point2f(0.5, 0.5))
        uv_mi = np.array(ds.uv).reshape(2, -1).T
        front = cam.to_camera(pts)[:, 2] > cam.near
        err = np.abs(kp[..., :2].reshape(-1, 2)[front] - uv_mi[front]).max()
        assert err < 0.5, (cam.name, err)


def test_visibility_on_a_constructed_occlusion(scene):
    vis = {}
    for cam, v in zip(scene["cams"], scene["views"]):
        vis[cam.name] = annotate_view(cam, scene["joints"], v["depth"], v["mask"])[..., 2]
    # behind a: b stands right behind a along the view, so b's joints are hidden, a's back is seen
    assert vis["behind_a"][1].mean() < 0.25 and vis["behind_a"][0].mean() > 0.6
    assert vis["behind_a"][1, 0] == 0 and vis["behind_a"][0, 0] == 1  # the pelvises
    # from the side both are seen (their far arm is hidden behind their own body)
    assert vis["side"][0].mean() > 0.5 and vis["side"][1].mean() > 0.5
    # close-up of b: joints outside the image are not visible, the pelvis in view is
    cam, v = scene["cams"][3], scene["views"][3]
    kp = annotate_view(cam, scene["joints"], v["depth"], v["mask"])
    outside = ~((kp[..., 0] >= 0) & (kp[..., 0] < cam.width) & (kp[..., 1] >= 0) & (kp[..., 1] < cam.height))
    assert outside[1].sum() >= 4 and (kp[..., 2][outside] == 0).all()
    assert kp[1, 0, 2] == 1
    # the rule itself: same actor, within tolerance in front, inside the image
    depth = np.full((4, 4), 2.0, np.float32)
    mask = np.array([[1, 1, 2, 0]] * 4, np.uint8)
    uv = np.array([[0.5, 0.5], [2.5, 0.5], [1.5, 1.5], [1.5, 1.5], [4.2, 1.0], [-0.1, 1.0]])
    z = np.array([2.1, 2.1, 2.1, 2.3, 2.1, 2.1])
    assert keypoint_visibility(uv, z, depth, mask, 1).tolist() == [True, False, True, False, False, False]
    with pytest.raises(ValueError, match="one size"):
        keypoint_visibility(uv, z, depth, mask[:2], 1)


def test_visibility_statistics_shapes_and_rates():
    kp = np.zeros((3, 4, 2, 22, 3), np.float32)
    kp[0, :, 0, 5, 2] = 1  # view 0, actor 0, joint 5 always visible
    kp[1, :2, 1, 0, 2] = 1  # view 1, actor 1, pelvis half the time
    coco = np.zeros((3, 4, 2, 17, 3), np.float32)
    names = [f"j{k}" for k in range(22)]
    doc = visibility_statistics(kp, coco, ["v0", "v1", "v2"], names, [f"c{k}" for k in range(17)])
    assert doc["joints"]["rate"][0][5] == pytest.approx(1 / 3, abs=1e-4) and doc["joints"]["rate"][1][0] == pytest.approx(1 / 6, abs=1e-4)
    assert doc["joints"]["per_view"]["v1"][1][0] == 0.5 and doc["joints"]["view_rate"]["v0"][0] == pytest.approx(1 / 22, abs=1e-4)
    assert doc["coco"]["overall"] == 0.0 and doc["frames"] == 4
    with pytest.raises(ValueError, match="joints keypoints must have shape"):
        visibility_statistics(kp[:, :, :, :21], coco, ["v0", "v1", "v2"], names, [f"c{k}" for k in range(17)])


def test_renderer_bad_input(scene, body_model):
    r = scene["renderer"]
    v = scene["verts"][0].copy()
    v[10, 1] = np.nan
    with pytest.raises(ValueError, match="actor 0 hold NaN"):
        r.set_frame(v, scene["verts"][1])
    with pytest.raises(ValueError, match=r"actor 1 must have shape \(13718, 3\)"):
        r.set_frame(scene["verts"][0], scene["verts"][1][:100])
    with pytest.raises(IndexError, match="4 cameras"):
        r.render_depth_mask(9)
    with pytest.raises(ValueError, match="faces must be integer indices"):
        SequenceRenderer(np.array([[0, 1, 99]]), 10, scene["cams"])
    with pytest.raises(ValueError, match="at least one camera"):
        SequenceRenderer(body_model.faces, body_model.num_vertices, [])


def test_srgb_encoding():
    from dualhuman_builder.render.renderer import linear_to_srgb8

    x = np.array([0.0, 0.0031308, 0.18, 0.5, 1.0, 7.0, -1.0, np.nan], np.float32)
    assert linear_to_srgb8(x).tolist() == [0, 10, 118, 188, 255, 255, 0, 0]


# --------------------------------------------------------------------------------------------- depth, templates, variants
def test_depth_is_camera_z_of_the_floor_plane(body_model):
    """A tilted camera over the outdoor template's floor: every floor pixel's depth equals the
    analytic camera z of the plane y = 0 through that pixel's centre, within 1 mm."""
    W, H = 48, 40
    f = W / (2 * np.tan(np.radians(35)))
    cam = Camera("down", [[f, 0, 23.0], [0, f, 21.5], [0, 0, 1]], *look_at([0.4, 2.0, 3.0], [0, 0, 0.3]), W, H)
    r = SequenceRenderer(body_model.faces, body_model.num_vertices, [cam], template="outdoor", spp=2)
    far = np.zeros((body_model.num_vertices, 3), np.float32) + [0.0, 0.5, -60.0]  # bodies out of view
    r.set_frame(far, far + [1.0, 0, 0])
    out = r.render_view(0)
    assert out["rgb"].shape == (H, W, 3) and out["rgb"].dtype == np.uint8 and out["rgb"].mean() > 10
    assert out["depth"].dtype == np.float32 and (out["mask"] == 0).all()
    origin, dirs, _ = pixel_rays(cam)
    t = -origin[1] / dirs[:, 1]
    hit = origin + t[:, None] * dirs
    z = cam.to_camera(hit)[:, 2].reshape(H, W)
    on_floor = ((t > 0) & (np.abs(hit[:, 0]) < 19) & (np.abs(hit[:, 2]) < 19)).reshape(H, W)
    assert on_floor.sum() > 0.5 * W * H
    err = np.abs(out["depth"][on_floor] - z[on_floor])
    assert err.max() < 1e-3, err.max()
    # camera z, not the ray length (which differs by up to 1/cos of the off-axis angle)
    assert np.abs(out["depth"][on_floor] - (t.reshape(H, W))[on_floor]).max() > 0.05


def test_scalar_variant_gives_the_same_depth_and_mask(scene, body_model):
    cams = [Camera(c.name, [[c.K[0, 0] / 4, 0, 8], [0, c.K[1, 1] / 4, 8], [0, 0, 1]], c.R, c.t, 16, 16) for c in scene["cams"][:2]]
    jit = SequenceRenderer(body_model.faces, body_model.num_vertices, cams, template="studio", spp=1)
    jit.set_frame(*scene["verts"])
    a = [jit.render_depth_mask(i) for i in range(2)]
    sc = SequenceRenderer(body_model.faces, body_model.num_vertices, cams, template="studio", spp=1, variant="scalar_rgb")
    assert sc.variant == "scalar_rgb"
    sc.set_frame(*scene["verts"])
    for i in range(2):
        d, m = sc.render_depth_mask(i)
        assert (m == a[i][1]).all() and (m > 0).sum() >= 8
        fin = np.isfinite(d)
        assert (fin == np.isfinite(a[i][0])).all() and np.abs(d[fin] - a[i][0][fin]).max() < 1e-4
    jit.render_depth_mask(0)  # the JIT renderer switches its variant back


def test_unusable_variant_falls_back_and_says_why(body_model):
    from dualhuman_builder.render.mitsuba_env import nvidia_gpus, pick_variant

    requested = "cuda_ad_rgb" if nvidia_gpus()[0] == 0 else "cuda_ad_no_such_variant"
    cam = Camera("c", [[8, 0, 4], [0, 8, 4], [0, 0, 1]], *look_at([0, 1, 3], [0, 1, 0]), 8, 8)
    logs = []
    r = SequenceRenderer(body_model.faces, body_model.num_vertices, [cam], spp=1, variant=requested, log=logs.append)
    assert r.variant == pick_variant() and r.variant != requested
    assert r.variant_note.startswith(f"variant {requested} is unusable here (") and f"fell back to {r.variant}" in r.variant_note
    assert any(requested in line for line in logs)
    assert r.describe()["variant_requested"] == requested


def test_template_errors(tmp_path, body_model):
    with pytest.raises(TemplateError, match=r"'nope' not found.*outdoor, studio"):
        load_template("nope")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(TemplateError, match="not valid JSON"):
        load_template(bad)
    doc = json.loads(load_template("studio").path.read_text())
    doc["actors"][1]["skin"] = [0.5, 2.0, 0.1]
    bad.write_text(json.dumps(doc))
    with pytest.raises(TemplateError, match=r"actors\[1\]\.skin must be 3 finite numbers in \[0, 1\]"):
        load_template(bad)
    doc["actors"] = doc["actors"][:1]
    bad.write_text(json.dumps(doc))
    with pytest.raises(TemplateError, match="exactly two actor materials"):
        load_template(bad)
    refused = write_template(tmp_path / "refused.json", integrator={"type": "no_such_integrator"})
    cam = Camera("c", [[8, 0, 4], [0, 8, 4], [0, 0, 1]], *look_at([0, 1, 3], [0, 1, 0]), 8, 8)
    with pytest.raises(TemplateError, match=r"cannot load render template 'studio'.*no_such_integrator") as e:
        SequenceRenderer(body_model.faces, body_model.num_vertices, [cam], template=refused, spp=1)
    assert "refused.json" in str(e.value)


def test_procedural_sky_follows_mitsubas_envmap_layout():
    import drjit as dr
    import mitsuba as mi

    from dualhuman_builder.render.mitsuba_env import configure_llvm, pick_variant

    configure_llvm()
    mi.set_variant(pick_variant())
    img = sky_latlong((256, 128), zenith=(0, 0, 1), horizon=(0, 1, 0), ground=(1, 0, 0), sun_azimuth_deg=120,
                      sun_elevation_deg=30, sun_radiance=(500, 400, 300), sun_size_deg=4)  # fmt: skip
    env = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(img)})
    dirs = np.array([sun_direction(120, 30), [0, 1, 0], [0.3, -0.9, 0.2], sun_direction(-60, 30)])
    si = dr.zeros(mi.SurfaceInteraction3f, len(dirs))
    si.wi = mi.Vector3f(-dirs[:, 0], -dirs[:, 1], -dirs[:, 2])  # eval looks along -wi
    val = np.array(env.eval(si)).reshape(3, -1).T
    assert np.allclose(val[0], [500, 400, 300], rtol=0.05)  # the sun where sun_direction says
    assert val[1, 2] > 0.9 and val[1, :2].max() < 0.1  # zenith
    assert val[2, 0] > 0.9 and val[2, 1:].max() < 0.1  # ground
    assert val[3].max() < 2  # no sun on the opposite side


# --------------------------------------------------------------------------------------------- sequences and the stage
def test_render_sequence_layout_resume_after_full_disk(body_model, tmp_path):
    seq = make_pair(body_model, frames=5, gap_m=0.6, drift_m=0.3)
    cams = stage_cameras(seq, views=2, size=32, frames=select_frames(5, 2))
    out = tmp_path / "render"

    def full_disk(path):
        if "00004" in path.name:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))

    with pytest.raises(RenderError, match=r"disk full while writing .*00004.*: 2 of 3 frames are complete") as e:
        render_sequence(seq, out, cams, spp=2, every=2, before_write=full_disk, log=lambda s: None)
    assert "resumes" in str(e.value)
    first = out / "views" / "view00" / "rgb" / "00000.png"
    stamp = first.stat().st_mtime_ns
    logs = []
    doc = render_sequence(seq, out, cams, spp=2, every=2, log=logs.append)
    assert doc["frames"] == [0, 2, 4] and doc["frames_resumed"] == 2 and doc["frames_rendered"] == 1
    assert first.stat().st_mtime_ns == stamp  # complete frames are not rendered again
    assert any("2 of 3 frames already complete" in line for line in logs)
    assert not (out / ".progress").exists()

    from PIL import Image

    from dualhuman_builder.render.mitsuba_env import pick_variant

    rend = json.loads((out / "render.json").read_text())
    camdoc = json.loads((out / "cameras.json").read_text())
    assert rend["variant"] == camdoc["variant"] == pick_variant() and rend["spp"] == 2 and rend["views"] == ["view00", "view01"]
    back = load_cameras(out / "cameras.json")
    assert all(np.allclose(a.K, b.K) and np.allclose(a.R, b.R) and np.allclose(a.t, b.t) for a, b in zip(back, cams))
    with np.load(out / "keypoints.npz") as z:
        joints, coco, frames = z["joints"], z["coco"], z["frames"]
        assert joints.shape == (2, 3, 2, 22, 3) and coco.shape == (2, 3, 2, 17, 3) and frames.tolist() == [0, 2, 4]
        assert z["views"].tolist() == ["view00", "view01"]
    # keypoints.npz agrees with the saved images: recomputed from the EXR depth and PNG mask
    res = [a.compute(frames=frames) for a in seq.actors]
    for i, cam in enumerate(cams):
        for n, f in enumerate(frames):
            depth = read_depth_exr(out / "views" / cam.name / "depth" / f"{f:05d}.exr")
            mask = np.asarray(Image.open(out / "views" / cam.name / "mask" / f"{f:05d}.png"))
            rgb = Image.open(out / "views" / cam.name / "rgb" / f"{f:05d}.png")
            assert depth.dtype == np.float32 and depth.shape == (32, 32) and rgb.mode == "RGB" and rgb.size == (32, 32)
            assert set(np.unique(mask)) == {0, 1, 2} and np.isfinite(depth[mask > 0]).all()
            pts = np.stack([r["joints"][n] for r in res])
            assert np.array_equal(annotate_view(cam, pts, depth, mask), joints[i, n], equal_nan=True)
    vis = json.loads((out / "visibility.json").read_text())
    rate = np.array(vis["joints"]["rate"])
    assert rate.shape == (2, 22) and (rate >= 0).all() and (rate <= 1).all() and rate.mean() > 0.3
    assert set(vis["joints"]["per_view"]) == {"view00", "view01"} and vis["actors"] == ["alice", "bob"]


def test_render_sequence_rejects_an_empty_sequence(body_model, tmp_path):
    seq = make_pair(body_model, frames=0)
    with pytest.raises(RenderError, match="no frames: there are no fitted bodies"):
        render_sequence(seq, tmp_path / "r", [], spp=1)
    with pytest.raises(ValueError, match="every must be >= 1"):
        select_frames(10, every=0)
    assert select_frames(10, every=3, max_frames=3).tolist() == [0, 3, 6]


def test_stage_needs_fit_resumes_and_publishes(ws, body_model):
    from dualhuman_builder.errors import WorkspaceError

    ws.add_take("T001")
    with pytest.raises(WorkspaceError, match=r"no fitted bodies.*has not run.*dualhuman fit .* --take T001"):
        run_render(ws, "T001", views=2, size=24, spp=1, log=lambda s: None)
    seq = make_pair(body_model, frames=3, gap_m=0.6)
    def fit(out):  # a fit stage whose result is this sequence
        seq.save(out.path("bodies.npz"))

    ws.run_stage("fit", fit, take="T001")

    def full_disk(path):
        if "00001" in path.name:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))

    kw = dict(views=2, size=24, spp=1, max_frames=2, log=lambda s: None)
    with pytest.raises(RenderError, match="1 of 2 frames are complete"):
        run_render(ws, "T001", before_write=full_disk, **kw)
    assert ws.stage_record("render", "T001")["status"] == "failed"
    assert list((ws.root / "scratch" / "render" / "T001").glob("*/.progress/00000.npz"))
    res = run_render(ws, "T001", **kw)
    assert res.summary["frames_resumed"] == 1 and res.summary["frames_rendered"] == 1 and res.summary["frames"] == 2
    arts = ws.artifacts("render", "T001")
    assert {"cameras.json", "render.json", "keypoints.npz", "visibility.json", "views/view01/depth/00001.exr",
            "views/view00/rgb/00000.png", "views/view00/mask/00001.png"} <= set(arts)  # fmt: skip
    assert not any(n.startswith(".") or "/." in n for n in arts)
    assert not (ws.root / "scratch" / "render" / "T001").exists()
    assert run_render(ws, "T001", **kw).skipped

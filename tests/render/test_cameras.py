"""Cameras: OpenCV geometry, the ring, rig files, and the conversion to Mitsuba's convention."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dualhuman_builder.render.cameras import Camera, CameraError, load_cameras, look_at, ring_cameras, save_cameras


def test_look_at_axes_follow_opencv():
    R, t = look_at([0, 1.5, 3.0], [0, 1.5, 0.0])  # looking along -Z world, Y up
    cam = Camera("c", [[100, 0, 50], [0, 100, 40], [0, 0, 1]], R, t, 100, 80)
    assert np.allclose(cam.position, [0, 1.5, 3.0])
    uv, z = cam.project(np.array([[0, 1.5, 0.0], [1.0, 1.5, 0.0], [0, 2.5, 0.0], [0, 1.5, 4.0]]))
    assert np.allclose(uv[0], [50, 40]) and np.isclose(z[0], 3.0)
    assert uv[1, 0] > 50 and np.isclose(uv[1, 1], 40)  # world +X is image right
    assert uv[2, 1] < 40  # world up is image up (smaller v)
    assert np.isnan(uv[3]).all() and z[3] < 0  # behind the camera
    with pytest.raises(CameraError, match="along the up vector"):
        look_at([0, 3, 0], [0, 0, 0])


def test_ring_looks_at_target_and_jitter_is_seeded():
    cams = ring_cameras(6, radius_m=2.5, height_m=1.2, fov_deg=60, target=(0.3, 1.0, -0.2), size=(64, 48))
    for c in cams:
        uv, z = c.project(np.array([0.3, 1.0, -0.2]))
        assert np.allclose(uv, [32, 24]) and z > 2.5
        assert np.isclose(np.hypot(*(c.position[[0, 2]] - [0.3, -0.2])), 2.5) and np.isclose(c.position[1], 1.2)
        assert np.isclose(c.fov_x_deg, 60)
    a = ring_cameras(4, jitter_seed=7)
    b = ring_cameras(4, jitter_seed=7)
    c = ring_cameras(4, jitter_seed=8)
    assert all(np.allclose(x.R, y.R) for x, y in zip(a, b))
    assert not all(np.allclose(x.R, y.R) for x, y in zip(a, c))
    with pytest.raises(CameraError, match="at least one view"):
        ring_cameras(0)


def test_mitsuba_round_trip_and_axes():
    cams = ring_cameras(3, size=(80, 60), jitter_seed=1)
    cams.append(Camera("offcentre", [[70, 0, 45.5], [0, 70, 27.0], [0, 0, 1]], *look_at([1, 2, 2], [0, 1, 0]), 80, 60))
    for c in cams:
        M = c.mitsuba_to_world()
        back = Camera.from_mitsuba(c.name, M, c.fov_x_deg, c.width, c.height, c.principal_offset())
        assert np.allclose(back.K, c.K) and np.allclose(back.R, c.R) and np.allclose(back.t, c.t)
        # Mitsuba looks along its +Z with +X to the image's left and +Y up
        assert np.allclose(M[:3, 2], c.R[2]) and np.allclose(M[:3, 0], -c.R[0]) and np.allclose(M[:3, 1], -c.R[1])
        assert np.allclose(M[:3, 3], c.position)


def test_rig_file_round_trip_and_errors(tmp_path):
    cams = ring_cameras(2, size=(32, 32))
    p = save_cameras(tmp_path / "cams.json", cams, variant="llvm_ad_rgb")
    back = load_cameras(p)
    assert [c.name for c in back] == ["view00", "view01"] and np.allclose(back[1].R, cams[1].R)
    assert json.loads(p.read_text())["variant"] == "llvm_ad_rgb"
    by_eye = tmp_path / "eye.json"
    by_eye.write_text(json.dumps({"cameras": [{"name": "side", "position": [3, 1.5, 0], "look_at": [0, 1, 0], "fov_deg": 40}]}))
    (side,) = load_cameras(by_eye, size=(64, 48))
    assert side.width == 64 and np.isclose(side.fov_x_deg, 40) and np.allclose(side.project(np.array([0, 1, 0]))[0], [32, 24])
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"cameras": [{"name": "x", "position": [0, 1, 0]}]}))
    with pytest.raises(CameraError, match="needs either K, R, t"):
        load_cameras(bad, size=(8, 8))
    bad.write_text("{nope")
    with pytest.raises(CameraError, match="not valid JSON"):
        load_cameras(bad)
    with pytest.raises(CameraError, match="not found"):
        load_cameras(tmp_path / "missing.json")
    with pytest.raises(CameraError, match="not a rotation"):
        Camera("x", np.eye(3), 2 * np.eye(3), np.zeros(3), 8, 8)

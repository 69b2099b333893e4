"""Cameras of the render stage, in the OpenCV convention, and their Mitsuba equivalents.

Convention (stated once, in :mod:`dualhuman_builder.conventions`): intrinsics ``K (3, 3)`` in pixels
and world-to-camera ``R (3, 3)``, ``t (3,)`` metres, camera +X right, +Y down, +Z forward; a world
point ``X`` projects to ``K (R X + t)``. Pixel centres are at integer + 0.5 (pixel ``(0, 0)``
covers ``[0, 1) x [0, 1)``), as in Mitsuba's film and OpenCV's ``projectPoints`` with that offset.

Mitsuba's perspective sensor looks along its +Z with +X *left* and +Y up, has one horizontal field
of view (so ``fx`` must equal ``fy``) and a principal point offset given as a fraction of the film
size. :meth:`Camera.mitsuba_sensor` and :meth:`Camera.from_mitsuba` convert both ways.

A rig is a list of cameras: :func:`ring_cameras` puts ``n`` of them on a circle around the pair
(views on a circle, as in the Dual-Human dataset), optionally jittered per sequence with a seed;
:func:`load_cameras` reads them from a JSON rig file, :func:`save_cameras` writes one.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dualhuman_builder.errors import DualhumanError


class CameraError(DualhumanError):
    """A camera or rig file that cannot be used."""


def look_at(eye, target, up=(0.0, 1.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera ``(R (3, 3), t (3,))`` (OpenCV) of a camera at ``eye`` looking at ``target``
    with world ``up`` pointing up in the image (world metres)."""
    eye, target, up = (np.asarray(v, dtype=float) for v in (eye, target, up))
    f = target - eye
    if not np.isfinite(f).all() or np.linalg.norm(f) < 1e-9:
        raise CameraError(f"camera at {eye.tolist()} cannot look at {target.tolist()}")
    f /= np.linalg.norm(f)
    r = np.cross(f, up)
    if np.linalg.norm(r) < 1e-9:
        raise CameraError(f"camera at {eye.tolist()} looks straight along the up vector {up.tolist()}")
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    R = np.stack([r, d, f])
    return R, -R @ eye


@dataclass
class Camera:
    """One pinhole camera (OpenCV convention, see the module docstring); ``near``/``far`` metres."""

    name: str
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    near: float = 0.01
    far: float = 100.0
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.K = np.asarray(self.K, dtype=float).reshape(3, 3)
        self.R = np.asarray(self.R, dtype=float).reshape(3, 3)
        self.t = np.asarray(self.t, dtype=float).reshape(3)
        self.width, self.height = int(self.width), int(self.height)
        if self.width < 1 or self.height < 1:
            raise CameraError(f"camera {self.name!r}: image size {self.width}x{self.height} is empty")
        if not (np.isfinite(self.K).all() and np.isfinite(self.R).all() and np.isfinite(self.t).all()):
            raise CameraError(f"camera {self.name!r} has non-finite K, R or t")
        if abs(np.linalg.det(self.R) - 1.0) > 1e-4 or np.abs(self.R @ self.R.T - np.eye(3)).max() > 1e-4:
            raise CameraError(f"camera {self.name!r}: R is not a rotation (det {np.linalg.det(self.R):.4f})")
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0:
            raise CameraError(f"camera {self.name!r}: focal lengths must be positive, got {self.K[0, 0]}, {self.K[1, 1]}")

    # ------------------------------------------------------------------ geometry
    @property
    def position(self) -> np.ndarray:
        """Camera centre in the world ``(3,)``, metres."""
        return -self.R.T @ self.t

    @property
    def fov_x_deg(self) -> float:
        """Horizontal field of view, degrees."""
        return math.degrees(2.0 * math.atan(self.width / (2.0 * self.K[0, 0])))

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points ``(..., 3)`` to camera coordinates ``(..., 3)`` (metres, OpenCV axes)."""
        return np.asarray(points, dtype=float) @ self.R.T + self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(uv (..., 2) pixels, z (...,) camera z in metres)`` of world points ``(..., 3)``. Points
        at or behind the camera (``z <= 0``) get NaN pixels."""
        pc = self.to_camera(points)
        z = pc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uvw = pc @ self.K.T
            uv = uvw[..., :2] / uvw[..., 2:3]
        uv[z <= 0] = np.nan
        return uv, z

    # ------------------------------------------------------------------ Mitsuba
    def mitsuba_to_world(self) -> np.ndarray:
        """Mitsuba's camera-to-world ``(4, 4)``: OpenCV's with the X and Y axes negated."""
        M = np.eye(4)
        M[:3, :3] = self.R.T
        M[:3, 3] = self.position
        return M @ np.diag([-1.0, -1.0, 1.0, 1.0])

    def principal_offset(self) -> tuple[float, float]:
        """Mitsuba's ``principal_point_offset_x/y``: the image centre's offset from the principal
        point as a fraction of the image width / height. Mitsuba (3.9) puts the principal point at
        pixel ``((0.5 - ox) W, (0.5 - oy) H)`` -- measured on its renders and ``sample_direction``."""
        return ((self.width / 2 - self.K[0, 2]) / self.width, (self.height / 2 - self.K[1, 2]) / self.height)

    def mitsuba_sensor(self, spp: int = 16, film: dict | None = None, sampler: str = "independent") -> dict:
        """A ``perspective`` sensor dict for ``mi.load_dict`` (``film`` defaults to an ``hdrfilm`` of
        this size with a box filter). Raises :class:`CameraError` when ``fx != fy`` or ``K`` has skew."""
        import mitsuba as mi

        if abs(self.K[0, 0] - self.K[1, 1]) > 1e-6 * self.K[0, 0] or abs(self.K[0, 1]) > 1e-9:
            raise CameraError(f"camera {self.name!r}: Mitsuba needs square pixels without skew (fx = fy, K[0,1] = 0), "
                              f"got fx {self.K[0, 0]:.3f}, fy {self.K[1, 1]:.3f}, skew {self.K[0, 1]:.3g}")  # fmt: skip
        ox, oy = self.principal_offset()
        return {
            "type": "perspective",
            "fov": self.fov_x_deg,
            "fov_axis": "x",
            "principal_point_offset_x": ox,
            "principal_point_offset_y": oy,
            "near_clip": self.near,
            "far_clip": self.far,
            "to_world": mi.ScalarTransform4f(self.mitsuba_to_world().tolist()),
            "sampler": {"type": sampler, "sample_count": int(spp)},
            "film": film or {"type": "hdrfilm", "width": self.width, "height": self.height, "rfilter": {"type": "box"},
                             "pixel_format": "rgb"},  # fmt: skip
        }

    @classmethod
    def from_mitsuba(cls, name: str, to_world: np.ndarray, fov_x_deg: float, width: int, height: int,
                     principal_offset: tuple[float, float] = (0.0, 0.0), near: float = 0.01, far: float = 100.0) -> "Camera":  # fmt: skip
        """The OpenCV camera of a Mitsuba sensor (inverse of :meth:`mitsuba_to_world` and friends)."""
        M = np.asarray(to_world, dtype=float).reshape(4, 4) @ np.diag([-1.0, -1.0, 1.0, 1.0])
        R = M[:3, :3].T
        f = width / (2.0 * math.tan(math.radians(fov_x_deg) / 2.0))
        K = np.array([[f, 0, width / 2 - principal_offset[0] * width], [0, f, height / 2 - principal_offset[1] * height], [0, 0, 1]])
        return cls(name, K, R, -R @ M[:3, 3], width, height, near, far)

    # ------------------------------------------------------------------ files
    def as_dict(self) -> dict:
        """JSON-ready: ``K``, ``R``, ``t`` (world-to-camera, OpenCV), size, clip planes, position."""
        return {"name": self.name, "width": self.width, "height": self.height, "K": self.K.tolist(), "R": self.R.tolist(),
                "t": self.t.tolist(), "position": self.position.tolist(), "fov_x_deg": self.fov_x_deg, "near": self.near,
                "far": self.far, **({"meta": self.meta} if self.meta else {})}  # fmt: skip

    @classmethod
    def from_dict(cls, d: dict, size: tuple[int, int] | None = None) -> "Camera":
        """From :meth:`as_dict`'s form, or from ``{"name", "position", "look_at", "fov_deg"[, "up"]}``
        (a camera placed by eye; ``size`` ``(width, height)`` or the entry's ``width``/``height``)."""
        try:
            w = int(d.get("width", size[0] if size else 0))
            h = int(d.get("height", size[1] if size else 0))
            name = str(d.get("name", "camera"))
            if "K" in d:
                return cls(name, d["K"], d["R"], d["t"], w, h, float(d.get("near", 0.01)), float(d.get("far", 100.0)))
            R, t = look_at(d["position"], d["look_at"], d.get("up", (0.0, 1.0, 0.0)))
            f = w / (2.0 * math.tan(math.radians(float(d["fov_deg"])) / 2.0))
            return cls(name, [[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], R, t, w, h)
        except (KeyError, TypeError, ValueError) as e:
            raise CameraError(f"camera entry {d.get('name', '?')!r} needs either K, R, t, width, height or "
                              f"position, look_at, fov_deg (and a size): {type(e).__name__}: {e}") from e  # fmt: skip


def ring_cameras(n: int = 8, radius_m: float = 3.0, height_m: float = 1.4, fov_deg: float = 50.0,
                 target=(0.0, 1.0, 0.0), size: tuple[int, int] = (512, 512), jitter_seed: int | None = None,
                 jitter_deg: float = 10.0, jitter_radius_m: float = 0.3, jitter_height_m: float = 0.2) -> list[Camera]:  # fmt: skip
    """``n`` cameras evenly spaced on a horizontal circle of ``radius_m`` around ``target`` (world
    metres), at ``height_m`` above the floor, all looking at ``target``; view 0 is on the +Z side.
    With ``jitter_seed``, each view's azimuth, radius and height are perturbed uniformly by up to
    ``jitter_deg`` / ``jitter_radius_m`` / ``jitter_height_m`` (deterministic for a seed)."""
    if n < 1:
        raise CameraError(f"a camera ring needs at least one view, got {n}")
    if not (radius_m > 0 and 0 < fov_deg < 180):
        raise CameraError(f"ring radius must be > 0 and field of view in (0, 180) degrees, got {radius_m}, {fov_deg}")
    target = np.asarray(target, dtype=float)
    rng = np.random.default_rng(jitter_seed) if jitter_seed is not None else None
    w, h = int(size[0]), int(size[1])
    f = w / (2.0 * math.tan(math.radians(fov_deg) / 2.0))
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    cams = []
    for i in range(n):
        az, r, y = 2 * math.pi * i / n, radius_m, height_m
        if rng is not None:
            az += math.radians(rng.uniform(-jitter_deg, jitter_deg))
            r += rng.uniform(-jitter_radius_m, jitter_radius_m)
            y += rng.uniform(-jitter_height_m, jitter_height_m)
        eye = np.array([target[0] + r * math.sin(az), y, target[2] + r * math.cos(az)])
        R, t = look_at(eye, target)
        cams.append(Camera(f"view{i:02d}", K, R, t, w, h, meta={"azimuth_deg": math.degrees(az), "radius_m": r, "height_m": y}))
    return cams


def save_cameras(path: str | Path, cameras: list[Camera], **extra) -> Path:
    """Write ``{"convention": ..., "cameras": [...], **extra}`` as JSON."""
    path = Path(path)
    doc = {"convention": "OpenCV: x_cam = R x_world + t; pixel = K x_cam; +X right, +Y down, +Z forward; metres",
           "cameras": [c.as_dict() for c in cameras], **extra}  # fmt: skip
    path.write_text(json.dumps(doc, indent=2))
    return path


def load_cameras(path: str | Path, size: tuple[int, int] | None = None) -> list[Camera]:
    """Cameras of a JSON rig file: ``{"cameras": [entry, ...]}`` with entries as in
    :meth:`Camera.from_dict`; ``size`` fills in entries that give none."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise CameraError(f"camera rig file not found: {path}") from None
    except json.JSONDecodeError as e:
        raise CameraError(f"camera rig file {path} is not valid JSON: {e}") from e
    entries = doc.get("cameras") if isinstance(doc, dict) else None
    if not isinstance(entries, list) or not entries:
        raise CameraError(f"camera rig file {path} has no \"cameras\" list")
    cams = [Camera.from_dict(e, size) for e in entries]
    names = [c.name for c in cams]
    if len(set(names)) != len(names):
        raise CameraError(f"camera rig file {path} repeats camera names: {sorted(n for n in set(names) if names.count(n) > 1)}")
    return cams


__all__ = ["Camera", "CameraError", "look_at", "ring_cameras", "save_cameras", "load_cameras"]

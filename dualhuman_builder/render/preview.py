"""A quick Mitsuba still of a few meshes on a floor, for previews (the demo, ``scene preview``).

Not the dataset renderer (that builds a scene once per sequence and updates vertices per frame):
this writes the meshes to temporary PLY files, frames them with a camera at a three-quarter view,
and renders one sRGB PNG with the best variant that works here (:func:`.mitsuba_env.pick_variant`).
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Sequence

import numpy as np


def render_preview(
    meshes: Sequence[tuple[np.ndarray, np.ndarray, tuple[float, float, float]]],
    path: str | Path,
    size: tuple[int, int] = (480, 320),
    spp: int = 32,
    variant: str | None = None,
    azimuth_deg: float = 35.0,
    elevation_deg: float = 25.0,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
    floor_y: float | None = None,
) -> dict:
    """Render ``meshes`` — ``(vertices (V, 3) world metres, faces (F, 3), rgb)`` with ``rgb`` one
    colour ``(3,)`` or per-vertex colours ``(V, 3)``, in [0, 1] — to ``path``.

    The camera looks at the centre of ``bounds`` (default: the meshes' bounding box) from
    ``azimuth_deg`` about +Y (0 looks along -Z from +Z) and ``elevation_deg`` above the horizon, far
    enough for the box to fill about 80 % of the frame. The floor lies at ``floor_y`` (default: the
    bottom of ``bounds``). Returns ``{"variant", "seconds"}``.
    """
    import trimesh

    from dualhuman_builder.render.mitsuba_env import configure_llvm, pick_variant

    configure_llvm()
    variant = variant or pick_variant()
    import mitsuba as mi

    mi.set_variant(variant)
    t0 = time.perf_counter()
    if bounds is None:
        pts = np.concatenate([np.asarray(v) for v, _, _ in meshes])
        bounds = (pts.min(0), pts.max(0))
    lo, hi = np.asarray(bounds[0], dtype=float), np.asarray(bounds[1], dtype=float)
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    fov = 35.0
    dist = radius / np.tan(np.radians(fov) / 2) / 0.8
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    eye = centre + dist * np.array([np.sin(az) * np.cos(el), np.sin(el), np.cos(az) * np.cos(el)])
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 4},
        "sensor": {
            "type": "perspective",
            "fov": fov,
            "fov_axis": "smaller",
            "to_world": mi.ScalarTransform4f().look_at(origin=eye.tolist(), target=centre.tolist(), up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": int(size[0]), "height": int(size[1])},
            "sampler": {"type": "independent", "sample_count": int(spp)},
        },
        "floor": {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f().translate([float(centre[0]), float(lo[1] if floor_y is None else floor_y),
                                                          float(centre[2])])
            @ mi.ScalarTransform4f().rotate([1, 0, 0], -90)
            @ mi.ScalarTransform4f().scale(4 * radius),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.6, 0.6]}},
        },
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.35, 0.37, 0.4]}},
        "sun": {"type": "directional", "direction": [-0.4, -1.0, -0.6], "irradiance": {"type": "rgb", "value": [2.5, 2.4, 2.2]}},
    }
    with tempfile.TemporaryDirectory(prefix="dualhuman-preview-") as tmp:
        for i, (verts, faces, rgb) in enumerate(meshes):
            ply = Path(tmp) / f"mesh{i}.ply"
            rgb = np.asarray(rgb, dtype=float)
            if rgb.ndim == 2:  # per-vertex colours: Mitsuba reads them as the 'vertex_color' attribute
                _write_coloured_ply(ply, np.asarray(verts), np.asarray(faces), np.clip(rgb, 0.0, 1.0))
                reflectance = {"type": "mesh_attribute", "name": "vertex_color"}
            else:
                trimesh.Trimesh(np.asarray(verts), np.asarray(faces), process=False).export(ply)
                reflectance = {"type": "rgb", "value": rgb.tolist()}
            # one BSDF per mesh, so Mitsuba keeps the meshes separate shapes
            scene[f"mesh{i}"] = {"type": "ply", "filename": str(ply), "bsdf": {"type": "diffuse", "reflectance": reflectance}}
        image = mi.render(mi.load_dict(scene))
    mi.util.write_bitmap(str(path), image, write_async=False)  # complete before the stage publishes it
    return {"variant": variant, "seconds": time.perf_counter() - t0}


def _write_coloured_ply(path: Path, verts: np.ndarray, faces: np.ndarray, rgb: np.ndarray) -> None:
    """Binary PLY with float ``red green blue`` per vertex in [0, 1] (Mitsuba's ``vertex_color``;
    8-bit colours would be read unscaled)."""
    v = np.zeros(len(verts), dtype=[("p", "<f4", 3), ("c", "<f4", 3)])
    v["p"], v["c"] = verts, rgb
    f = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", 3)])
    f["n"], f["i"] = 3, faces
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property float red\nproperty float green\nproperty float blue\n"
              f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n")  # fmt: skip
    with open(path, "wb") as out:
        out.write(header.encode("ascii"))
        out.write(v.tobytes())
        out.write(f.tobytes())


def render_strip(
    sequence,
    faces: np.ndarray,
    path: str | Path,
    *,
    frames: int | Sequence[int] = 6,
    colours: Sequence = ((0.80, 0.35, 0.25), (0.25, 0.45, 0.80)),
    highlight: Sequence[np.ndarray] | None = None,
    size: tuple[int, int] = (300, 360),
    spp: int = 24,
    variant: str | None = None,
    progress=None,
) -> dict:
    """A PNG strip of the two bodies of ``sequence`` (an InteractionSequence) over time: ``frames``
    (a count, spread evenly, or explicit indices) rendered side by side from one fixed camera
    (side view across the line between the actors, framing every chosen frame), each captioned
    with its time. ``highlight[i] (T, V)`` bool paints those vertices of actor ``i`` yellow (e.g.
    ground-truth contacts). A path ending in ``.gif`` writes an animated GIF instead, one
    image per chosen frame. Returns ``{"variant", "seconds", "frames"}``."""
    from PIL import Image, ImageDraw

    t0 = time.perf_counter()
    T = sequence.num_frames
    idx = np.linspace(0, T - 1, int(frames)).round().astype(int) if np.isscalar(frames) else np.asarray(frames, int)
    if len(idx) == 0 or idx.min() < 0 or idx.max() >= T:
        raise ValueError(f"frames must lie in [0, {T - 1}], got {idx.tolist()}")
    verts = [a.vertices() for a in sequence.actors]
    chosen = np.concatenate([v[idx].reshape(-1, 3) for v in verts])
    lo, hi = chosen.min(0), chosen.max(0)
    lo[1] = min(lo[1], 0.0)  # keep the floor in view
    # the camera looks across the actors' line (the horizontal axis along which they are spread)
    spread = hi - lo
    azimuth = 90.0 if spread[2] >= spread[0] else 0.0
    images, used = [], None
    for n, f in enumerate(idx):
        if progress:
            progress(f"rendering frame {f} ({n + 1}/{len(idx)})")
        meshes = []
        for i, v in enumerate(verts):
            rgb = np.asarray(colours[i], dtype=float)
            if highlight is not None and highlight[i][f].any():
                rgb = np.tile(rgb, (v.shape[1], 1))
                rgb[highlight[i][f]] = (0.98, 0.85, 0.15)
            meshes.append((v[f], faces, rgb))
        with tempfile.TemporaryDirectory(prefix="dualhuman-strip-") as tmp:
            tile = Path(tmp) / "tile.png"
            info = render_preview(meshes, tile, size=size, spp=spp, variant=variant, azimuth_deg=azimuth,
                                  elevation_deg=10.0, bounds=(lo, hi))  # fmt: skip
            used = info["variant"]
            img = Image.open(tile).convert("RGB")
        ImageDraw.Draw(img).text((8, 6), f"{f / sequence.fps:.2f} s", fill=(20, 20, 20))
        images.append(img)
    path = Path(path)
    if path.suffix.lower() == ".gif":
        images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 * (idx[-1] - idx[0] + 1)
                       / sequence.fps / len(idx)), loop=0)  # fmt: skip
    else:
        strip = Image.new("RGB", (size[0] * len(images), size[1]), (255, 255, 255))
        for n, img in enumerate(images):
            strip.paste(img, (n * size[0], 0))
        strip.save(path)
    return {"variant": used, "seconds": time.perf_counter() - t0, "frames": idx.tolist()}

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
) -> dict:
    """Render ``meshes`` — ``(vertices (V, 3) world metres, faces (F, 3), rgb in [0, 1])`` — to ``path``.

    The camera looks at the meshes' bounding-box centre from the front-right, 25 degrees above
    the horizon, far enough for the box to fill about 80 % of the frame. Returns ``{"variant",
    "seconds"}``.
    """
    import trimesh

    from dualhuman_builder.render.mitsuba_env import configure_llvm, pick_variant

    configure_llvm()
    variant = variant or pick_variant()
    import mitsuba as mi

    mi.set_variant(variant)
    t0 = time.perf_counter()
    pts = np.concatenate([np.asarray(v) for v, _, _ in meshes])
    lo, hi = pts.min(0), pts.max(0)
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    fov = 35.0
    dist = radius / np.tan(np.radians(fov) / 2) / 0.8
    az, el = np.radians(35.0), np.radians(25.0)
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
            "to_world": mi.ScalarTransform4f().translate([float(centre[0]), float(lo[1]), float(centre[2])])
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
            trimesh.Trimesh(np.asarray(verts), np.asarray(faces), process=False).export(ply)
            # one BSDF per mesh, so Mitsuba keeps the meshes separate shapes
            scene[f"mesh{i}"] = {"type": "ply", "filename": str(ply),
                                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(rgb)}}}  # fmt: skip
        image = mi.render(mi.load_dict(scene))
    mi.util.write_bitmap(str(path), image, write_async=False)  # complete before the stage publishes it
    return {"variant": variant, "seconds": time.perf_counter() - t0}

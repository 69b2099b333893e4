"""What ``dualhuman body warm`` and ``dualhuman body info`` report."""

from __future__ import annotations

import time
from typing import Any


def warm_cache() -> dict[str, Any]:
    """Build (or load) the default anny model once so that later constructions take < 1 s.

    Returns ``{"built": bool, "seconds": float, "cache_dir": str, "cache_mb": float}``.
    """
    from dualhuman_builder.body.model import anny_cache_dir, anny_cache_is_warm
    from dualhuman_builder.warp_runtime import init_warp

    init_warp()  # before anny starts it, so that it starts quietly
    import anny

    was_warm = anny_cache_is_warm()
    t0 = time.perf_counter()
    anny.Anny()
    seconds = time.perf_counter() - t0
    size = sum(p.stat().st_size for p in anny_cache_dir().rglob("*") if p.is_file())
    return {"built": not was_warm, "seconds": seconds, "cache_dir": str(anny_cache_dir()), "cache_mb": size / 2**20}


def body_info(model, mapping_path=None, regions_path=None) -> dict[str, Any]:
    """Model name and version, mesh facts (watertightness, components), joint sets, the MVN
    mapping with its measured T-pose deviations, and the region sizes."""
    import numpy as np

    from dualhuman_builder.body.joints import JOINT22_BONES, JOINT22_NAMES
    from dualhuman_builder.body.mapping import load_segment_mapping, tpose_deviations
    from dualhuman_builder.body.regions import load_regions
    from dualhuman_builder.body.topology import mesh_report

    rest = model.rest()
    report = mesh_report(rest.vertices[0].detach().cpu().numpy(), model.faces.cpu().numpy())
    mapping = load_segment_mapping(mapping_path, model.bone_names, model.num_vertices)
    dev = tpose_deviations(model, mapping)
    regions = load_regions(model, regions_path)
    counts = np.bincount(regions.vertex_region, minlength=len(regions.names))
    heights = rest.vertices[0, :, 1]
    return {
        "model": model.name,
        "version": model.version,
        "vertices": report.num_vertices,
        "faces": report.num_faces,
        "bones": list(model.bone_names),
        "shape_names": list(model.shape_names),
        "stature_m_default_shape": float(heights.max() - heights.min()),
        "mesh": report,
        "joints22": list(zip(JOINT22_NAMES, JOINT22_BONES)),
        "mapping_path": str(mapping.path),
        "mapping": [(s, m.bone, m.tolerance_deg, dev[s]) for s, m in mapping.segments.items()],
        "regions": list(zip(regions.names, counts.tolist())),
    }

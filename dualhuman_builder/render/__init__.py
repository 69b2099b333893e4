"""Render stage: synthetic multi-view images of the fitted pair with Mitsuba 3.

A ring of cameras around the two bodies (plus cameras from a rig file) renders RGB, depth
(camera z), instance masks, 2D keypoints with per-joint visibility and visibility statistics;
camera parameters are stored in the OpenCV convention (the renderer converts to Mitsuba's).

- :mod:`.mitsuba_env`: which Mitsuba variant renders here (cuda > llvm > scalar), probed safely;
- :mod:`.cameras`: OpenCV cameras, their Mitsuba sensors, rings and rig files;
- :mod:`.template`: render templates (floor, lights, materials) in ``render_templates/``;
- :mod:`.renderer`: :class:`SequenceRenderer`, one scene per sequence, vertices updated per frame;
- :mod:`.annotations`: keypoints, the visibility rule and its statistics;
- :mod:`.stage`: :func:`render_sequence` (a folder, resumable) and :func:`run_render` (workspace);
- :mod:`.preview`: quick stills for the demo.

Everything below is re-exported lazily, so that importing this package imports neither mitsuba
nor numpy-heavy modules, and ``python -m dualhuman_builder.render.mitsuba_env`` (the probe's child
process) runs that module fresh.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from dualhuman_builder.render.annotations import annotate_view, keypoint_visibility, visibility_statistics
    from dualhuman_builder.render.cameras import Camera, CameraError, load_cameras, ring_cameras, save_cameras
    from dualhuman_builder.render.mitsuba_env import (
        LLVM_CANDIDATES,
        PREFERRED_VARIANTS,
        VariantProbe,
        configure_llvm,
        find_llvm,
        llvm_path_from_user,
        nvidia_gpus,
        pick_variant,
        probe_variant,
    )
    from dualhuman_builder.render.renderer import RenderError, SequenceRenderer, body_model_uvs, choose_variant
    from dualhuman_builder.render.stage import read_depth_exr, render_sequence, run_render, stage_cameras
    from dualhuman_builder.render.template import RenderTemplate, TemplateError, available_templates, load_template

_EXPORTS = {
    "dualhuman_builder.render.mitsuba_env": (
        "LLVM_CANDIDATES", "PREFERRED_VARIANTS", "VariantProbe", "configure_llvm", "find_llvm",
        "llvm_path_from_user", "nvidia_gpus", "pick_variant", "probe_variant",
    ),
    "dualhuman_builder.render.cameras": ("Camera", "CameraError", "load_cameras", "ring_cameras", "save_cameras"),
    "dualhuman_builder.render.template": ("RenderTemplate", "TemplateError", "available_templates", "load_template"),
    "dualhuman_builder.render.renderer": ("RenderError", "SequenceRenderer", "body_model_uvs", "choose_variant"),
    "dualhuman_builder.render.annotations": ("annotate_view", "keypoint_visibility", "visibility_statistics"),
    "dualhuman_builder.render.stage": ("read_depth_exr", "render_sequence", "run_render", "stage_cameras"),
}  # fmt: skip
_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = [
    "Camera", "CameraError", "LLVM_CANDIDATES", "PREFERRED_VARIANTS", "RenderError", "RenderTemplate",
    "SequenceRenderer", "TemplateError", "VariantProbe", "annotate_view", "available_templates", "body_model_uvs",
    "choose_variant", "configure_llvm", "find_llvm", "keypoint_visibility", "llvm_path_from_user", "load_cameras",
    "load_template", "nvidia_gpus", "pick_variant", "probe_variant", "read_depth_exr", "render_sequence",
    "ring_cameras", "run_render", "save_cameras", "stage_cameras", "visibility_statistics",
]  # fmt: skip
assert sorted(__all__) == sorted(_MODULE_OF)


def __getattr__(name: str):
    if name in _MODULE_OF:
        return getattr(importlib.import_module(_MODULE_OF[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""Render stage: synthetic multi-view images of the fitted pair with Mitsuba 3.

A ring of cameras around the two bodies renders RGB, depth, instance masks, 2D keypoints and
per-joint visibility, with camera parameters stored in the OpenCV convention (the renderer
converts to Mitsuba's internally). The scene is built once per sequence and only vertex positions
change per frame. The renderer itself comes with a later issue; this package already decides
*which* Mitsuba variant works on this machine (:mod:`.mitsuba_env`).

The helpers below are re-exported lazily, so that ``python -m
dualhuman_builder.render.mitsuba_env`` (the probe's child process) runs that module fresh.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
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

__all__ = [
    "LLVM_CANDIDATES",
    "PREFERRED_VARIANTS",
    "VariantProbe",
    "configure_llvm",
    "find_llvm",
    "llvm_path_from_user",
    "nvidia_gpus",
    "pick_variant",
    "probe_variant",
]


def __getattr__(name: str):
    if name in __all__:
        return getattr(importlib.import_module("dualhuman_builder.render.mitsuba_env"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""The body model: anny in the toolkit's Y-up world, its joint sets, the MVN mapping, regions.

See :mod:`dualhuman_builder.body.model` for the pose parameterisation.

The names below are imported on first use (PEP 562), so that a module needing only the MVN
segment table (the capture decoders, their decoding process) does not load torch and anny.
"""

from __future__ import annotations

import importlib

#: Public name -> the submodule that defines it.
_WHERE = {
    "COCO17": "joints", "JOINT22_BONES": "joints", "JOINT22_NAMES": "joints", "JOINT22_PARENTS": "joints",
    "tpose": "joints", "MVN_SEGMENTS": "mapping", "load_segment_mapping": "mapping", "tpose_deviations": "mapping",
    "BodyModel": "model", "BodyOutput": "model", "anny_cache_is_warm": "model", "get_body_model": "model",
    "BodyRegions": "regions", "load_regions": "regions", "shape_for_stature": "shape", "stature": "shape",
}  # fmt: skip

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_WHERE))

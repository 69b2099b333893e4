"""The body model: anny in the toolkit's Y-up world, its joint sets, the MVN mapping, regions.

See :mod:`dualhuman_builder.body.model` for the pose parameterisation.
"""

from dualhuman_builder.body.joints import COCO17, JOINT22_BONES, JOINT22_NAMES, JOINT22_PARENTS, tpose
from dualhuman_builder.body.mapping import MVN_SEGMENTS, load_segment_mapping, tpose_deviations
from dualhuman_builder.body.model import BodyModel, BodyOutput, anny_cache_is_warm, get_body_model
from dualhuman_builder.body.regions import BodyRegions, load_regions
from dualhuman_builder.body.shape import shape_for_stature, stature

__all__ = [
    "BodyModel", "BodyOutput", "BodyRegions", "COCO17", "JOINT22_BONES", "JOINT22_NAMES",
    "JOINT22_PARENTS", "MVN_SEGMENTS", "anny_cache_is_warm", "get_body_model", "load_regions",
    "load_segment_mapping", "shape_for_stature", "stature", "tpose", "tpose_deviations",
]  # fmt: skip

"""What the fit reads of each actor (:class:`ActorInput`) and how it is made from fused skeletons.

Frames are the synced timeline's (``T`` of them, one per ``1 / fps`` s); positions are metres in the
tracker world (Y up); orientations are ``xyzw`` quaternions of the 23 MVN segments.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.errors import DualhumanError


class FitError(DualhumanError):
    """The fit cannot run on this input."""


@dataclass
class ActorInput:
    """What the fitter needs of one actor (``T`` frames on the timeline, ``K`` trackers)."""

    name: str
    shape: dict  # anny phenotype (calibrated or registered)
    seg_rot: np.ndarray  # (T, 23, 4) xyzw fused segment orientations, tracker world
    pelvis: np.ndarray  # (T, 3) fused pelvis origin (m)
    valid: np.ndarray  # (T,) bool: frames with suit data
    trk_pos: np.ndarray  # (T, K, 3) tracker positions (m; nan where missing)
    trk_valid: np.ndarray  # (T, K) bool
    trk_segment: np.ndarray  # (K,) the MVN segment each tracker is mounted on
    trk_offset: np.ndarray  # (K, 3) the tracker's offset in its segment's frame (m)
    ankles: np.ndarray  # (T, 2, 3) fused LeftFoot, RightFoot origins (m; stance detection)


def inputs_from_fused(fused: list, shapes: dict[str, dict]) -> list[ActorInput]:
    """:class:`ActorInput` per :class:`~dualhuman_builder.fit.fuse.FusedActor`; ``shapes``: actor name ->
    anny phenotype."""
    out = []
    lf, rf = MVN_SEGMENTS.index("LeftFoot"), MVN_SEGMENTS.index("RightFoot")
    for f in fused:
        sk = f.skeleton
        valid = np.asarray(sk.orientation_valid).all(1)
        out.append(ActorInput(name=sk.actor, shape=shapes[sk.actor], seg_rot=np.asarray(sk.orientations),
                              pelvis=np.asarray(sk.positions[:, 0]), valid=valid, trk_pos=f.trk_pos, trk_valid=f.trk_valid,
                              trk_segment=f.trk_segment, trk_offset=f.trk_offset,
                              ankles=np.asarray(sk.positions[:, [lf, rf]])))  # fmt: skip
    return out

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
    #: (23,) trust in each MVN segment's orientation, 1 measured, 0 where no sensor measured it (the legs of an
    #: upper-body MVN recording: a fixed pose, not the actor's); None: every segment measured
    segment_weight: np.ndarray | None = None
    #: RMS (m) of the suit's segment lengths against the anny shape calibrated to them
    #: (:attr:`~dualhuman_builder.fit.calibrate.ShapeCalibration.rms_mm`): how far the suit's skeleton is from any
    #: anny body, per take (:mod:`~dualhuman_builder.fit.mounts`); None for a registered shape (not measured)
    skeleton_rms_m: float | None = None

    @property
    def unmeasured(self) -> tuple[str, ...]:
        """The MVN segments whose :attr:`segment_weight` is 0."""
        if self.segment_weight is None:
            return ()
        return tuple(g for g, w in zip(MVN_SEGMENTS, self.segment_weight) if w == 0)


def segment_weights(unmeasured) -> np.ndarray | None:
    """``(23,)`` :attr:`ActorInput.segment_weight` (MVN order): 0 for each segment named in ``unmeasured``,
    1 elsewhere; None when it names none. A name that is no MVN segment raises :class:`FitError`."""
    unmeasured = tuple(unmeasured or ())
    if not unmeasured:
        return None
    unknown = [g for g in unmeasured if g not in MVN_SEGMENTS]
    if unknown:
        raise FitError(f"unmeasured segments {unknown} are not MVN segments")
    return np.array([0.0 if g in unmeasured else 1.0 for g in MVN_SEGMENTS])


def inputs_from_fused(fused: list, shapes: dict[str, dict], unmeasured: dict | None = None,
                      skeleton_rms: dict[str, float] | None = None) -> list[ActorInput]:  # fmt: skip
    """:class:`ActorInput` per :class:`~dualhuman_builder.fit.fuse.FusedActor`; ``shapes``: actor name ->
    anny phenotype; ``unmeasured``: actor name -> the MVN segments no sensor measured
    (:func:`segment_weights`; the sync report's ``imported`` says which for an imported take);
    ``skeleton_rms``: actor name -> :attr:`ActorInput.skeleton_rms_m` (m), for the actors whose shape was
    calibrated from the suit."""
    out = []
    lf, rf = MVN_SEGMENTS.index("LeftFoot"), MVN_SEGMENTS.index("RightFoot")
    for f in fused:
        sk = f.skeleton
        valid = np.asarray(sk.orientation_valid).all(1)
        out.append(ActorInput(name=sk.actor, shape=shapes[sk.actor], seg_rot=np.asarray(sk.orientations),
                              pelvis=np.asarray(sk.positions[:, 0]), valid=valid, trk_pos=f.trk_pos, trk_valid=f.trk_valid,
                              trk_segment=f.trk_segment, trk_offset=f.trk_offset,
                              ankles=np.asarray(sk.positions[:, [lf, rf]]),
                              segment_weight=segment_weights((unmeasured or {}).get(sk.actor)),
                              skeleton_rms_m=(skeleton_rms or {}).get(sk.actor)))  # fmt: skip
    return out

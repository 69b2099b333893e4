"""Ground-truth Xsens-style segment kinematics of a body track.

MVN reports, per body segment, a global orientation and the position of the segment's origin.
At the calibration T-pose every segment's frame is the actor's own frame: x forward, y left,
z up. So for a body track we define, for each of the 23 MVN segments mapped to an anny bone by
``rigs/mvn_anny.toml``:

* position: the head (joint centre) of the mapped bone, world metres;
* orientation: ``R_seg(t) = A_bone(t) @ A_bone(T-pose)^T @ B`` where ``A`` are world-aligned
  global rotations (see :mod:`dualhuman_builder.body.model`) and ``B`` (:data:`SEGMENT_TPOSE_FRAME`)
  holds the segment axes (forward, left, up) of a body at identity orientation in world
  coordinates (+Z, +X, +Y). In anny's T-pose every segment orientation is therefore ``B``
  rotated by the body's heading, exactly as MVN reports a calibrated actor in T-pose.
"""

from __future__ import annotations

import numpy as np
import roma
import torch

from dualhuman_builder.body.joints import tpose
from dualhuman_builder.body.mapping import MVN_SEGMENTS, SEGMENT_TPOSE_FRAME, SegmentMapping, load_segment_mapping
from dualhuman_builder.tracks import BodyTrack, SkeletonTrack



def segment_kinematics(track: BodyTrack, mapping: SegmentMapping | None = None, model=None) -> SkeletonTrack:
    """The 23 MVN segments of ``track`` as a :class:`SkeletonTrack` (orientations ``(T, 23, 4)``
    xyzw, positions ``(T, 23, 3)``), timestamped ``frame / fps`` on both clocks."""
    from dualhuman_builder.body.model import get_body_model

    model = model or get_body_model()
    mapping = mapping or load_segment_mapping()
    bones = [model.bone_index(mapping.bone_of(s)) for s in MVN_SEGMENTS]
    with torch.no_grad():
        local = roma.rotvec_to_rotmat(torch.tensor(np.array(track.pose), dtype=torch.float64))
        glob = model.local_to_global(local)[:, bones]  # (T, 23, 3, 3)
        shape = torch.tensor(np.array(track.shape), dtype=model.dtype)
        t_local = roma.rotvec_to_rotmat(tpose(model, shape).double())
        t_glob = model.local_to_global(t_local[None])[0, bones]  # (23, 3, 3)
    b = torch.tensor(SEGMENT_TPOSE_FRAME, dtype=torch.float64)
    rot = glob @ t_glob.transpose(-1, -2) @ b
    quat = roma.rotmat_to_unitquat(rot).numpy()  # xyzw
    heads = track.bone_heads()[:, bones].astype(np.float64)
    t_ns = np.round(np.arange(track.num_frames) / track.fps * 1e9).astype(np.int64)
    return SkeletonTrack(segment_names=MVN_SEGMENTS, orientations=quat, positions=heads, device_time_ns=t_ns,
                         host_time_ns=t_ns, actor=track.actor, fps=track.fps,
                         meta={"ground_truth": True, "mapping": str(mapping.path)})  # fmt: skip


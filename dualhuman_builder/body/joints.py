"""Joint sets on the anny skeleton, and anny's T-pose.

``JOINT22_NAMES``: HumanML3D's 22 joints in its order (the first 22 SMPL joints), used by the motion
features. Each is the head (joint centre) of one anny bone, :data:`JOINT22_BONES`; anny has five
spine bones where SMPL has three, so spine1/2/3 take the anny spine bones at the nearest heights
(measured on the average body: spine03 0.14 m, spine02 0.21 m, spine01 0.35 m above the pelvis,
against SMPL's ~0.11, ~0.25, ~0.31 m), and the foot joint is the base of the middle toe (the
ball of the foot, where SMPL's foot joint sits).

``COCO17``: the 17 COCO keypoints, regressed from vertices with anny's own COCO regressor.
"""

from __future__ import annotations

import numpy as np
import roma
import torch

JOINT22_NAMES = (
    "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
    "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck", "left_collar",
    "right_collar", "head", "left_shoulder", "right_shoulder", "left_elbow", "right_elbow",
    "left_wrist", "right_wrist",
)  # fmt: skip

JOINT22_BONES = (
    "root", "upperleg01.L", "upperleg01.R", "spine03", "lowerleg01.L", "lowerleg01.R", "spine02",
    "foot.L", "foot.R", "spine01", "toe3-1.L", "toe3-1.R", "neck01", "clavicle.L",
    "clavicle.R", "head", "upperarm01.L", "upperarm01.R", "lowerarm01.L", "lowerarm01.R",
    "wrist.L", "wrist.R",
)  # fmt: skip

#: Parent of each of the 22 joints (HumanML3D / SMPL kinematic tree), -1 for the pelvis.
JOINT22_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19)

COCO17 = (
    "nose", "left_eye", "right_eye", "left_ear", "right_ear", "left_shoulder", "right_shoulder",
    "left_elbow", "right_elbow", "left_wrist", "right_wrist", "left_hip", "right_hip",
    "left_knee", "right_knee", "left_ankle", "right_ankle",
)  # fmt: skip

#: For each arm: (bone rotated, bone whose head marks the far end of the segment).
_TPOSE_ARM_CHAIN = (
    ("upperarm01", "lowerarm01"),
    ("lowerarm01", "wrist"),
    ("wrist", "finger3-1"),
)


def _minimal_rotation(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Smallest rotation matrix taking direction ``a (3,)`` onto direction ``b (3,)``."""
    a = a / a.norm()
    b = b / b.norm()
    axis = torch.linalg.cross(a, b)
    s = axis.norm()
    angle = torch.atan2(s, (a * b).sum())
    if s < 1e-9:
        return torch.eye(3, dtype=a.dtype, device=a.device)
    return roma.rotvec_to_rotmat(axis / s * angle)


def tpose(model, shape=None) -> torch.Tensor:
    """Pose ``(J, 3)`` (rotation vectors) putting anny in a T-pose: arms straight out sideways.

    Starting from anny's rest A-pose, the upper arm, forearm and hand of each side are turned
    (smallest rotation each) onto the lateral axis: +X for the left arm, -X for the right. Legs,
    spine, neck and head keep their rest directions. Depends slightly on ``shape``.
    """
    rest = model.rest(shape)
    heads = rest.bone_heads[0]
    glob = torch.eye(3, dtype=model.dtype, device=model.device).repeat(model.num_bones, 1, 1)
    for side, sign in (("L", 1.0), ("R", -1.0)):
        target = torch.tensor([sign, 0.0, 0.0], dtype=model.dtype, device=model.device)
        for bone, end in _TPOSE_ARM_CHAIN:
            b, e = model.bone_index(f"{bone}.{side}"), model.bone_index(f"{end}.{side}")
            rot = _minimal_rotation(heads[e] - heads[b], target)
            # this bone and everything below it take this global rotation until overridden
            for c in _descendants(model.bone_parents, b):
                glob[c] = rot
    local = model.global_to_local(glob[None])[0]
    return roma.rotmat_to_rotvec(local)


def _descendants(parents: np.ndarray, bone: int) -> list[int]:
    out = [bone]
    for c in range(bone + 1, len(parents)):
        if parents[c] in out:
            out.append(c)
    return out

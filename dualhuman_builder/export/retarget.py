"""Retargeting a motion to a format's reference skeleton, so its features fall in the distribution that
the format's pretrained models and evaluators were trained on.

Rule (HumanML3D's ``uniform_skeleton`` in ``motion_representation.ipynb``): every bone keeps its
direction on every frame and takes the reference skeleton's length; the root path is scaled by the
leg-length ratio. HumanML3D does this by inverse kinematics onto ``t2m_raw_offsets`` and forward
kinematics with the reference offsets (``t2m_raw_offsets`` times the bone lengths of its reference
subject ``000021``, frame 0), which keeps each bone's direction exactly; here the same is done
directly on the bone vectors (:func:`retarget_joints`).

Root path: scaled by ``s = (L_ref[right knee] + L_ref[right ankle]) / (L_src[right knee] + L_src[right
ankle])`` (thigh plus shin, HumanML3D's ``l_idx1, l_idx2 = 5, 8``) about the root's floor point at
frame 0, ``(root_x(0), floor, root_z(0))``, all three axes, so the stride matches the new legs and
a planted foot does not slide more than the differing bone ratios make it; then the body is moved
vertically so that its lowest joint over the motion is on the source's floor again. For one motion
this is what HumanML3D does (it scales about the world origin, then puts the floor at y = 0 and the
root of frame 0 at the origin). ``L_src`` is each bone's mean length over the frames (HumanML3D takes
frame 0; a body model's bones are rigid, so both agree, and the mean is steadier for measured joints).
For a pair, each person is scaled about its own starting point, so their placement at frame 0 is kept;
afterwards the spacing differs by each person's displacement times ``s - 1``, and contacts between
the two (hands meeting) are not preserved where the arms change length.

Reference skeletons (:data:`RETARGET_CHOICES`):

* ``humanml3d``: :data:`HUMANML3D_BONE_LENGTHS`, the bone lengths of HumanML3D's shipped sample
  ``HumanML3D/new_joints/012314.npy`` (EricGuo5513/HumanML3D), averaged over its frames, where they
  agree to 2e-6 m (float32): every HumanML3D clip is retargeted to subject 000021's frame-0 lengths,
  so these are those lengths. Directions are :data:`~dualhuman_builder.export.features.REST_DIRECTIONS`
  (``t2m_raw_offsets``). Left and right differ by up to 7 mm, as in 000021.
* ``interhuman``: not available. InterHuman is not retargeted by its authors (InterGen's
  ``process_motion_np`` has ``uniform_skeleton`` commented out; each subject keeps its SMPL-H shape),
  and no published source gives the SMPL neutral skeleton's bone lengths in numbers (they come from
  the licensed SMPL model file). :func:`reference_lengths` raises a DualhumanError saying so; pass
  your own 21 lengths (for example measured on SMPL's neutral joints) as ``retarget=`` in Python.
* ``none``: no change; the output is bit-for-bit what it is without the option.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from dualhuman_builder.body.joints import JOINT22_NAMES, JOINT22_PARENTS
from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.export.features import NUM_JOINTS, check_joints

RETARGET_CHOICES = ("none", "humanml3d", "interhuman")
#: Bone lengths (m) of HumanML3D's reference skeleton, the bone ending at joint ``k`` at index ``k``
#: (index 0, the root, unused): measured on ``HumanML3D/new_joints/012314.npy`` of EricGuo5513/HumanML3D.
HUMANML3D_BONE_LENGTHS = np.array([
    0.0, 0.103074, 0.109883, 0.131568, 0.393623, 0.390188, 0.143190, 0.432433, 0.425643, 0.057365, 0.143382,
    0.149419, 0.219360, 0.137487, 0.143383, 0.103039, 0.131614, 0.122984, 0.256840, 0.263092, 0.266012, 0.269876,
])  # fmt: skip
#: Joints whose bones (thigh, shin) make the leg length of the root scale (HumanML3D's ``l_idx1, l_idx2``).
LEG_JOINTS = (5, 8)
_PARENTS = np.asarray(JOINT22_PARENTS)


def reference_lengths(retarget) -> np.ndarray | None:
    """The reference bone lengths ``(22,)`` (m, index 0 unused) that ``retarget`` names: ``"none"`` ->
    None, ``"humanml3d"`` -> :data:`HUMANML3D_BONE_LENGTHS`, or 21 / 22 positive lengths given as an
    array (bones of joints 1..21, or 22 with the root's ignored). DualhumanError for ``"interhuman"``
    (no published numbers, module docstring), an unknown name or unusable lengths."""
    if retarget is None or (isinstance(retarget, str) and retarget == "none"):
        return None
    if isinstance(retarget, str):
        if retarget == "humanml3d":
            return HUMANML3D_BONE_LENGTHS.copy()
        if retarget == "interhuman":
            raise DualhumanError(
                "no reference skeleton for InterHuman: its data is not retargeted (each subject keeps its SMPL-H "
                "shape) and no published source gives the SMPL neutral skeleton's bone lengths",
                fix="use --retarget humanml3d or --retarget none; from Python pass retarget= your own 21 bone "
                    "lengths (m), e.g. measured on SMPL's neutral joints")  # fmt: skip
        raise DualhumanError(f"unknown retarget {retarget!r}", fix=f"choose one of {', '.join(RETARGET_CHOICES)}")
    lengths = np.asarray(retarget, dtype=np.float64).reshape(-1)
    if lengths.shape == (NUM_JOINTS - 1,):
        lengths = np.concatenate([[0.0], lengths])
    if lengths.shape != (NUM_JOINTS,) or not np.isfinite(lengths).all() or not (lengths[1:] > 0).all():
        raise DualhumanError(f"retarget lengths must be 21 (or 22) positive finite metres, got shape {lengths.shape}",
                             fix="give the bone lengths of joints 1..21 in HumanML3D's joint order")  # fmt: skip
    lengths[0] = 0.0
    return lengths


def bone_lengths(joints) -> np.ndarray:
    """Bone lengths ``(T, 21)`` (m) of ``joints (T, 22, 3)``: bone ``k - 1`` ends at joint ``k``."""
    j = np.asarray(joints, dtype=np.float64)
    return np.linalg.norm(j[:, 1:] - j[:, _PARENTS[1:]], axis=-1)


def retarget_joints(joints, lengths) -> tuple[np.ndarray, dict[str, Any]]:
    """``(retargeted joints (T, 22, 3) float64, report)`` of ``joints (T, 22, 3)`` world metres, Y up,
    onto the skeleton ``lengths (22,)`` (m, index 0 unused): each bone keeps its direction per frame and
    takes its reference length, the root path is scaled by the leg ratio about the frame-0 floor point
    and the lowest joint is put back on the source's floor (module docstring).

    ``report``: ``root_scale`` (the leg ratio), ``ratio_min``/``ratio_max``/``ratio_mean`` over the 21
    bones of reference length / source length (mean over frames), ``ratios`` per joint name, and
    ``source_length_spread`` (m, the largest change of a source bone's length over the frames).
    ValueError on joints that are not ``(T, 22, 3)`` finite, or a bone of zero length."""
    j = check_joints(joints, min_frames=1)
    ref = np.asarray(lengths, dtype=np.float64)
    bones = j[:, 1:] - j[:, _PARENTS[1:]]
    src = np.linalg.norm(bones, axis=-1)  # (T, 21)
    if (src < 1e-9).any():
        t, b = np.argwhere(src < 1e-9)[0]
        raise ValueError(f"joint {JOINT22_NAMES[b + 1]} coincides with its parent at frame {t}: no bone direction")
    mean_src = src.mean(axis=0)
    scale = float(ref[list(LEG_JOINTS)].sum() / mean_src[[k - 1 for k in LEG_JOINTS]].sum())
    floor = float(j[..., 1].min())
    anchor = np.array([j[0, 0, 0], floor, j[0, 0, 2]])
    out = np.empty_like(j)
    out[:, 0] = anchor + scale * (j[:, 0] - anchor)
    unit = bones / src[..., None]
    for k in range(1, NUM_JOINTS):  # parents come before their children
        out[:, k] = out[:, _PARENTS[k]] + ref[k] * unit[:, k - 1]
    out[..., 1] += floor - out[..., 1].min()
    ratios = ref[1:] / mean_src
    report = {"root_scale": scale, "ratio_min": float(ratios.min()), "ratio_max": float(ratios.max()),
              "ratio_mean": float(ratios.mean()),
              "ratios": {JOINT22_NAMES[k]: float(ratios[k - 1]) for k in range(1, NUM_JOINTS)},
              "source_length_spread": float((src.max(axis=0) - src.min(axis=0)).max())}  # fmt: skip
    return out, report


def summarize(reports: list[dict[str, Any]]) -> dict[str, Any]:
    """Per-bone ``{joint name: [min, max]}`` ratio over ``reports`` (of :func:`retarget_joints`) and the
    overall ``ratio_min``/``ratio_max``/``ratio_mean``, ``root_scale_min``/``root_scale_max``."""
    if not reports:
        return {}
    names = list(reports[0]["ratios"])
    per = {n: [min(r["ratios"][n] for r in reports), max(r["ratios"][n] for r in reports)] for n in names}
    return {"persons": len(reports), "ratio_min": min(r["ratio_min"] for r in reports),
            "ratio_max": max(r["ratio_max"] for r in reports),
            "ratio_mean": float(np.mean([r["ratio_mean"] for r in reports])),
            "root_scale_min": min(r["root_scale"] for r in reports),
            "root_scale_max": max(r["root_scale"] for r in reports), "per_bone": per}  # fmt: skip


__all__ = [
    "HUMANML3D_BONE_LENGTHS",
    "LEG_JOINTS",
    "RETARGET_CHOICES",
    "bone_lengths",
    "reference_lengths",
    "retarget_joints",
    "summarize",
]  # fmt: skip

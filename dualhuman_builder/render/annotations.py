"""2D keypoints of both actors per view, with per-joint visibility from the rendered depth and mask.

Keypoints are the world joints (HumanML3D's 22, :data:`~dualhuman_builder.body.joints.JOINT22_NAMES`,
and COCO's 17, :data:`~dualhuman_builder.body.joints.COCO17`) projected with
:meth:`.cameras.Camera.project` (OpenCV, pixel centres at +0.5). Stored as ``(..., 3)`` float32
rows ``(u, v, visible)``: ``u, v`` in pixels (NaN behind the camera), ``visible`` 0 or 1.

Visibility rule (a joint lies *inside* its body, so its own surface always covers it from a few
centimetres in front): joint ``j`` of the actor with mask label ``L`` is visible in a view when

1. it is in front of the camera (camera z > near clip) and its pixel ``(floor(u), floor(v))`` lies
   inside the image (``0 <= u < W``, ``0 <= v < H``);
2. that pixel of the instance mask shows the same actor (``mask == L``): another actor or the
   floor in front of it hides it;
3. the rendered surface there is at most ``tolerance_m`` (default 0.15 m) in front of the joint
   (``depth >= z - tolerance_m``): the actor's own arm in front of its hip hides the hip.

:func:`visibility_statistics` aggregates over a camera ring: visible rate per actor x joint, per
view x actor x joint, and per view x actor (the reaction prior's noise augmentation drops joints at
these rates).
"""

from __future__ import annotations

import numpy as np

from dualhuman_builder.render.cameras import Camera

#: How far (m) the rendered surface may lie in front of a joint that still counts as visible.
VISIBILITY_TOLERANCE_M = 0.15

VISIBILITY_RULE = ("visible = in front of the camera, pixel (floor(u), floor(v)) inside the image, instance mask "
                   "there shows the same actor, and rendered depth there >= joint camera z - tolerance_m")  # fmt: skip


def keypoint_visibility(uv: np.ndarray, z: np.ndarray, depth: np.ndarray, mask: np.ndarray, label: int,
                        tolerance_m: float = VISIBILITY_TOLERANCE_M, near: float = 0.0) -> np.ndarray:  # fmt: skip
    """Boolean visibility ``(...)`` of keypoints at pixels ``uv (..., 2)`` with camera z ``z (...)``
    (metres) for the actor drawn as ``label`` in ``mask (H, W)``, against ``depth (H, W)`` camera
    z (inf background); the rule is in the module docstring."""
    uv = np.asarray(uv, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    depth = np.asarray(depth)
    mask = np.asarray(mask)
    if depth.ndim != 2 or depth.shape != mask.shape:
        raise ValueError(f"depth and mask must be (H, W) images of one size, got {depth.shape} and {mask.shape}")
    if uv.shape[:-1] != z.shape or uv.shape[-1] != 2:
        raise ValueError(f"uv must be (..., 2) and z (...), got {uv.shape} and {z.shape}")
    h, w = depth.shape
    with np.errstate(invalid="ignore"):
        inside = np.isfinite(uv).all(-1) & (z > near) & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
    px = np.where(inside, np.floor(np.nan_to_num(uv[..., 0])), 0).astype(np.int64)
    py = np.where(inside, np.floor(np.nan_to_num(uv[..., 1])), 0).astype(np.int64)
    px, py = np.clip(px, 0, w - 1), np.clip(py, 0, h - 1)
    return inside & (mask[py, px] == label) & (depth[py, px] >= z - tolerance_m)


def annotate_view(camera: Camera, points: np.ndarray, depth: np.ndarray, mask: np.ndarray,
                  labels=(1, 2), tolerance_m: float = VISIBILITY_TOLERANCE_M) -> np.ndarray:  # fmt: skip
    """Keypoints of both actors in one view: ``points (2, J, 3)`` world metres -> ``(2, J, 3)``
    float32 rows ``(u, v, visible)``; actor ``k`` is ``labels[k]`` in ``mask``."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 3 or points.shape[0] != len(labels) or points.shape[2] != 3:
        raise ValueError(f"points must have shape ({len(labels)}, J, 3), got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("keypoints hold NaN or infinite world coordinates")
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth is {depth.shape}, camera {camera.name!r} is {camera.height}x{camera.width}")
    uv, z = camera.project(points)
    out = np.empty(points.shape, np.float32)
    out[..., :2] = uv
    for k, label in enumerate(labels):
        out[k, :, 2] = keypoint_visibility(uv[k], z[k], depth, mask, label, tolerance_m, camera.near)
    return out


def _rates(vis: np.ndarray) -> np.ndarray:
    """Mean over frames of ``vis (views, frames, 2, J)`` -> ``(views, 2, J)``."""
    return vis.mean(axis=1) if vis.shape[1] else np.zeros((vis.shape[0],) + vis.shape[2:])


def visibility_statistics(joints: np.ndarray, coco: np.ndarray, view_names, joint_names, coco_names,
                          actor_names=("actor0", "actor1"), tolerance_m: float = VISIBILITY_TOLERANCE_M) -> dict:  # fmt: skip
    """Per-joint visible rates over a camera ring, JSON-ready.

    ``joints (views, frames, 2, 22, 3)`` and ``coco (views, frames, 2, 17, 3)`` as written to
    ``keypoints.npz``. For each set: ``rate`` ``[actor][joint]`` over all views and frames,
    ``per_view`` ``{view: [actor][joint]}``, ``view_rate`` ``{view: [actor]}`` (mean over joints),
    ``overall`` (one number)."""
    doc = {"rule": VISIBILITY_RULE, "tolerance_m": tolerance_m, "views": list(view_names), "actors": list(actor_names),
           "frames": int(joints.shape[1])}  # fmt: skip
    for key, kp, names in (("joints", joints, joint_names), ("coco", coco, coco_names)):
        kp = np.asarray(kp)
        if kp.ndim != 5 or kp.shape[0] != len(view_names) or kp.shape[2] != 2 or kp.shape[4] != 3 or kp.shape[3] != len(names):
            raise ValueError(f"{key} keypoints must have shape ({len(view_names)}, frames, 2, {len(names)}, 3), got {kp.shape}")
        vis = kp[..., 2] > 0.5
        per_view = _rates(vis)
        rate = per_view.mean(axis=0)
        doc[key] = {"names": list(names), "rate": np.round(rate, 4).tolist(),
                    "per_view": {v: np.round(per_view[i], 4).tolist() for i, v in enumerate(view_names)},
                    "view_rate": {v: np.round(per_view[i].mean(axis=-1), 4).tolist() for i, v in enumerate(view_names)},
                    "overall": round(float(vis.mean()) if vis.size else 0.0, 4)}  # fmt: skip
    return doc


__all__ = ["VISIBILITY_RULE", "VISIBILITY_TOLERANCE_M", "annotate_view", "keypoint_visibility", "visibility_statistics"]

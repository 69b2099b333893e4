"""Shape calibration: one anny phenotype per actor per take, never per frame.

MVN's biomechanical model reports each segment's origin; the 22 parent-to-child distances
(pelvis to hips, hip to knee, shoulder to elbow, ...) are the actor's bone lengths as the suit was
scaled to them (the same numbers as MVN's scale message and an MVNX file's segment points). We take
their median over the valid frames of the take and solve anny's six phenotype values (gender, age,
muscle, weight, height, proportions; each in [0, 1]) so that the distances between the heads of
the mapped anny bones match, with the actor's registered stature (if any) as a further term and a
weak pull towards the registered gender and an adult age. Solved with L-BFGS on a sigmoid
parameterisation of the phenotype (so the values stay in [0, 1]), through anny's differentiable
rest pose.
"""

# ruff: noqa: B023 -- the L-BFGS closures run inside the loop iteration that defines them

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from dualhuman_builder.body.mapping import MVN_PARENTS, MVN_SEGMENTS
from dualhuman_builder.errors import DualhumanError

#: Fewest valid frames a shape calibration accepts.
MIN_FRAMES = 10


class CalibrationError(DualhumanError):
    """Not enough data to calibrate a shape."""


@dataclass
class ShapeCalibration:
    """``shape``: phenotype dict; ``lengths_m``: segment -> measured length; ``residual_mm``:
    per-segment anny-minus-measured length after the fit; ``stature_m`` of the solved shape."""

    shape: dict[str, float]
    lengths_m: dict[str, float]
    residual_mm: dict[str, float]
    rms_mm: float
    stature_m: float
    frames_used: int

    def as_dict(self) -> dict:
        return {"shape": {k: round(v, 5) for k, v in self.shape.items()}, "rms_length_error_mm": round(self.rms_mm, 3),
                "stature_m": round(self.stature_m, 4), "frames_used": self.frames_used,
                "residual_mm": {k: round(v, 2) for k, v in self.residual_mm.items()}}  # fmt: skip


def segment_offsets(orientations: np.ndarray, positions: np.ndarray, valid: np.ndarray) -> tuple[dict[str, np.ndarray], int]:
    """Median child-origin offset in the parent segment's frame, per MVN segment, over valid frames
    of ``orientations (T, 23, 4)`` xyzw and ``positions (T, 23, 3)``: ``{segment: (3,) m}``."""
    from scipy.spatial.transform import Rotation

    ok = np.asarray(valid, bool) & np.isfinite(positions).all(axis=(1, 2)) & np.isfinite(orientations).all(axis=(1, 2))
    n = int(ok.sum())
    if n < MIN_FRAMES:
        raise CalibrationError(f"only {n} valid suit frames; shape calibration needs at least {MIN_FRAMES}",
                               fix="record a longer take, or register the actor's shape with `dualhuman actor add`")  # fmt: skip
    p, q = positions[ok], orientations[ok]
    out = {}
    for c, name in enumerate(MVN_SEGMENTS):
        parent = MVN_PARENTS[name]
        if parent is None:
            continue
        j = MVN_SEGMENTS.index(parent)
        out[name] = np.median(Rotation.from_quat(q[:, j]).apply(p[:, c] - p[:, j], inverse=True), axis=0)
    return out, n


def calibrate_shape(model, orientations: np.ndarray, positions: np.ndarray, valid: np.ndarray,
                    stature_m: float | None = None, gender: float | None = None, iterations: int = 40,
                    mapping=None) -> ShapeCalibration:  # fmt: skip
    """Solve a phenotype from a suit's segments ``orientations (T, 23, 4)``, ``positions (T, 23, 3)``
    (see the module docstring). The offsets are compared as 3-D vectors in the parent segment's
    frame (66 numbers: lengths and directions, e.g. hip width and spine curve), from several
    starting phenotypes (both genders unless registered); the best fit wins."""
    from dualhuman_builder.fit.skeleton import BodyRig
    from dualhuman_builder.body.mapping import load_segment_mapping
    from dualhuman_builder.body.shape import ADULT_AGE, stature

    mapping = mapping or load_segment_mapping(bone_names=model.bone_names, num_vertices=model.num_vertices)
    offsets, n = segment_offsets(orientations, positions, valid)
    names = list(offsets)
    child = torch.as_tensor([model.bone_index(mapping.bone_of(s)) for s in names])
    parent = torch.as_tensor([model.bone_index(mapping.bone_of(MVN_PARENTS[s])) for s in names])
    parent_seg = torch.as_tensor([MVN_SEGMENTS.index(MVN_PARENTS[s]) for s in names])
    target = torch.as_tensor(np.array([offsets[s] for s in names]), dtype=model.dtype)
    # the segment frames of anny at zero pose are constant (BodyRig.seg_frame); it barely depends
    # on the shape, so it is taken from the average body
    frame = BodyRig(model, None, mapping).seg_frame.to(model.dtype)[parent_seg]  # (N, 3, 3)
    best = None
    for g in ([float(gender)] if gender is not None else [0.0, 1.0]):
        prior = {n_: 0.5 for n_ in model.shape_names}
        prior.update(age=ADULT_AGE, gender=g)
        prior_t = torch.as_tensor([prior[k] for k in model.shape_names], dtype=model.dtype)
        z = torch.logit(prior_t.clamp(0.05, 0.95)).clone().requires_grad_(True)
        opt = torch.optim.LBFGS([z], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe")

        def closure():
            opt.zero_grad()
            shape = torch.sigmoid(z)
            out = model.forward(None, shape, None, batch_size=1)
            h = out.bone_heads[0]
            o = (frame.transpose(-1, -2) @ (h[child] - h[parent])[..., None])[..., 0]
            loss = ((o - target) / 0.002).pow(2).sum()  # 2 mm per component
            if stature_m is not None:
                v = out.vertices[0, :, 1]
                loss = loss + ((v.max() - v.min() - stature_m) / 0.005).pow(2)
            loss = loss + ((shape - prior_t) / 0.5).pow(2).sum()  # weak: only where the skeleton does not decide
            loss.backward()
            return loss

        opt.step(closure)
        final = float(closure().detach())
        if best is None or final < best[0]:
            best = (final, torch.sigmoid(z).detach().clone())
    shape = best[1]
    with torch.no_grad():
        h = model.forward(None, shape, None, batch_size=1).bone_heads[0]
        d = (h[child] - h[parent]).norm(dim=-1)
        res = ((d - target.norm(dim=-1)) * 1000).tolist()
        st = stature(model, shape)
    shape_d = {k: float(v) for k, v in zip(model.shape_names, shape.tolist())}
    lengths = {s: float(np.linalg.norm(offsets[s])) for s in names}
    return ShapeCalibration(shape_d, lengths, dict(zip(names, res)), float(np.sqrt(np.mean(np.square(res)))), st, n)

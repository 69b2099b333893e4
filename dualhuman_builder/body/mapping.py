"""The Xsens MVN segment -> anny bone mapping, kept as data in ``rigs/mvn_anny.toml``.

A mapping names, for each of the 23 MVN body segments, the anny bone that takes its orientation
and the point that marks its far end, plus its direction in MVN's T-pose. See the comments at the
top of ``rigs/mvn_anny.toml`` for the fields. :func:`tpose_deviations` measures how well anny's
T-pose (:func:`~dualhuman_builder.body.joints.tpose`) reproduces those directions.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from dualhuman_builder.errors import RigError
from dualhuman_builder.resources import RIGS_DIR

#: The 23 MVN body segments in ID order (segment ID = index + 1), per the MVN streaming spec.
MVN_SEGMENTS = (
    "Pelvis", "L5", "L3", "T12", "T8", "Neck", "Head",
    "RightShoulder", "RightUpperArm", "RightForeArm", "RightHand",
    "LeftShoulder", "LeftUpperArm", "LeftForeArm", "LeftHand",
    "RightUpperLeg", "RightLowerLeg", "RightFoot", "RightToe",
    "LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "LeftToe",
)  # fmt: skip

#: Parent segment of each MVN segment (the Pelvis is the root).
MVN_PARENTS = {
    "Pelvis": None, "L5": "Pelvis", "L3": "L5", "T12": "L3", "T8": "T12", "Neck": "T8", "Head": "Neck",
    "RightShoulder": "T8", "RightUpperArm": "RightShoulder", "RightForeArm": "RightUpperArm",
    "RightHand": "RightForeArm", "LeftShoulder": "T8", "LeftUpperArm": "LeftShoulder",
    "LeftForeArm": "LeftUpperArm", "LeftHand": "LeftForeArm", "RightUpperLeg": "Pelvis",
    "RightLowerLeg": "RightUpperLeg", "RightFoot": "RightLowerLeg", "RightToe": "RightFoot",
    "LeftUpperLeg": "Pelvis", "LeftLowerLeg": "LeftUpperLeg", "LeftFoot": "LeftLowerLeg",
    "LeftToe": "LeftFoot",
}  # fmt: skip

DEFAULT_MAPPING_PATH = RIGS_DIR / "mvn_anny.toml"

#: Columns: an MVN segment's x (forward), y (left), z (up) axes in world coordinates for a body at
#: identity orientation (faces +Z, left +X, up +Y): every segment's frame at the calibration T-pose.
SEGMENT_TPOSE_FRAME = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


def body_frame_to_world(direction: Sequence[float]) -> np.ndarray:
    """``[forward, left, up]`` in an actor's own frame -> world axes of a body at identity
    orientation (faces +Z, left +X, up +Y), unit length."""
    f, l, u = (float(x) for x in direction)
    v = np.array([l, u, f])
    n = np.linalg.norm(v)
    if n == 0 or not np.isfinite(n):
        raise ValueError("direction must be a non-zero finite vector")
    return v / n


@dataclass(frozen=True)
class SegmentMap:
    segment: str
    bone: str
    also: tuple[str, ...]
    end: str  # "bone:<name>" or "vertex:<index>"
    tpose_direction: np.ndarray = field(compare=False)  # (3,) unit, world axes of a body at identity
    tolerance_deg: float

    @property
    def bones(self) -> tuple[str, ...]:
        return (self.bone, *self.also)


@dataclass(frozen=True)
class SegmentMapping:
    path: Path
    body_model: str
    segments: dict[str, SegmentMap]

    def __getitem__(self, segment: str) -> SegmentMap:
        return self.segments[segment]

    def bone_of(self, segment: str) -> str:
        return self.segments[segment].bone


def _err(path: Path, message: str, fix: str | None = None) -> RigError:
    return RigError(message, path=path, fix=fix or f"edit {path.name}; see the comments in {DEFAULT_MAPPING_PATH}")


def load_segment_mapping(
    path: str | Path | None = None,
    bone_names: Sequence[str] | None = None,
    num_vertices: int | None = None,
) -> SegmentMapping:
    """Read and check a segment mapping. Every MVN segment must be mapped exactly once, every bone
    must exist in ``bone_names`` (default: the anny rig), and no bone may take two segments."""
    path = Path(path) if path is not None else DEFAULT_MAPPING_PATH
    if bone_names is None or num_vertices is None:
        from dualhuman_builder.body.model import get_body_model

        model = get_body_model()
        bone_names = bone_names or model.bone_names
        num_vertices = num_vertices or model.num_vertices
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RigError("segment mapping file not found", path=path, fix=f"use {DEFAULT_MAPPING_PATH}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise _err(path, f"not valid TOML: {e}") from e
    segs = doc.get("segments")
    if not isinstance(segs, dict):
        raise _err(path, "no [segments.<MVN segment>] tables")
    unknown = sorted(set(segs) - set(MVN_SEGMENTS))
    if unknown:
        raise _err(path, f"unknown MVN segment names {unknown}; the 23 MVN segments are {list(MVN_SEGMENTS)}")
    missing = [s for s in MVN_SEGMENTS if s not in segs]
    if missing:
        raise _err(path, f"segments not mapped: {missing}; every MVN segment needs a bone")
    known = set(bone_names)
    owner: dict[str, str] = {}
    out: dict[str, SegmentMap] = {}
    for name in MVN_SEGMENTS:
        entry = segs[name]
        where = f"[segments.{name}]"
        if not isinstance(entry, dict) or "bone" not in entry:
            raise _err(path, f"{where} needs a 'bone'")
        also = entry.get("also", [])
        if not isinstance(also, list) or not all(isinstance(b, str) for b in also):
            raise _err(path, f"{where} 'also' must be a list of bone names")
        for bone in (entry["bone"], *also):
            if bone not in known:
                close = sorted(b for b in known if b.split(".")[0][:4] == str(bone).split(".")[0][:4])[:6]
                raise _err(
                    path,
                    f"{where} names unknown anny bone {bone!r}" + (f" (similar: {close})" if close else ""),
                    fix="list anny's bones with `dualhuman body info --bones`",
                )
            if bone in owner:
                raise _err(path, f"bone {bone!r} is mapped by both {owner[bone]} and {name}")
            owner[bone] = name
        end = entry.get("end", "")
        kind, _, ref = str(end).partition(":")
        if kind == "bone":
            if ref not in known:
                raise _err(path, f"{where} end names unknown anny bone {ref!r}")
        elif kind == "vertex":
            if not ref.isdigit() or not int(ref) < num_vertices:
                raise _err(path, f"{where} end vertex {ref!r} is not an index below {num_vertices}")
        else:
            raise _err(path, f"{where} end must be 'bone:<name>' or 'vertex:<index>', got {end!r}")
        try:
            direction = body_frame_to_world(entry["tpose_direction"])
        except (KeyError, TypeError, ValueError):
            raise _err(path, f"{where} tpose_direction must be three numbers [forward, left, up], not all zero") from None
        tol = entry.get("tolerance_deg", 10)
        if not isinstance(tol, (int, float)) or not 0 < tol <= 180:
            raise _err(path, f"{where} tolerance_deg must be in (0, 180]")
        out[name] = SegmentMap(name, entry["bone"], tuple(also), str(end), direction, float(tol))
    return SegmentMapping(path=path, body_model=str(doc.get("mapping", {}).get("body_model", "anny")), segments=out)


def tpose_deviations(model, mapping: SegmentMapping, shape=None) -> dict[str, float]:
    """Angle in degrees between each segment's direction on anny in T-pose and MVN's T-pose."""
    from dualhuman_builder.body.joints import tpose

    pose = tpose(model, shape)
    out = model.forward(pose[None], shape)
    heads = out.bone_heads[0].detach().cpu().numpy()
    verts = out.vertices[0].detach().cpu().numpy()
    result = {}
    for name, seg in mapping.segments.items():
        kind, _, ref = seg.end.partition(":")
        end = heads[model.bone_index(ref)] if kind == "bone" else verts[int(ref)]
        d = end - heads[model.bone_index(seg.bone)]
        d = d / np.linalg.norm(d)
        result[name] = float(np.degrees(np.arccos(np.clip(d @ seg.tpose_direction, -1.0, 1.0))))
    return result

"""Core data types passed between stages, each saved as a versioned ``.npz`` (see :mod:`fileio`).

* :class:`SkeletonTrack` — one actor's segments over time, as a suit/fusion stage produces them.
* :class:`BodyTrack` — one actor's body-model parameters over time; vertices and joints on demand.
* :class:`InteractionSequence` — two ``BodyTrack``s of one interaction, plus labels and text.

Frames and units follow :mod:`dualhuman_builder.conventions` (Y-up world, metres, quaternions
``(x, y, z, w)``, times in int64 ns). Arrays are stored read-only so that cached derived data
(vertices, joints) cannot go stale; build a new object to change them.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dualhuman_builder.errors import FormatError
from dualhuman_builder.fileio import load_npz, save_npz

log = logging.getLogger(__name__)

SKELETON_TRACK_VERSION = 1
BODY_TRACK_VERSION = 1
INTERACTION_SEQUENCE_VERSION = 1


def _frozen(a, dtype, shape: tuple, what: str) -> np.ndarray:
    """``a`` as a read-only array of ``dtype``; ``shape`` may hold ``None`` for free sizes."""
    arr = np.array(a, dtype=dtype, copy=True)
    if arr.ndim != len(shape) or any(s is not None and s != n for s, n in zip(shape, arr.shape)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{what} must have shape {want}, got {arr.shape}")
    arr.setflags(write=False)
    return arr


def _first_bad(mask: np.ndarray) -> tuple[int, ...]:
    return tuple(int(i) for i in np.argwhere(mask)[0])


# --------------------------------------------------------------------------------------------
@dataclass(eq=False)
class SkeletonTrack:
    """One actor's skeleton: per-frame global segment orientations and positions.

    ``segment_names (S,)``; ``orientations (T, S, 4)`` unit quaternions (x, y, z, w), each
    segment's orientation in the world frame; ``positions (T, S, 3)`` segment origins in metres;
    ``device_time_ns (T,)`` and ``host_time_ns (T,)`` int64 (host times never decrease);
    ``orientation_valid`` and ``position_valid (T, S)`` bool — values under a False are ignored
    and may be NaN. ``fps`` is the nominal rate (0 when irregular).
    """

    segment_names: tuple[str, ...]
    orientations: np.ndarray
    positions: np.ndarray
    device_time_ns: np.ndarray
    host_time_ns: np.ndarray
    orientation_valid: np.ndarray | None = None
    position_valid: np.ndarray | None = None
    actor: str = ""
    fps: float = 0.0
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        self.segment_names = tuple(str(s) for s in self.segment_names)
        if len(set(self.segment_names)) != len(self.segment_names):
            raise ValueError(f"duplicate segment names in {self.segment_names}")
        S = len(self.segment_names)
        self.orientations = _frozen(self.orientations, np.float64, (None, S, 4), "orientations")
        T = self.orientations.shape[0]
        self.positions = _frozen(self.positions, np.float64, (T, S, 3), "positions")
        self.device_time_ns = _frozen(self.device_time_ns, np.int64, (T,), "device_time_ns")
        self.host_time_ns = _frozen(self.host_time_ns, np.int64, (T,), "host_time_ns")
        ones = np.ones((T, S), dtype=bool)
        self.orientation_valid = _frozen(
            ones if self.orientation_valid is None else self.orientation_valid, bool, (T, S), "orientation_valid"
        )
        self.position_valid = _frozen(
            ones if self.position_valid is None else self.position_valid, bool, (T, S), "position_valid"
        )
        self.fps = float(self.fps)
        bad = self.orientation_valid & ~np.isfinite(self.orientations).all(-1)
        if bad.any():
            t, s = _first_bad(bad)
            raise ValueError(f"orientation of {self.segment_names[s]!r} at frame {t} is marked valid but not finite")
        norms = np.linalg.norm(np.where(self.orientation_valid[..., None], self.orientations, 1.0), axis=-1)
        bad = self.orientation_valid & (np.abs(norms - 1.0) > 1e-3)
        if bad.any():
            t, s = _first_bad(bad)
            raise ValueError(
                f"orientation of {self.segment_names[s]!r} at frame {t} is not a unit quaternion (norm {norms[t, s]:.4f})"
            )
        bad = self.position_valid & ~np.isfinite(self.positions).all(-1)
        if bad.any():
            t, s = _first_bad(bad)
            raise ValueError(f"position of {self.segment_names[s]!r} at frame {t} is marked valid but not finite")
        if T > 1 and np.any(np.diff(self.host_time_ns) < 0):
            t = int(np.flatnonzero(np.diff(self.host_time_ns) < 0)[0]) + 1
            raise ValueError(f"host_time_ns goes backwards at frame {t}")

    @property
    def num_frames(self) -> int:
        return self.orientations.shape[0]

    def segment_index(self, name: str) -> int:
        try:
            return self.segment_names.index(name)
        except ValueError:
            raise KeyError(f"no segment {name!r}; this track has {list(self.segment_names)}") from None

    def save(self, path: str | Path) -> Path:
        return save_npz(
            path,
            "SkeletonTrack",
            SKELETON_TRACK_VERSION,
            {
                "orientations": self.orientations,
                "positions": self.positions,
                "device_time_ns": self.device_time_ns,
                "host_time_ns": self.host_time_ns,
                "orientation_valid": self.orientation_valid,
                "position_valid": self.position_valid,
            },
            {"segment_names": list(self.segment_names), "actor": self.actor, "fps": self.fps, "meta": self.meta},
        )

    @classmethod
    def load(cls, path: str | Path) -> "SkeletonTrack":
        names = ("orientations", "positions", "device_time_ns", "host_time_ns", "orientation_valid", "position_valid")
        arrays, meta = load_npz(path, "SkeletonTrack", SKELETON_TRACK_VERSION, required=names)
        try:
            return cls(segment_names=meta["segment_names"], actor=meta.get("actor", ""), fps=meta.get("fps", 0.0),
                       meta=meta.get("meta", {}), **{n: arrays[n] for n in names})  # fmt: skip
        except (KeyError, ValueError) as e:
            raise FormatError(f"inconsistent SkeletonTrack: {e}", path=path) from e


# --------------------------------------------------------------------------------------------
_BODY_ARRAYS = ("pose", "transl", "shape")


@dataclass(eq=False)
class BodyTrack:
    """One actor's body-model parameters over time.

    ``pose (T, J, 3)`` rotation vectors and ``transl (T, 3)`` metres in the parameterisation of
    :mod:`dualhuman_builder.body.model`; ``shape (P,)`` one phenotype for the whole track (never per
    frame); ``fps`` frames per second; ``model``/``model_version`` the body model that defines them;
    ``bone_names (J,)`` and ``shape_names (P,)`` as that model names them.

    :meth:`vertices`, :meth:`joints`, :meth:`bone_heads` and :meth:`coco` run the model in batches
    on demand; whole-track results are cached on the object (vertices take T x V x 12 bytes:
    165 MB for 1,000 frames).
    """

    pose: np.ndarray
    transl: np.ndarray
    shape: np.ndarray
    fps: float
    bone_names: tuple[str, ...]
    shape_names: tuple[str, ...]
    model: str = "anny"
    model_version: str = ""
    actor: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        self.bone_names = tuple(self.bone_names)
        self.shape_names = tuple(self.shape_names)
        J, P = len(self.bone_names), len(self.shape_names)
        self.pose = _frozen(self.pose, np.float32, (None, J, 3), "pose")
        T = self.pose.shape[0]
        self.transl = _frozen(self.transl, np.float32, (T, 3), "transl")
        self.shape = _frozen(self.shape, np.float32, (P,), "shape")
        self.fps = float(self.fps)
        if not self.fps > 0:
            raise ValueError(f"fps must be positive, got {self.fps}")
        for name in _BODY_ARRAYS:
            a = getattr(self, name)
            if not np.isfinite(a).all():
                raise ValueError(f"{name} holds NaN or infinite values (first at index {_first_bad(~np.isfinite(a))})")
        self._cache: dict[str, np.ndarray] = {}

    @classmethod
    def from_model(cls, model, pose, transl, shape, fps: float, actor: str = "", meta=None) -> "BodyTrack":
        """A track whose names and version come from ``model`` (a
        :class:`~dualhuman_builder.body.BodyModel`)."""
        return cls(pose=pose, transl=transl, shape=shape, fps=fps, bone_names=model.bone_names,
                   shape_names=model.shape_names, model=model.name, model_version=model.version,
                   actor=actor, meta=dict(meta or {}))  # fmt: skip

    @property
    def num_frames(self) -> int:
        return self.pose.shape[0]

    # ------------------------------------------------------------------ derived data
    def _model(self, device: str):
        from dualhuman_builder.body.model import get_body_model

        model = get_body_model(device)
        if self.model != model.name or tuple(model.bone_names) != self.bone_names:
            raise ValueError(
                f"this track was made for body model {self.model!r} with {len(self.bone_names)} bones; "
                f"the installed model is {model.name!r} with {len(model.bone_names)}"
            )
        if self.model_version and self.model_version != model.version:
            log.warning("track made with %s %s, computing with %s", self.model, self.model_version, model.version)
        return model

    def compute(self, frames=None, device: str = "cpu", batch_size: int = 128) -> dict[str, np.ndarray]:
        """Run the body model over ``frames`` (default: all). Returns float32 arrays
        ``vertices (N, V, 3)``, ``joints (N, 22, 3)``, ``bone_heads (N, J, 3)`` and ``coco (N, 17, 3)``
        in world metres."""
        import torch

        model = self._model(device)
        idx = np.arange(self.num_frames)[frames if frames is not None else slice(None)]
        idx = np.atleast_1d(idx)
        shape = torch.tensor(self.shape, device=model.device)
        out: dict[str, list] = {"vertices": [], "joints": [], "bone_heads": [], "coco": []}
        with torch.no_grad():
            for start in range(0, len(idx), batch_size):
                sel = idx[start : start + batch_size]
                res = model.forward(
                    torch.as_tensor(self.pose[sel], device=model.device),
                    shape,
                    torch.as_tensor(self.transl[sel], device=model.device),
                )
                out["vertices"].append(res.vertices.cpu().numpy())
                out["joints"].append(res.joints.cpu().numpy())
                out["bone_heads"].append(res.bone_heads.cpu().numpy())
                out["coco"].append(model.coco(res.vertices).cpu().numpy())
        return {k: np.concatenate(v) if v else np.zeros((0,), np.float32) for k, v in out.items()}

    def _cached(self, key: str) -> np.ndarray:
        if key not in self._cache and key in ("joints", "bone_heads"):
            self._store(self._kinematics())  # no skinning needed (the export asks for joints only)
        if key not in self._cache:  # joints always come from the kinematics path, whatever ran first
            self._store({k: v for k, v in self.compute().items() if k not in ("joints", "bone_heads")})
        return self._cache[key]

    def _store(self, arrays: dict[str, np.ndarray]) -> None:
        for k, v in arrays.items():
            v.setflags(write=False)
            self._cache[k] = v

    def _kinematics(self, batch_size: int = 512) -> dict[str, np.ndarray]:
        """``bone_heads (T, J, 3)`` and ``joints (T, 22, 3)`` float32 by forward kinematics only."""
        import torch

        model = self._model("cpu")
        heads = []
        with torch.no_grad():
            for s0 in range(0, self.num_frames, batch_size):
                sl = slice(s0, s0 + batch_size)
                heads.append(model.bone_heads(self.pose[sl], self.shape, self.transl[sl]).cpu().numpy())
        h = np.concatenate(heads).astype(np.float32, copy=False)
        return {"bone_heads": h, "joints": np.ascontiguousarray(h[:, model.joint22_index.cpu().numpy()])}

    def vertices(self) -> np.ndarray:
        """``(T, V, 3)`` float32 mesh vertices, world metres (cached)."""
        return self._cached("vertices")

    def joints(self) -> np.ndarray:
        """``(T, 22, 3)`` HumanML3D-order joints, world metres (cached)."""
        return self._cached("joints")

    def bone_heads(self) -> np.ndarray:
        """``(T, J, 3)`` anny bone heads (joint centres), world metres (cached)."""
        return self._cached("bone_heads")

    def coco(self) -> np.ndarray:
        """``(T, 17, 3)`` COCO keypoints regressed from the vertices by anny's regressor (cached)."""
        return self._cached("coco")

    # ------------------------------------------------------------------ disk
    def _arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        return {prefix + n: getattr(self, n) for n in _BODY_ARRAYS}

    def _meta(self) -> dict[str, Any]:
        return {"fps": self.fps, "bone_names": list(self.bone_names), "shape_names": list(self.shape_names),
                "model": self.model, "model_version": self.model_version, "actor": self.actor, "meta": self.meta}  # fmt: skip

    @classmethod
    def _from(cls, arrays: dict, meta: dict, prefix: str = "") -> "BodyTrack":
        return cls(**{n: arrays[prefix + n] for n in _BODY_ARRAYS}, fps=meta["fps"], bone_names=meta["bone_names"],
                   shape_names=meta["shape_names"], model=meta["model"], model_version=meta.get("model_version", ""),
                   actor=meta.get("actor", ""), meta=meta.get("meta", {}))  # fmt: skip

    def save(self, path: str | Path) -> Path:
        return save_npz(path, "BodyTrack", BODY_TRACK_VERSION, self._arrays(), self._meta())

    @classmethod
    def load(cls, path: str | Path) -> "BodyTrack":
        arrays, meta = load_npz(path, "BodyTrack", BODY_TRACK_VERSION, required=_BODY_ARRAYS)
        try:
            return cls._from(arrays, meta)
        except (KeyError, ValueError) as e:
            raise FormatError(f"inconsistent BodyTrack: {e}", path=path) from e


# --------------------------------------------------------------------------------------------
@dataclass(eq=False)
class InteractionSequence:
    """Two actors' :class:`BodyTrack`s over the same frames of one interaction.

    ``actors``: exactly two tracks with equal frame counts and fps; ``take`` and ``frame_range``
    ``(start, stop)`` locate the frames in their take (stop exclusive); ``labels``: interaction
    labels; ``text``: free-text descriptions; ``meta``: anything else JSON-serialisable.
    """

    actors: tuple[BodyTrack, BodyTrack]
    take: str = ""
    frame_range: tuple[int, int] | None = None
    labels: tuple[str, ...] = ()
    text: tuple[str, ...] = ()
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self):
        self.actors = tuple(self.actors)
        if len(self.actors) != 2:
            raise ValueError(f"an InteractionSequence holds two actors, got {len(self.actors)}")
        a, b = self.actors
        if a.num_frames != b.num_frames:
            raise ValueError(f"actors have different frame counts: {a.num_frames} and {b.num_frames}")
        if a.fps != b.fps:
            raise ValueError(f"actors have different fps: {a.fps} and {b.fps}")
        if self.frame_range is None:
            self.frame_range = (0, a.num_frames)
        self.frame_range = (int(self.frame_range[0]), int(self.frame_range[1]))
        if self.frame_range[1] - self.frame_range[0] != a.num_frames:
            raise ValueError(f"frame_range {self.frame_range} does not span the {a.num_frames} frames")
        self.labels = tuple(str(x) for x in self.labels)
        self.text = tuple(str(x) for x in self.text)

    @property
    def num_frames(self) -> int:
        return self.actors[0].num_frames

    @property
    def fps(self) -> float:
        return self.actors[0].fps

    def to_arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        """The arrays of both tracks, keyed ``{prefix}a0.pose`` etc. (for containers that embed it)."""
        return {**self.actors[0]._arrays(f"{prefix}a0."), **self.actors[1]._arrays(f"{prefix}a1.")}

    def to_meta(self) -> dict[str, Any]:
        return {"actors": [a._meta() for a in self.actors], "take": self.take, "frame_range": list(self.frame_range),
                "labels": list(self.labels), "text": list(self.text), "meta": self.meta}  # fmt: skip

    @classmethod
    def from_arrays(cls, arrays: dict, meta: dict, prefix: str = "") -> "InteractionSequence":
        actors = tuple(BodyTrack._from(arrays, meta["actors"][i], f"{prefix}a{i}.") for i in (0, 1))
        return cls(actors=actors, take=meta.get("take", ""), frame_range=tuple(meta["frame_range"]),
                   labels=meta.get("labels", ()), text=meta.get("text", ()), meta=meta.get("meta", {}))  # fmt: skip

    def save(self, path: str | Path) -> Path:
        return save_npz(path, "InteractionSequence", INTERACTION_SEQUENCE_VERSION, self.to_arrays(), self.to_meta())

    @classmethod
    def load(cls, path: str | Path) -> "InteractionSequence":
        required = tuple(f"a{i}.{n}" for i in (0, 1) for n in _BODY_ARRAYS)
        arrays, meta = load_npz(path, "InteractionSequence", INTERACTION_SEQUENCE_VERSION, required=required)
        try:
            return cls.from_arrays(arrays, meta)
        except (KeyError, IndexError, ValueError) as e:
            raise FormatError(f"inconsistent InteractionSequence: {e}", path=path) from e


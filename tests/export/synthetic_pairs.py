"""Synthetic two-person joints and the least of an export the converters read, shared by the
interchange tests (no body model needed)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from dualhuman_builder.body.joints import JOINT22_PARENTS
from dualhuman_builder.export.features import REST_DIRECTIONS

FPS = 10.0
BONE_LENGTHS = np.array([0, .11, .11, .12, .38, .38, .13, .40, .40, .05, .12, .12, .20, .14, .14, .10, .12, .12,
                         .26, .26, .24, .24])  # fmt: skip
TEXT = "Two people hug, the left one turns right."


def body(T: int, seed: int, turns: float = 0.0) -> np.ndarray:
    """``(T, 22, 3)`` joints of a wiggling rest skeleton facing +Z at frame 0 (hips exactly level),
    its root yaw going through ``turns`` full turns."""
    rng = np.random.default_rng(seed)
    rest = np.zeros((22, 3))
    rest[0] = [0.0, 0.95, 0.0]
    for j in range(1, 22):
        rest[j] = rest[JOINT22_PARENTS[j]] + BONE_LENGTHS[j] * REST_DIRECTIONS[j]
    wiggle = np.cumsum(rng.normal(0.0, 0.01, (T, 22, 3)), axis=0)
    j = rest + wiggle - wiggle[:1]
    yaw = np.linspace(0.0, 2 * np.pi * turns, T)
    rel = j - j[:, :1]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    rel = np.stack([c * rel[..., 0] + s * rel[..., 2], rel[..., 1], -s * rel[..., 0] + c * rel[..., 2]], -1)
    return rel + j[:, :1]


def face_to_face(T: int = 12, seed: int = 0, turns: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Person a faces +Z, person b faces exactly -Z 0.8 m in front of it (a half turn written exactly)."""
    return body(T, seed, turns) + [0.3, 0.0, -1.0], body(T, seed + 1) * [-1.0, 1.0, -1.0] + [0.3, 0.0, -0.2]


def write_export(root: Path, seqs: dict, fps: float = FPS) -> Path:
    """A minimal export (manifest with SHA-256 of every file) of ``{sid: (joints a, joints b, split)}``,
    what the converters read."""
    files, sequences = {}, {}
    for sid, (a, b, split) in seqs.items():
        base = root / "sequences" / sid
        base.mkdir(parents=True)
        np.savez(base / "motion.npz", **{"a.joints": np.float32(a), "b.joints": np.float32(b)})
        (base / "text.json").write_text(json.dumps({"texts": [TEXT]}))
        for name in ("motion.npz", "text.json"):
            files[f"sequences/{sid}/{name}"] = {"sha256": hashlib.sha256((base / name).read_bytes()).hexdigest()}
        sequences[sid] = {"split": split}
    manifest = {"format": "dualhuman-export", "format_version": 1, "fps": fps, "sequences": sequences, "files": files}
    (root / "manifest.json").write_text(json.dumps(manifest))
    return root

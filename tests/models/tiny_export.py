"""A real, tiny dataset export for the model tests: anny bodies posed frame by frame, written by the
toolkit's own export writer, so that every reader is exercised on the layout `dualhuman export` writes.

Two people face each other about 1.3 m apart. The actor walks towards the other and swings its arms
forwards (a push); the reactor, a few frames later, steps back and lifts its arms in the same rhythm, so
the reactor's motion is a function of the actor's and a reaction model has signal to learn. Sequences
cycle through four kinds: person a acts (``push``), person b acts (``hit``, roles ``("reactor",
"actor")``), a symmetric ``handshake`` without roles (person a acts by convention), and a ``push``
again. ``make_tiny_export`` builds each (n_sequences, frames, seed) once per process and copies it.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

import numpy as np

FPS = 20.0
KINDS = (  # labels, roles, text; the acting person is "a" unless roles say b acts
    (("push",), ("actor", "reactor"), "The person on the left pushes the other, who steps back."),
    (("hit",), ("reactor", "actor"), "The person on the right swings at the other, who backs away."),
    (("handshake",), None, "Two people walk up to each other and shake hands."),
    (("push",), ("actor", "reactor"), "One person shoves the other, who staggers back."),
)
_CACHE: dict[tuple[int, int, int], Path] = {}
_TMP: list[Path] = []


def _bone(model, name: str) -> int:
    return model.bone_names.index(name)


def _person(model, T: int, rng: np.random.Generator, x0: float, facing: float, drive: np.ndarray, acts: bool) -> tuple:
    """pose (T, bones, 3) rotation vectors, transl (T, 3) metres, shape (6,) for one person.

    ``drive (T,)`` in [0, 1] is the actor's approach (0: at rest, 1: arrived); the actor moves
    towards the other by up to 0.45 m, the reactor away by up to 0.35 m. ``facing``: +1 faces +x.
    """
    pose = np.zeros((T, model.num_bones, 3))
    pose[:, 0, 1] = facing * np.pi / 2 + rng.normal(0.0, 0.05)  # yaw: anny faces +z at rest
    pose[:, 0] += np.cumsum(rng.normal(0.0, 0.004, (T, 3)), axis=0)  # a little sway
    reach = drive * (1.0 if acts else 0.7)
    for side, sign in (("L", 1.0), ("R", -1.0)):
        pose[:, _bone(model, f"upperarm01.{side}"), 0] = -1.2 * reach + rng.normal(0.0, 0.05)  # arms forward
        pose[:, _bone(model, f"upperarm01.{side}"), 2] = sign * 0.3 * reach
        pose[:, _bone(model, f"lowerarm01.{side}"), 0] = -0.4 * (1.0 - reach) - 0.2
    step = np.sin(np.linspace(0.0, 4.0 * np.pi, T)) * np.gradient(drive) * 6.0  # legs move while walking
    pose[:, _bone(model, "upperleg01.L"), 0] = step
    pose[:, _bone(model, "upperleg01.R"), 0] = -step
    shift = (0.45 if acts else -0.35) * drive
    transl = np.stack([np.full(T, x0) + facing * shift, np.full(T, 0.95), rng.normal(0.0, 0.01) + np.zeros(T)], axis=1)
    return pose, transl, rng.uniform(0.3, 0.7, len(model.shape_names))


def _sequence(model, T: int, k: int, seed: int):
    from dualhuman_builder.export.items import ExportItem
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    rng = np.random.default_rng(seed * 1000 + k)
    labels, roles, text = KINDS[k % len(KINDS)]
    b_acts = roles is not None and roles[1] == "actor"
    t = np.arange(T) / T
    onset, speed = rng.uniform(0.15, 0.35), rng.uniform(6.0, 10.0)
    lead = 1.0 / (1.0 + np.exp(-speed * (t - onset) * 2.0))  # the actor's approach, a smooth step
    lag = max(1, round(rng.uniform(0.05, 0.1) * T))
    follow = np.concatenate([np.zeros(lag), lead[:-lag]])  # the reactor's, a few frames behind
    gap = rng.uniform(1.2, 1.4)
    drive_a, drive_b = (follow, lead) if b_acts else (lead, follow)
    pa = _person(model, T, rng, 0.0, +1.0, drive_a, not b_acts)
    pb = _person(model, T, rng, gap, -1.0, drive_b, b_acts)
    a = BodyTrack.from_model(model, *pa, FPS, actor=f"p{(k + seed) % 3}")
    b = BodyTrack.from_model(model, *pb, FPS, actor=f"q{(k + seed) % 3}")
    seq = InteractionSequence((a, b), labels=labels, text=(text,))
    return ExportItem(f"tiny{k:02d}", seq, labels=list(labels), texts=[text], roles=roles)


def make_tiny_export(root: str | Path, n_sequences: int = 4, frames: int = 80, seed: int = 0) -> Path:
    """A copy of a real export of ``n_sequences`` two-person sequences of ``frames`` frames at 20 fps
    under ``root/tiny-export`` (train and test split, labels, texts, roles, motion with pose, transl,
    shape and joints); `dualhuman export verify` accepts it. Built once per process per arguments."""
    key = (int(n_sequences), int(frames), int(seed))
    if key not in _CACHE:
        from dualhuman_builder.body.model import get_body_model
        from dualhuman_builder.export.writer import export_dataset

        if not _TMP:
            _TMP.append(Path(tempfile.mkdtemp(prefix="tiny-export-")))
            atexit.register(shutil.rmtree, _TMP[0], True)
        model = get_body_model()
        items = [_sequence(model, key[1], k, key[2]) for k in range(key[0])]
        out = _TMP[0] / f"n{key[0]}-T{key[1]}-s{key[2]}"
        manifest = export_dataset(items, out, split_ratio=0.75, seed=key[2], expect=("motion", "text"))
        if key[0] >= 2 and not manifest["counts"]["test"]:
            raise RuntimeError("tiny export has an empty test split; use another seed")
        _CACHE[key] = out
    dest = Path(root) / "tiny-export"
    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(_CACHE[key], dest)
    return dest

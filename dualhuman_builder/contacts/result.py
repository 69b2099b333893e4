"""The contacts of a sequence as arrays, and their ``.npz`` file (the contacts stage's ``contacts.npz``).

Index 0 is actor A, 1 actor B; ``T`` frames, ``V`` vertices of the shared topology. Distances are
metres, negative inside the other body (see :mod:`dualhuman_builder.contacts.frames`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

#: Version of the ``ContactResult`` ``.npz`` layout; :meth:`ContactResult.load` refuses newer ones.
CONTACT_RESULT_VERSION = 1


@dataclass(eq=False)
class ContactResult:
    """Contacts of two bodies over T frames (index 0 = actor A, 1 = actor B).

    ``labels (2, T, V)`` bool: vertex of actor i in contact with the other body (signed distance
    below ``threshold_m``, penetration included); ``distances (2, T, V)`` float16 signed distance
    in metres (negative inside), NaN beyond the band or not queried, ``-inf`` inside deeper than
    the band; ``frame_contact (T,)``: any contact on the frame; ``valid (T,)``: frame computed
    (False: skipped because of non-finite vertices); ``events``: region-level contact events (see
    the module docstring; keys ``region_a``, ``region_b``, ``start``, ``end`` (exclusive),
    ``contact_frames``, ``peak_vertices``, ``min_distance_m``, and ``start_s``/``end_s`` when
    ``fps`` is known); ``stats``: counts and timings; ``region_names``; ``actors`` names.
    """

    labels: np.ndarray
    distances: np.ndarray
    frame_contact: np.ndarray
    valid: np.ndarray
    events: list[dict[str, Any]]
    stats: dict[str, Any]
    region_names: tuple[str, ...] = ()
    actors: tuple[str, str] = ("a", "b")

    def __post_init__(self):
        self.labels = np.asarray(self.labels, dtype=bool)
        if self.labels.ndim != 3 or self.labels.shape[0] != 2:
            raise ValueError(f"labels must have shape (2, T, V), got {self.labels.shape}")
        self.distances = np.asarray(self.distances, dtype=np.float16)
        if self.distances.shape != self.labels.shape:
            raise ValueError(f"distances {self.distances.shape} and labels {self.labels.shape} differ in shape")
        T = self.labels.shape[1]
        self.frame_contact = np.asarray(self.frame_contact, dtype=bool)
        self.valid = np.asarray(self.valid, dtype=bool)
        for name in ("frame_contact", "valid"):
            if getattr(self, name).shape != (T,):
                raise ValueError(f"{name} must have shape ({T},), got {getattr(self, name).shape}")
        self.region_names = tuple(self.region_names)
        self.actors = tuple(self.actors)

    @property
    def num_frames(self) -> int:
        return self.labels.shape[1]

    def contact_counts(self) -> np.ndarray:
        """``(2, T)`` int: number of contact vertices of each actor per frame."""
        return self.labels.sum(axis=2)

    def f1(self, other) -> dict[str, float]:
        """Precision, recall and F1 of these labels against ``other`` (the reference): a
        ``(2, T, V)`` bool array or a pair of ``(T, V)`` arrays. F1 is 1.0 when neither has a
        contact."""
        ref = np.stack([np.asarray(o, dtype=bool) for o in other]) if not isinstance(other, np.ndarray) \
            else np.asarray(other, dtype=bool)  # fmt: skip
        if ref.shape != self.labels.shape:
            raise ValueError(f"reference labels have shape {ref.shape}, these have {self.labels.shape}")
        tp = int(np.sum(self.labels & ref))
        fp = int(np.sum(self.labels & ~ref))
        fn = int(np.sum(~self.labels & ref))
        precision = tp / (tp + fp) if tp + fp else 1.0
        recall = tp / (tp + fn) if tp + fn else 1.0
        f1 = 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 1.0
        return {"f1": f1, "precision": precision, "recall": recall, "tp": tp, "fp": fp, "fn": fn}

    def save(self, path: str | Path) -> Path:
        """One ``.npz`` (atomic): labels bit-packed along V, float16 distances, JSON metadata."""
        from dualhuman_builder.fileio import save_npz

        arrays = {"labels_packed": np.packbits(self.labels, axis=2), "distances": self.distances,
                  "frame_contact": self.frame_contact, "valid": self.valid}  # fmt: skip
        meta = {"num_vertices": int(self.labels.shape[2]), "events": self.events, "stats": self.stats,
                "region_names": list(self.region_names), "actors": list(self.actors)}  # fmt: skip
        return save_npz(path, "ContactResult", CONTACT_RESULT_VERSION, arrays, meta)

    @classmethod
    def load(cls, path: str | Path) -> "ContactResult":
        from dualhuman_builder.errors import FormatError
        from dualhuman_builder.fileio import load_npz

        names = ("labels_packed", "distances", "frame_contact", "valid")
        arrays, meta = load_npz(path, "ContactResult", CONTACT_RESULT_VERSION, required=names)
        try:
            labels = np.unpackbits(arrays["labels_packed"], axis=2, count=int(meta["num_vertices"])).astype(bool)
            return cls(labels, arrays["distances"], arrays["frame_contact"], arrays["valid"], meta["events"],
                       meta["stats"], tuple(meta["region_names"]), tuple(meta["actors"]))  # fmt: skip
        except (KeyError, ValueError) as e:
            raise FormatError(f"inconsistent ContactResult: {e}", path=path) from e

"""Body-part regions of anny's mesh (``rigs/anny_regions.toml``), for region-level contacts.

Each vertex takes the region of the bone with its largest skinning weight; regions with a
``side`` split their bones' vertices into front and back along the body's forward axis (+Z at rest)
relative to the bone head. Bone patterns may use ``*`` (``finger*.L``).
"""

from __future__ import annotations

import fnmatch
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dualhuman_builder.errors import RigError
from dualhuman_builder.resources import RIGS_DIR

DEFAULT_REGIONS_PATH = RIGS_DIR / "anny_regions.toml"


@dataclass(frozen=True)
class BodyRegions:
    """``names`` (R,) region names; ``vertex_region`` ``(V,)`` int16 region index per vertex."""

    names: tuple[str, ...]
    vertex_region: np.ndarray

    def vertices_of(self, name: str) -> np.ndarray:
        return np.flatnonzero(self.vertex_region == self.names.index(name))


def load_regions(model, path: str | Path | None = None) -> BodyRegions:
    """Per-vertex region labels for ``model`` from a regions file (default ``rigs/anny_regions.toml``)."""
    path = Path(path) if path is not None else DEFAULT_REGIONS_PATH
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RigError("regions file not found", path=path, fix=f"use {DEFAULT_REGIONS_PATH}") from None
    except tomllib.TOMLDecodeError as e:
        raise RigError(f"not valid TOML: {e}", path=path) from e
    entries = doc.get("region")
    if not isinstance(entries, list) or not entries:
        raise RigError("no [[region]] entries", path=path)

    vertex_bone = model.vertex_bone()
    rest = model.rest()
    verts = rest.vertices[0].detach().cpu().numpy()
    heads = rest.bone_heads[0].detach().cpu().numpy()
    # +1 in front of the bone head (towards +Z), -1 behind it
    front = np.where(verts[:, 2] >= heads[vertex_bone, 2], 1, -1)

    names: list[str] = []
    claims: dict[tuple[int, int], str] = {}  # (bone, side) -> region; side 0 = both
    for i, entry in enumerate(entries):
        name, patterns, side = entry.get("name"), entry.get("bones"), entry.get("side")
        if not isinstance(name, str) or not isinstance(patterns, list) or not patterns:
            raise RigError(f"region #{i + 1} needs a 'name' and a non-empty 'bones' list", path=path)
        if name in names:
            raise RigError(f"region {name!r} is defined twice", path=path)
        if side not in (None, "front", "back"):
            raise RigError(f"region {name!r}: side must be 'front' or 'back', got {side!r}", path=path)
        names.append(name)
        for pat in patterns:
            bones = [j for j, b in enumerate(model.bone_names) if fnmatch.fnmatchcase(b, pat)]
            if not bones:
                raise RigError(
                    f"region {name!r}: {pat!r} matches no anny bone",
                    path=path,
                    fix="list anny's bones with `dualhuman body info --bones`",
                )
            for j in bones:
                keys = [(j, 0)] if side is None else [(j, 1 if side == "front" else -1)]
                for key in keys:
                    clash = claims.get(key) or claims.get((j, 0))
                    if clash is None and key[1] == 0:
                        clash = claims.get((j, 1)) or claims.get((j, -1))
                    if clash:
                        raise RigError(f"bone {model.bone_names[j]!r} is in both {clash!r} and {name!r}", path=path)
                    claims[key] = name

    label = np.full(len(verts), -1, dtype=np.int16)
    for (bone, side), name in claims.items():
        sel = vertex_bone == bone
        if side:
            sel &= front == side
        label[sel] = names.index(name)
    orphan = sorted({model.bone_names[b] for b in vertex_bone[label < 0]})
    if orphan:
        raise RigError(f"bones carrying vertices are in no region: {orphan}", path=path)
    return BodyRegions(tuple(names), label)

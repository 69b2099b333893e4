"""Seeded train/test splits of an export's sequences (``splits/train.txt``, ``splits/test.txt``)."""

from __future__ import annotations

from typing import Mapping

import numpy as np


def make_splits(subjects: Mapping[str, tuple[str, str]], split_ratio: float = 0.75, subject_disjoint: bool = False,
                seed: int = 0) -> tuple[list[str], list[str]]:  # fmt: skip
    """Seeded train/test split of sequence ids; returns sorted ``(train, test)``.

    ``subjects``: seq_id -> its two subject names. About ``split_ratio`` of the sequences go to
    train (at least one to each side when there are two or more and ``split_ratio < 1``).
    ``subject_disjoint``: sequences are grouped by shared subjects (connected components) and whole
    groups are assigned, so no subject appears in both splits; ValueError when that is impossible
    (one group) or a sequence has an unnamed subject.
    """
    if not (isinstance(split_ratio, (int, float)) and 0.0 < float(split_ratio) <= 1.0):
        raise ValueError(f"split_ratio must be in (0, 1], got {split_ratio!r}")
    ids = sorted(subjects)
    n = len(ids)
    if n == 0:
        return [], []
    rng = np.random.default_rng(seed)
    if split_ratio >= 1.0:
        return ids, []
    target = min(max(round(split_ratio * n), 1), n - 1) if n >= 2 else n
    if not subject_disjoint:
        order = [ids[i] for i in rng.permutation(n)]
        return sorted(order[:target]), sorted(order[target:])
    unnamed = [s for s in ids if not all(subjects[s])]
    if unnamed:
        raise ValueError(f"subject-disjoint split needs both subjects named; sequences {unnamed[:5]} have an empty name")
    parent: dict[str, str] = {}

    def find(x):
        while parent.setdefault(x, x) != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for s in ids:
        a, b = subjects[s]
        parent[find(a)] = find(b)
    groups: dict[str, list[str]] = {}
    for s in ids:
        groups.setdefault(find(subjects[s][0]), []).append(s)
    comps = sorted(groups.values())
    if len(comps) < 2:
        names = sorted({x for s in ids for x in subjects[s]})
        raise ValueError(
            f"a subject-disjoint split is impossible: all {n} sequences are linked through shared subjects "
            f"{names[:10]} (need at least two groups of sequences with no subject in common)"
        )
    train: list[str] = []
    test: list[str] = []
    for i in rng.permutation(len(comps)):
        comp = comps[i]
        if abs(len(train) + len(comp) - target) < abs(len(train) - target) or not train:
            train += comp
        else:
            test += comp
    if not test:  # the first group took everything it could; move the smallest other group over
        comps_in = sorted((c for c in comps), key=len)
        for c in comps_in:
            if set(c) <= set(train) and len(c) < len(train):
                test = c
                train = [s for s in train if s not in set(c)]
                break
    return sorted(train), sorted(test)


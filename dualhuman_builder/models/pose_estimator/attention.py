"""The queries of the two-person pose estimator and the masks of its interaction-aware self-attention
(the Dual-Human paper, §3.2).

Queries come in one block per person ``p`` (0: person a, 1: person b), :data:`PER_PERSON` = 25 each:
the 22 ``Pose`` queries (one per joint, HumanML3D order, :data:`~dualhuman_builder.body.joints.JOINT22_NAMES`),
then ``Transl``, ``Prob`` and ``Track``; :func:`query_index` gives a query's position in the sequence of
:data:`NUM_QUERIES` = 50.

The masks are boolean ``(Q, Q)`` tensors in :class:`torch.nn.MultiheadAttention`'s convention: ``True``
where query ``i`` (row) may **not** attend to key ``j`` (column). Every row allows at least itself.

* **Intra-human** (:func:`intra_mask`): the two people never see each other. A ``Pose`` query sees
  itself, its skeleton ancestors up to the pelvis and its direct children
  (:data:`~dualhuman_builder.body.joints.JOINT22_PARENTS`), and its own person's ``Track`` query (the
  previous frame's root, which tells the query which person it follows); nothing else: not its
  siblings, cousins or other limbs, nor its person's ``Transl`` and ``Prob``. ``Transl``, ``Prob`` and
  ``Track`` see every query of their own person (they summarise the person).
* **Inter-human** (:func:`inter_mask`): ``Pose`` and ``Transl`` queries of both people see each other
  (any two joints of two people may interact), the ``Track`` queries join that group (both people's
  previous roots reach every pose and translation query); the two ``Prob`` queries see only each other.
* The ablation (``interaction_attention = false``) uses one plain self-attention without a mask.
"""

from __future__ import annotations

import torch

from dualhuman_builder.body.joints import JOINT22_PARENTS

PERSONS = 2
JOINTS = len(JOINT22_PARENTS)  #: 22
POSE, TRANSL, PROB, TRACK = "pose", "transl", "prob", "track"
PER_PERSON = JOINTS + 3  #: 22 Pose + Transl + Prob + Track
NUM_QUERIES = PERSONS * PER_PERSON  #: 50


def query_index(person: int, kind: str, joint: int = 0) -> int:
    """Position of a query in the sequence: ``kind`` is ``"pose"`` (with ``joint``), ``"transl"``, ``"prob"`` or ``"track"``."""
    if not 0 <= person < PERSONS:
        raise ValueError(f"person must be 0 or 1, got {person}")
    if kind == POSE:
        if not 0 <= joint < JOINTS:
            raise ValueError(f"joint must be 0..{JOINTS - 1}, got {joint}")
        return person * PER_PERSON + joint
    offsets = {TRANSL: JOINTS, PROB: JOINTS + 1, TRACK: JOINTS + 2}
    if kind not in offsets:
        raise ValueError(f"query kind must be one of pose, transl, prob, track; got {kind!r}")
    return person * PER_PERSON + offsets[kind]


def ancestors(joint: int) -> list[int]:
    """The joints on the chain from ``joint``'s parent up to the pelvis (root, joint 0)."""
    out = []
    j = JOINT22_PARENTS[joint]
    while j >= 0:
        out.append(j)
        j = JOINT22_PARENTS[j]
    return out


def children(joint: int) -> list[int]:
    """The joints whose parent is ``joint``."""
    return [k for k, p in enumerate(JOINT22_PARENTS) if p == joint]


def skeleton_neighbours(joint: int) -> set[int]:
    """What a ``Pose`` query sees of its own person's joints in the intra stage: itself, its ancestors, its children."""
    return {joint, *ancestors(joint), *children(joint)}


def intra_mask() -> torch.Tensor:
    """The intra-human mask ``(NUM_QUERIES, NUM_QUERIES)`` bool, True = blocked (module docstring)."""
    allow = torch.zeros(NUM_QUERIES, NUM_QUERIES, dtype=torch.bool)
    for p in range(PERSONS):
        block = slice(p * PER_PERSON, (p + 1) * PER_PERSON)
        track = query_index(p, TRACK)
        for j in range(JOINTS):
            i = query_index(p, POSE, j)
            for k in skeleton_neighbours(j):
                allow[i, query_index(p, POSE, k)] = True
            allow[i, track] = True
        for kind in (TRANSL, PROB, TRACK):
            allow[query_index(p, kind), block] = True
    return ~allow


def inter_mask() -> torch.Tensor:
    """The inter-human mask ``(NUM_QUERIES, NUM_QUERIES)`` bool, True = blocked (module docstring)."""
    group = torch.zeros(NUM_QUERIES, dtype=torch.bool)
    for p in range(PERSONS):
        group[p * PER_PERSON:p * PER_PERSON + JOINTS] = True
        group[query_index(p, TRANSL)] = True
        group[query_index(p, TRACK)] = True
    prob = torch.zeros(NUM_QUERIES, dtype=torch.bool)
    prob[[query_index(p, PROB) for p in range(PERSONS)]] = True
    allow = (group[:, None] & group[None, :]) | (prob[:, None] & prob[None, :])
    return ~allow


__all__ = ["JOINTS", "NUM_QUERIES", "PERSONS", "PER_PERSON", "ancestors", "children", "inter_mask", "intra_mask",
           "query_index", "skeleton_neighbours"]  # fmt: skip

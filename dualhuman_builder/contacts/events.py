"""Region-level contact events, following CHI3D's contact signatures.

A region pair (region ``r`` of actor 0, region ``s`` of actor 1) is in contact on a frame when a
contact vertex of actor 0 in ``r`` has its closest point on a face of actor 1 in region ``s``, or
symmetrically from actor 1's side. A face's region is the majority region of its vertices
(:class:`~dualhuman_builder.contacts.topology.ContactTopology`); vertices deeper than the band
have no closest face and count towards no pair. An event is a maximal run of frames in which a
pair is in contact, gaps of up to ``merge_gap`` frames merged: ``start`` inclusive, ``end``
exclusive (frame indices).
"""

from __future__ import annotations

from typing import Any

import numpy as np


def frame_pairs(topo, d_a, f_a, d_b, f_b, threshold: float) -> dict[tuple[int, int], tuple[int, float]]:
    """Region pairs in contact on one frame: ``(region of actor 0, region of actor 1)`` ->
    ``(contact vertices on both sides, min distance m)``. ``d_a``, ``d_b`` ``(V,)``: signed
    distances of each actor's vertices (m); ``f_a``, ``f_b`` ``(V,)``: their closest faces
    (indices into ``topo.faces``, -1 where the distance is not finite)."""
    ra, rb, dist = [], [], []
    for i, (d, f) in enumerate(((d_a, f_a), (d_b, f_b))):
        v = np.flatnonzero(np.isfinite(d) & (d < threshold))
        if not len(v):
            continue
        own, other = topo.vertex_region[v], topo.face_region[f[v]]
        ra.append(own if i == 0 else other)
        rb.append(other if i == 0 else own)
        dist.append(d[v])
    if not ra:
        return {}
    ra, rb, dist = np.concatenate(ra), np.concatenate(rb), np.concatenate(dist)
    key = ra * len(topo.region_names) + rb
    order = np.argsort(key, kind="stable")
    key, dist = key[order], dist[order]
    uniq, start, count = np.unique(key, return_index=True, return_counts=True)
    mins = np.minimum.reduceat(dist, start)
    R = len(topo.region_names)
    return {(int(k // R), int(k % R)): (int(c), float(m)) for k, c, m in zip(uniq, count, mins)}


def contact_events(per_frame: list[dict], names, merge_gap: int, fps: float | None) -> list[dict[str, Any]]:
    """The events of a sequence from :func:`frame_pairs` of each frame (``{}`` for frames not
    computed), sorted by ``(start, region_a, region_b)``: dicts with ``region_a``, ``region_b``
    (names from ``names``), ``start``, ``end`` (exclusive), ``contact_frames``, ``peak_vertices``,
    ``min_distance_m``, and ``start_s``/``end_s`` when ``fps`` is given."""
    runs: dict[tuple[int, int], list[tuple[int, int, float]]] = {}
    for t, pairs in enumerate(per_frame):
        for pair, (count, mind) in pairs.items():
            runs.setdefault(pair, []).append((t, count, mind))
    events = []
    for (ra, rb), frames in runs.items():
        group = [frames[0]]
        for item in frames[1:] + [None]:
            if item is not None and item[0] - group[-1][0] - 1 <= merge_gap:
                group.append(item)
                continue
            ev = {"region_a": names[ra], "region_b": names[rb], "start": group[0][0], "end": group[-1][0] + 1,
                  "contact_frames": len(group), "peak_vertices": max(g[1] for g in group),
                  "min_distance_m": round(min(g[2] for g in group), 6)}  # fmt: skip
            if fps:
                ev["start_s"], ev["end_s"] = round(ev["start"] / fps, 6), round(ev["end"] / fps, 6)
            events.append(ev)
            group = [item]
    events.sort(key=lambda e: (e["start"], e["region_a"], e["region_b"]))
    return events


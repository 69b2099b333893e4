"""Per-vertex contacts between two body meshes over a sequence, and their region events.

For every frame and both directions (vertices of A against B's surface, of B against A's), the
pseudonormal signed distance (metres, negative inside) within a band ``band_m``; a vertex is in
contact when its distance is below ``threshold_m`` (penetrations included). Vertices ``(T, V, 3)``
metres in the world frame of :mod:`dualhuman_builder.conventions`.

:func:`compute_contacts` takes a fitted :class:`~dualhuman_builder.tracks.InteractionSequence`,
:func:`contacts_from_vertices` raw vertex arrays; both return a
:class:`~dualhuman_builder.contacts.result.ContactResult`. Frames are computed by the kernel of
:mod:`~dualhuman_builder.contacts.frames`, in this process or, for long sequences on machines with
four CPUs or more, in worker processes (:mod:`~dualhuman_builder.contacts.workers`); the result
does not depend on which. Region events: :mod:`~dualhuman_builder.contacts.events`.
"""

from __future__ import annotations

import math
import time
from typing import Callable, Sequence

import numpy as np

from dualhuman_builder.contacts.events import contact_events
from dualhuman_builder.contacts.frames import (COUNT_KEYS, DEFAULT_BAND_M, DEFAULT_THRESHOLD_M, compute_frames,
                                               contact_frame)  # fmt: skip
from dualhuman_builder.contacts.result import ContactResult
from dualhuman_builder.contacts.topology import ContactTopology, default_topology

#: Events of one region pair separated by at most this many frames without contact are merged.
DEFAULT_MERGE_GAP = 1

__all__ = ["DEFAULT_BAND_M", "DEFAULT_MERGE_GAP", "DEFAULT_THRESHOLD_M", "ContactResult", "ContactTopology",
           "check_params", "compute_contacts", "contact_frame", "contacts_from_vertices", "default_topology"]  # fmt: skip


def check_params(threshold_m: float, band_m: float, merge_gap: int = DEFAULT_MERGE_GAP) -> tuple[float, float, int]:
    """Validated ``(threshold_m, band_m, merge_gap)``: a positive threshold (metres), a finite band
    at least as wide, a non-negative whole number of frames; ValueError otherwise."""
    try:
        threshold, band = float(threshold_m), float(band_m)
    except (TypeError, ValueError):
        raise ValueError(f"threshold_m and band_m must be numbers (metres), got {threshold_m!r} and {band_m!r}") from None
    if not (math.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold_m must be a positive distance in metres, got {threshold_m}")
    if not (math.isfinite(band) and band >= threshold):
        raise ValueError(f"band_m must be finite and at least threshold_m ({threshold}), got {band_m}")
    if isinstance(merge_gap, bool) or not isinstance(merge_gap, (int, np.integer)) or merge_gap < 0:
        raise ValueError(f"merge_gap must be a non-negative whole number of frames, got {merge_gap!r}")
    return threshold, band, int(merge_gap)


def _check_vertices(name: str, v, V: int) -> np.ndarray:
    """``v`` as an array when it holds floating-point ``(T, V, 3)`` coordinates with ``T > 0``,
    else ValueError naming ``name``."""
    v = np.asarray(v)
    if v.ndim != 3 or v.shape[2] != 3:
        raise ValueError(f"{name} must have shape (T, V, 3), got {v.shape}")
    if v.shape[0] == 0:
        raise ValueError(f"{name} has no frames (shape {v.shape})")
    if v.shape[1] != V:
        raise ValueError(f"{name} has {v.shape[1]} vertices per frame; the mesh topology has {V}")
    if not np.issubdtype(v.dtype, np.floating):
        raise ValueError(f"{name} must hold floating-point coordinates, got dtype {v.dtype}")
    return v


def contacts_from_vertices(verts_a: np.ndarray, verts_b: np.ndarray, topology: ContactTopology, *,
                           threshold_m: float = DEFAULT_THRESHOLD_M, band_m: float = DEFAULT_BAND_M,
                           merge_gap: int = DEFAULT_MERGE_GAP, fps: float | None = None,
                           actors: Sequence[str] = ("a", "b"), nan_policy: str = "skip",
                           progress: Callable[[str], None] | None = None, workers: int | None = None) -> ContactResult:  # fmt: skip
    """Contacts between two bodies given their vertices ``verts_a``, ``verts_b`` ``(T, V, 3)``
    (world metres, any float dtype) on the mesh ``topology`` (see :meth:`ContactTopology.for_model`).

    ``threshold_m``: contact distance (> 0); ``band_m`` (>= threshold): distances are computed
    within it; ``merge_gap``: events separated by at most this many frames are merged;
    ``nan_policy``: ``"skip"`` (frames with any non-finite vertex are left out, counted in
    ``stats["skipped_nan_frames"]``, with ``valid`` False) or ``"raise"`` (ValueError naming the
    first such frame, before any work). ``progress(str)`` is called about every 10 % of frames.
    ``workers``: processes to spread the frames over (:mod:`~dualhuman_builder.contacts.workers`;
    1: all in this process; default: one per two CPUs, up to 8, when each gets at least 48 frames).
    The result does not depend on it.
    """
    topo = topology
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1):
        raise ValueError(f"workers must be a whole number >= 1 (or None for automatic), got {workers!r}")
    V = topo.num_vertices
    verts_a = _check_vertices("verts_a", verts_a, V)
    verts_b = _check_vertices("verts_b", verts_b, V)
    if verts_a.shape != verts_b.shape:
        raise ValueError(f"verts_a {verts_a.shape} and verts_b {verts_b.shape} must have the same shape")
    threshold, band, merge_gap = check_params(threshold_m, band_m, merge_gap)
    if nan_policy not in ("skip", "raise"):
        raise ValueError(f"nan_policy must be 'skip' or 'raise', got {nan_policy!r}")
    if len(actors) != 2:
        raise ValueError(f"actors must name two actors, got {list(actors)}")

    T = verts_a.shape[0]
    finite = np.isfinite(verts_a).all(axis=(1, 2)) & np.isfinite(verts_b).all(axis=(1, 2))
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        which = "verts_a" if not np.isfinite(verts_a[bad]).all() else "verts_b"
        if nan_policy == "raise":
            raise ValueError(f"{which} holds NaN or infinite coordinates at frame {bad} "
                             f"({int((~finite).sum())} of {T} frames affected)")  # fmt: skip
        if not finite.any():
            raise ValueError(f"every one of the {T} frames holds NaN or infinite vertex coordinates")

    t0 = time.perf_counter()
    labels = np.zeros((2, T, V), dtype=bool)
    distances = np.full((2, T, V), np.nan, dtype=np.float16)
    counts = dict.fromkeys(COUNT_KEYS, 0)
    per_frame: list[dict] = [{} for _ in range(T)]
    far_frames = done = 0
    frames = np.flatnonzero(finite)
    step = max(1, math.ceil(len(frames) / 10))

    def tick():
        nonlocal done
        done += 1
        if progress is not None and (done % step == 0 or done == len(frames)):
            progress(f"contacts: {done}/{len(frames)} frames ({100 * done // len(frames)} %)")

    # imported here: the package imports this module, and ``python -m ...contacts.workers`` must
    # not find itself imported before it runs
    from dualhuman_builder.contacts.workers import auto_workers, run_in_workers

    n_workers = auto_workers(len(frames)) if workers is None else min(int(workers), max(1, len(frames)))
    if n_workers > 1:
        if progress is not None:
            progress(f"contacts: {len(frames)} frames in {n_workers} worker processes")
        results = run_in_workers(topo, verts_a, verts_b, frames, threshold, band, n_workers, counts, on_done=tick)
    else:
        results = compute_frames(topo, verts_a, verts_b, frames, threshold, band, counts, on_done=tick)
    for t, result in results:
        if result is None:
            far_frames += 1
        else:
            labels[:, t], distances[:, t], per_frame[t] = result
    seconds = time.perf_counter() - t0
    frame_contact = labels.any(axis=(0, 2))
    computed = int(finite.sum())
    stats = {
        "frames": T,
        "contact_frames": int(frame_contact.sum()),
        "skipped_far_frames": far_frames,
        "skipped_nan_frames": int(T - computed),
        "first_nan_frames": np.flatnonzero(~finite)[:10].tolist(),
        "queried_vertices": counts["queried_vertices"],
        "queried_faces": counts["queried_faces"],
        "pseudonormal_vertices": counts["pseudonormal_vertices"],
        "deep_vertices": counts["deep_vertices"],
        "seconds": round(seconds, 4),
        "frame_pairs_per_s": round(computed / seconds, 2) if seconds > 0 else None,
        "threshold_m": threshold,
        "band_m": band,
        "merge_gap": int(merge_gap),
        "fps": fps,
        "workers": n_workers,
    }
    events = contact_events(per_frame, topo.region_names, int(merge_gap), fps)
    return ContactResult(labels, distances, frame_contact, finite, events, stats, topo.region_names, tuple(actors))


def compute_contacts(seq, threshold_m: float = DEFAULT_THRESHOLD_M, band_m: float = DEFAULT_BAND_M,
                     progress: Callable[[str], None] | None = None, merge_gap: int = DEFAULT_MERGE_GAP,
                     nan_policy: str = "skip", topology: ContactTopology | None = None,
                     workers: int | None = None) -> ContactResult:  # fmt: skip
    """Contacts between the two fitted bodies of ``seq`` (an
    :class:`~dualhuman_builder.tracks.InteractionSequence`, e.g. the fit stage's ``bodies.npz``);
    vertices from :meth:`BodyTrack.vertices` (computed here unless cached).
    See :func:`contacts_from_vertices`; ``topology`` defaults to the installed anny's."""
    from dualhuman_builder.tracks import InteractionSequence

    if seq is None:
        raise ValueError("no fitted bodies: pass the InteractionSequence the fit stage wrote (bodies.npz)")
    if not isinstance(seq, InteractionSequence):
        raise ValueError(f"expected an InteractionSequence of two fitted bodies (the fit stage's bodies.npz), "
                         f"got {type(seq).__name__}")  # fmt: skip
    if seq.num_frames == 0:
        raise ValueError(f"sequence {seq.take or '(unnamed)'} has no frames: the fit stage produced no bodies")
    check_params(threshold_m, band_m, merge_gap)  # before the body model runs
    topo = topology or default_topology()
    return contacts_from_vertices(seq.actors[0].vertices(), seq.actors[1].vertices(), topo, threshold_m=threshold_m,
                                  band_m=band_m, merge_gap=merge_gap, fps=seq.fps,
                                  actors=tuple(a.actor or f"actor{i}" for i, a in enumerate(seq.actors)),
                                  nan_policy=nan_policy, progress=progress, workers=workers)  # fmt: skip


"""The ``contacts`` workspace stage of a take (idempotent, crash-safe: see
:mod:`dualhuman_builder.workspace.runner`).

Reads the fit stage's ``bodies.npz`` (:class:`~dualhuman_builder.tracks.InteractionSequence`) and
writes, under ``WS/artifacts/TAKE/_take/contacts/``:

* ``contacts.npz``: the :class:`~dualhuman_builder.contacts.result.ContactResult` (labels
  bit-packed, float16 distances, per-frame flags, events and stats);
* ``contacts.json``: region-level events, per-actor contact-vertex counts per frame, stats.

It never runs the fit itself: a take without a complete fit is an error saying which command to
run. The parameters hash covers ``threshold_m``, ``band_m``, ``merge_gap`` and the fit's
artifacts, so a new fit makes the contacts stale.
"""

from __future__ import annotations

import json
from typing import Callable

from dualhuman_builder.contacts.compute import DEFAULT_BAND_M, DEFAULT_MERGE_GAP, DEFAULT_THRESHOLD_M, check_params
from dualhuman_builder.fit.stage import fitted_bodies
from dualhuman_builder.workspace.runner import Stage

STAGE_VERSION = "1"
CONTACTS_FILE, REPORT_FILE = "contacts.npz", "contacts.json"
CONTACTS = Stage("contacts", per="take", artifacts=(CONTACTS_FILE, REPORT_FILE), reads=("fit",),
                 command="dualhuman contacts {ws} --take {take}")  # fmt: skip


def run_contacts(ws, take: str, threshold_m: float = DEFAULT_THRESHOLD_M, band_m: float = DEFAULT_BAND_M,
                 force: bool = False, log: Callable[[str], None] = print, merge_gap: int = DEFAULT_MERGE_GAP,
                 workers: int | None = None):  # fmt: skip
    """Contacts between the two fitted bodies of ``take`` (thresholds in metres); returns the
    :class:`~dualhuman_builder.workspace.runner.StageResult` (``skipped`` when up to date).
    ``workers``: processes (see :func:`~dualhuman_builder.contacts.compute.contacts_from_vertices`;
    the result does not depend on it, so it is not part of the stage's parameters)."""
    from dualhuman_builder.contacts.compute import compute_contacts
    from dualhuman_builder.tracks import InteractionSequence

    threshold_m, band_m, merge_gap = check_params(threshold_m, band_m, merge_gap)
    ws.take(take)  # unknown take: a clear error before anything else
    bodies = fitted_bodies(ws, take)

    def compute(out):
        seq = InteractionSequence.load(bodies)
        log(f"contacts: {seq.num_frames} frames of {take}, threshold {1000 * threshold_m:g} mm, "
            f"band {1000 * band_m:g} mm")  # fmt: skip
        res = compute_contacts(seq, threshold_m, band_m, progress=log, merge_gap=merge_gap, workers=workers)
        res.save(out.path(CONTACTS_FILE))
        counts = res.contact_counts()
        report = {
            "take": take,
            "actors": list(res.actors),
            "events": res.events,
            "contact_vertices": {a: counts[i].tolist() for i, a in enumerate(res.actors)},
            "stats": res.stats,
        }
        out.path(REPORT_FILE).write_text(json.dumps(report, indent=1))
        st = res.stats
        log(f"contacts: {st['contact_frames']}/{st['frames']} frames in contact, {len(res.events)} region events, "
            f"{st['skipped_far_frames']} frames skipped as far apart, {st['skipped_nan_frames']} with NaN vertices; "
            f"{st['frame_pairs_per_s']} frame pairs/s")  # fmt: skip
        return {"frames": st["frames"], "contact_frames": st["contact_frames"], "events": len(res.events),
                "skipped_far_frames": st["skipped_far_frames"], "skipped_nan_frames": st["skipped_nan_frames"],
                "frame_pairs_per_s": st["frame_pairs_per_s"]}  # fmt: skip

    params = {"threshold_m": float(threshold_m), "band_m": float(band_m), "merge_gap": int(merge_gap)}
    return ws.run_stage(CONTACTS, compute, take=take, params=params, depends_on=[("fit", None)],
                        version=STAGE_VERSION, force=force)  # fmt: skip


def load_contacts(ws, take: str):
    """The take's :class:`~dualhuman_builder.contacts.result.ContactResult` (its contacts stage
    must be done)."""
    from dualhuman_builder.contacts.result import ContactResult

    return ContactResult.load(CONTACTS.artifact(ws, take, CONTACTS_FILE))

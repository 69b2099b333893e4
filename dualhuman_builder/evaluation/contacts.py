"""Contacts of a ground-truth scene against the scene's own per-vertex contacts.

A check of the contacts stage on data whose every contact is known: the scene generator stores
per-vertex signed distances within a band (:data:`~dualhuman_builder.sim.scenes.DISTANCE_BAND`),
so the contacts stage run on the scene's own bodies must find the same vertices.
"""

from __future__ import annotations

from pathlib import Path

from dualhuman_builder.contacts.compute import ContactResult, ContactTopology, compute_contacts


def contacts_for_scene(scene, threshold_m: float | None = None, band_m: float | None = None,
                       topology: ContactTopology | None = None) -> tuple[ContactResult, dict[str, float]]:
    """Contacts of a ground-truth :class:`~dualhuman_builder.sim.scenes.Scene` (or a path to a
    saved one) and their precision, recall and F1 against the scene's own per-vertex contacts
    (:meth:`~dualhuman_builder.sim.scenes.Scene.contact_labels` at the same threshold). Defaults:
    :data:`~dualhuman_builder.sim.scenes.CONTACT_THRESHOLD` and
    :data:`~dualhuman_builder.sim.scenes.DISTANCE_BAND`."""
    from dualhuman_builder.sim.scenes import CONTACT_THRESHOLD, DISTANCE_BAND, Scene

    if isinstance(scene, (str, Path)):
        scene = Scene.load(scene)
    threshold = CONTACT_THRESHOLD if threshold_m is None else threshold_m
    band = DISTANCE_BAND if band_m is None else band_m
    if threshold > DISTANCE_BAND:
        raise ValueError(f"threshold_m {threshold} exceeds the scene's stored distance band {DISTANCE_BAND} m; "
                         "its reference labels cannot be compared")  # fmt: skip
    res = compute_contacts(scene.sequence, threshold, band, topology=topology)
    return res, res.f1(scene.contact_labels(threshold))

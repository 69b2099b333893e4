"""Contacts stage: per-vertex contact labels between the two fitted meshes with libigl.

Signed distances (metres, negative inside, world frame) of each body's vertices to the other's
closed mesh (``igl.signed_distance``, pseudonormal sign, within a band), per-vertex labels
(distance below a threshold, penetration included), per-frame flags and region-level contact
events over the regions of ``rigs/anny_regions.toml``:

* :func:`compute_contacts` — an :class:`~dualhuman_builder.tracks.InteractionSequence` to a
  :class:`ContactResult`; :func:`contacts_from_vertices` for raw ``(T, V, 3)`` vertex arrays
  (:mod:`.compute`); :func:`contact_frame` for one frame in float64 (:mod:`.frames`, the kernel);
* :class:`ContactTopology` (:mod:`.topology`), :class:`ContactResult` (:mod:`.result`), region
  events (:mod:`.events`), worker processes for long sequences (:mod:`.workers`);
* :func:`~dualhuman_builder.contacts.stage.run_contacts` — the workspace stage.

The distance kernels live in :mod:`dualhuman_builder.geometry`; scoring against a scene's own contacts in
:mod:`dualhuman_builder.evaluation.contacts`.
"""

from dualhuman_builder.contacts.compute import DEFAULT_MERGE_GAP, compute_contacts, contacts_from_vertices
from dualhuman_builder.contacts.frames import DEFAULT_BAND_M, DEFAULT_THRESHOLD_M, contact_frame
from dualhuman_builder.contacts.result import ContactResult
from dualhuman_builder.contacts.stage import run_contacts
from dualhuman_builder.contacts.topology import ContactTopology, default_topology

__all__ = ["DEFAULT_BAND_M", "DEFAULT_MERGE_GAP", "DEFAULT_THRESHOLD_M", "ContactResult", "ContactTopology",
           "compute_contacts", "contact_frame", "contacts_from_vertices", "default_topology",
           "run_contacts"]  # fmt: skip

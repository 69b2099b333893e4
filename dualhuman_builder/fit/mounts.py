"""Tracker offsets on the body that is fitted (:func:`offsets_on_body`).

Sync solves each tracker's offset on its suit segment (:func:`~dualhuman_builder.sync.mount.calibrate_mounts`)
against the suit's own skeleton: MVN's segment origins, placed by its joint-centre estimates and its segment
lengths scaled from the actor's measured dimensions. The fit needs the offset from anny's segment origin.
The two skeletons differ by a constant per segment that no data of the take separates from the mount
itself: regression-predicted joint centres miss the true ones by 12-25 mm (Harrington and Davis methods:
Mantovani et al., Gait & Posture 44:48-54, 2016; Hara et al., Sci. Rep. 6:37707, 2016), and a distal
segment's origin carries the errors of the chain above it. So sync's offset is a measurement of the
tracker's offset on anny with that error, and the capture protocol's site
(:data:`~dualhuman_builder.rig.TRACKER_SITES`, prior :data:`~dualhuman_builder.sync.priors.SITE_M`) is a
second one; per axis::

    o = (s_skel^2 site + s_site^2 o_sync) / (s_skel^2 + s_site^2)

with ``s_site`` the site prior and ``s_skel`` the std of the two skeletons' difference at the tracker's segment.
The take measures the latter: the shape calibration's RMS ``r`` of the suit's segment lengths against the
anny body fitted to them (:attr:`~dualhuman_builder.fit.inputs.ActorInput.skeleton_rms_m`; millimetres for
a suit whose skeleton is anny's, centimetres for one scaled from tape-measured dimensions) is the scale
of each segment's disagreement, and a segment ``n`` links from the pelvis (the pelvis itself 1) carries
``n`` of them: ``s_skel = r sqrt(n)``. Without a calibrated shape (a registered one) ``s_skel`` is
:attr:`~dualhuman_builder.fit.config.FitConfig.sigma_suit_skeleton_m` (25 mm, the literature's joint-centre
figure). Solving the offsets again on anny from the take itself (anny driven by the suit's orientations, a
free root per frame, the floor under the stance feet) was tried and rejected: the suit's orientation errors
along a limb (2-5 degrees over 0.5-0.8 m) reach the offsets in full, and the fit came out worse
(``docs/decisions/0027-tracker-offsets-on-the-body.md``).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from dualhuman_builder.body.mapping import MVN_PARENTS, MVN_SEGMENTS
from dualhuman_builder.fit.config import FitConfig
from dualhuman_builder.fit.inputs import ActorInput
from dualhuman_builder.rig import tracker_site
from dualhuman_builder.sync.priors import SITE_M


def chain_links(segment: str) -> int:
    """Segments from the pelvis to MVN ``segment``, both included (the pelvis: 1, a foot: 4, a hand: 9)."""
    n = 1
    while MVN_PARENTS[segment] is not None:
        segment, n = MVN_PARENTS[segment], n + 1
    return n


def skeleton_std(inp: ActorInput, cfg: FitConfig) -> np.ndarray:
    """``(K,)`` std per axis (m) of the suit's segment origin against anny's at each tracker's segment (module
    docstring): from the take's shape calibration when it has one, else ``cfg.sigma_suit_skeleton_m``."""
    segs = [MVN_SEGMENTS[int(s)] for s in inp.trk_segment]
    if inp.skeleton_rms_m is None or not np.isfinite(inp.skeleton_rms_m):
        return np.full(len(segs), float(cfg.sigma_suit_skeleton_m))
    return np.array([float(inp.skeleton_rms_m) * np.sqrt(chain_links(g)) for g in segs])


def offsets_on_body(inp: ActorInput, cfg: FitConfig) -> tuple[ActorInput, list[float]]:
    """``(inp', change_mm)``: ``inp`` with each tracker's offset ``trk_offset (K, 3)`` (m, segment frame)
    weighed with its segment's protocol site (module docstring), and each offset's change (mm). Unchanged
    when ``cfg.sigma_suit_skeleton_m`` is 0 (sync's offsets as they are) or the actor has no trackers. A
    non-finite offset (a tracker sync could not calibrate) takes the site."""
    K = len(inp.trk_segment)
    if K == 0 or cfg.sigma_suit_skeleton_m <= 0:
        return inp, []
    o_sync = np.asarray(inp.trk_offset, np.float64)
    site = np.array([tracker_site(MVN_SEGMENTS[int(s)]) for s in inp.trk_segment], np.float64)
    s_skel = skeleton_std(inp, cfg)[:, None]
    w = s_skel**2 / (s_skel**2 + SITE_M**2)
    o = np.where(np.isfinite(o_sync), w * site + (1.0 - w) * np.nan_to_num(o_sync), site)
    change = np.linalg.norm(o - np.nan_to_num(o_sync), axis=-1) * 1000
    return replace(inp, trk_offset=o), [round(float(v), 1) for v in change]

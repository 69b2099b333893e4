"""The fit's tracker offsets on the body: sync's offset and the protocol's site weighed by their stds."""

import numpy as np
import pytest

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.fit.config import FitConfig
from dualhuman_builder.fit.inputs import ActorInput
from dualhuman_builder.fit.mounts import chain_links, offsets_on_body, skeleton_std
from dualhuman_builder.rig import tracker_site
from dualhuman_builder.sync.priors import SITE_M


def _input(offsets, segments=("Pelvis", "RightHand"), rms=None):
    T, K = 3, len(segments)
    return ActorInput(name="a", shape={}, seg_rot=np.tile([0.0, 0.0, 0.0, 1.0], (T, 23, 1)), pelvis=np.zeros((T, 3)),
                      valid=np.ones(T, bool), trk_pos=np.zeros((T, K, 3)), trk_valid=np.ones((T, K), bool),
                      trk_segment=np.array([MVN_SEGMENTS.index(s) for s in segments]),
                      trk_offset=np.asarray(offsets, np.float64), ankles=np.zeros((T, 2, 3)), skeleton_rms_m=rms)  # fmt: skip


def test_inverse_variance_mean_of_sync_and_site():
    sync = np.array([[-0.15, 0.01, -0.05], [0.05, 0.06, 0.0]])
    site = np.array([tracker_site("Pelvis"), tracker_site("RightHand")])
    s = 0.025
    out, change = offsets_on_body(_input(sync), FitConfig(sigma_suit_skeleton_m=s))
    w = s**2 / (s**2 + SITE_M**2)
    np.testing.assert_allclose(out.trk_offset, w * site + (1 - w) * sync)
    np.testing.assert_allclose(change, np.linalg.norm(out.trk_offset - sync, axis=-1) * 1000, atol=0.06)
    # a tighter skeleton std trusts sync more
    tight, _ = offsets_on_body(_input(sync), FitConfig(sigma_suit_skeleton_m=0.005))
    assert np.linalg.norm(tight.trk_offset - sync) < np.linalg.norm(out.trk_offset - sync)


def test_off_keeps_sync_and_uncalibrated_takes_site():
    sync = np.array([[-0.15, 0.01, -0.05], [np.nan, np.nan, np.nan]])
    same, change = offsets_on_body(_input(sync), FitConfig(sigma_suit_skeleton_m=0.0))
    assert same.trk_offset is not None and change == []
    np.testing.assert_array_equal(same.trk_offset[0], sync[0])
    out, _ = offsets_on_body(_input(sync), FitConfig())
    np.testing.assert_allclose(out.trk_offset[1], tracker_site("RightHand"))
    assert np.isfinite(out.trk_offset).all()


def test_no_trackers_unchanged():
    inp = _input(np.zeros((0, 3)), segments=())
    out, change = offsets_on_body(inp, FitConfig())
    assert out is inp and change == []


@pytest.mark.parametrize("segment", ["Pelvis", "Head", "LeftFoot"])
def test_offset_at_its_site_does_not_move(segment):
    site = np.array([tracker_site(segment)])
    out, change = offsets_on_body(_input(site, segments=(segment,)), FitConfig())
    np.testing.assert_allclose(out.trk_offset, site)
    assert change == [0.0]


def test_chain_links_count_segments_from_the_pelvis():
    assert [chain_links(s) for s in ("Pelvis", "LeftFoot", "Head", "RightHand")] == [1, 4, 7, 9]


def test_measured_skeleton_std_grows_along_the_chain_and_sets_the_weight():
    sync = np.array([[-0.15, 0.01, -0.05], [0.05, 0.06, 0.0]])
    site = np.array([tracker_site("Pelvis"), tracker_site("RightHand")])
    np.testing.assert_allclose(skeleton_std(_input(sync, rms=0.015), FitConfig()), [0.015, 0.045])
    # a suit whose skeleton is anny's (a few mm): sync's offsets nearly kept; a suit cm off: the site counts more
    for rms in (0.003, 0.015):
        out, _ = offsets_on_body(_input(sync, rms=rms), FitConfig())
        w = (skeleton_std(_input(sync, rms=rms), FitConfig()) ** 2 / (skeleton_std(_input(sync, rms=rms), FitConfig()) ** 2
                                                                         + SITE_M**2))[:, None]  # fmt: skip
        np.testing.assert_allclose(out.trk_offset, w * site + (1 - w) * sync)
    near, _ = offsets_on_body(_input(sync, rms=0.003), FitConfig())
    assert np.linalg.norm(near.trk_offset[0] - sync[0]) < 0.03 * np.linalg.norm(site[0] - sync[0])
    # without a measurement (a registered shape) the configured std holds for every tracker
    np.testing.assert_allclose(skeleton_std(_input(sync), FitConfig(sigma_suit_skeleton_m=0.02)), [0.02, 0.02])

"""PA-MPJPE's alignment (:func:`~dualhuman_builder.evaluation.fit.procrustes_aligned`)."""

import numpy as np
from scipy.spatial.transform import Rotation

from dualhuman_builder.evaluation.fit import procrustes_aligned


def test_a_turned_scaled_moved_copy_aligns_exactly_and_noise_does_not_vanish():
    rng = np.random.default_rng(0)
    truth = rng.normal(0, 0.3, (5, 22, 3))
    rot = Rotation.random(5, random_state=1).as_matrix()
    pred = 1.3 * np.einsum("tij,tkj->tki", rot, truth) + rng.normal(0, 1, (5, 1, 3))
    assert np.abs(procrustes_aligned(pred, truth) - truth).max() < 1e-9
    noisy = truth + rng.normal(0, 0.01, truth.shape)
    err = np.linalg.norm(procrustes_aligned(noisy, truth) - truth, axis=-1)
    assert 0.005 < err.mean() < np.linalg.norm(noisy - truth, axis=-1).mean()


def test_a_mirror_image_is_not_aligned_by_a_reflection():
    truth = np.random.default_rng(2).normal(0, 0.3, (1, 22, 3))
    mirrored = truth * [-1.0, 1.0, 1.0]
    aligned = procrustes_aligned(mirrored, truth)
    assert np.linalg.norm(aligned - truth, axis=-1).mean() > 0.05

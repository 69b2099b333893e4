"""The scene generator's fast paths give the answers of the plain ones: the vectorised pair query
(:mod:`dualhuman_builder.sim.pairquery`) against ``PairDistance`` bit for bit, the ground-truth
distances with the winding number skipped where no vertex can be inside against the winding number
on every frame, and generation on one torch thread
(:data:`~dualhuman_builder.sim.scenes.TORCH_THREADS`), with the caller's thread count restored."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dualhuman_builder.sim.scenes import TORCH_THREADS, SceneParams, make_scene

_POSES: dict = {}


def _two_bodies(body_model):
    """Two rest bodies facing each other 0.4 m apart (their arms overlap), float64 ``(V, 3)`` each."""
    if not _POSES:
        import torch

        with torch.no_grad():
            rest = body_model.rest(body_model.default_shape()).vertices[0].double().numpy()
        turned = rest * [-1.0, 1.0, -1.0]  # half a turn about +Y
        _POSES["a"], _POSES["b"] = rest, turned + [0.0, 0.0, 0.4]
    return _POSES["a"], _POSES["b"]


def _same(x: np.ndarray, y: np.ndarray) -> bool:
    return x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()


@settings(max_examples=25, deadline=None)
@given(dx=st.floats(-0.3, 0.3), dz=st.floats(-0.45, 0.3), yaw=st.floats(-0.6, 0.6), band=st.sampled_from([0.01, 0.05]),
       query_seed=st.integers(0, 2**31 - 1))  # fmt: skip
def test_fast_pair_answers_as_pair_distance_bit_for_bit(dx, dz, yaw, band, query_seed, body_model):
    """Any placement of the second body, all vertices or a random query set, and any ``need``
    subset: ``FastPair`` returns ``PairDistance``'s distances on what it was asked for, NaN elsewhere."""
    from dualhuman_builder.geometry.distance import get_pair_distance
    from dualhuman_builder.sim.pairquery import get_fast_pair

    a, b0 = _two_bodies(body_model)
    c, s = np.cos(yaw), np.sin(yaw)
    b = (b0 - [0.0, 0.0, 0.4]) @ np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]]) + [dx, 0.0, 0.4 + dz]
    pair, fast = get_pair_distance(), get_fast_pair()
    rng = np.random.default_rng(query_seed)
    V = len(a)
    qa, qb = (np.sort(rng.choice(V, size=int(rng.integers(1, V)), replace=False)) for _ in range(2))
    for query in ((None, None), (qa, qb)):
        want = pair(a, b, band, *query)
        got = fast(a, b, band, *query)
        assert all(_same(w, g) for w, g in zip(want, got))
    na, nb = (q[rng.random(len(q)) < 0.3] for q in (qa, qb))
    got = fast(a, b, band, qa, qb, na, nb)
    for w, g, n in zip(pair(a, b, band, qa, qb), got, (na, nb)):
        assert _same(w[n], g[n])
        rest = np.ones(V, bool)
        rest[n] = False
        assert np.isnan(g[rest]).all()


def test_fast_pair_builds_no_mesh_for_a_far_body(body_model):
    """A body farther than the band from the other queries nothing, so no BVH is built; a near
    one builds both."""
    from dualhuman_builder.geometry.distance import PairDistance, get_pair_distance
    from dualhuman_builder.sim.pairquery import FastPair

    base = get_pair_distance()
    a, b = _two_bodies(body_model)
    faces = base.meshes[0]._indices.numpy().reshape(-1, 3)
    regions = np.zeros(len(a), np.int64)
    for r, g in enumerate(base.groups):
        regions[g] = r
    fresh = PairDistance(faces, len(a), None, regions)
    fast = FastPair(fresh)
    everyone = np.arange(len(a))
    far = fast(a, b + [5.0, 0.0, 0.0], 0.05, everyone, everyone)
    assert fresh.meshes[0].mesh is None and fresh.meshes[1].mesh is None  # nothing near: no mesh built
    assert np.isnan(far[0]).all() and np.isnan(far[1]).all()
    fast(a, b, 0.05, everyone, everyone)
    assert fresh.meshes[0].mesh is not None and fresh.meshes[1].mesh is not None


def test_ground_truth_distances_skip_the_winding_number_only_where_it_decides_nothing(body_model):
    """A handshake's ground truth, made with the winding number skipped on frames whose bodies'
    boxes are apart or have no vertex within the band, equals the banded distances signed by the
    winding number on every frame, bit for bit; and some frames were skipped (the approach)."""
    from dualhuman_builder.sim import scenes
    from dualhuman_builder.sim.pairquery import get_fast_pair
    from dualhuman_builder.sim.quality import sign_by_winding

    sc = make_scene(SceneParams(type="handshake", seed=0, fps=5.0), model=body_model)
    seq = sc.sequence
    got = scenes.ground_truth_distances(seq)
    pair = get_fast_pair()
    va, vb = seq.actors[0].vertices(), seq.actors[1].vertices()
    want = np.empty(va.shape[:2], np.float16), np.empty(vb.shape[:2], np.float16)
    for f in range(len(va)):
        want[0][f], want[1][f] = pair(va[f], vb[f], scenes.DISTANCE_BAND)
    far = [f for f in range(len(va)) if not (np.isfinite(want[0][f]).any() or np.isfinite(want[1][f]).any())]
    assert far, "the handshake's approach has frames with no vertex within the band"
    sign_by_winding(want, va, vb)
    assert all(_same(w, g) for w, g in zip(want, got))


def test_make_scene_runs_on_one_torch_thread_and_restores_the_callers(body_model):
    """The body-model calls of a generation run on :data:`TORCH_THREADS` threads (a loaded 2-core
    machine runs them several times faster so); the caller's setting is back afterwards, also
    when generation fails."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    seen = []
    try:
        make_scene(SceneParams(type="handshake", seed=0, fps=5.0), model=body_model,
                   log=lambda _line: seen.append(torch.get_num_threads()))  # fmt: skip
        assert seen and set(seen) == {TORCH_THREADS}
        assert torch.get_num_threads() == 2
        with pytest.raises(ValueError):
            make_scene(SceneParams(type="handshake", seed=0, fps=5.0, duration=1.0), model=body_model)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)

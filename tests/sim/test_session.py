"""Long takes: a session chains interactions with walks and stands between them; it meets the scene
contract, records each meeting's interval, and its joins are continuous."""

from __future__ import annotations

import numpy as np
import pytest

FPS = 10.0  # low, so one session generates in well under a minute; the walks and meetings are fps-independent
DURATION = 20.0


@pytest.fixture(scope="module")
def session():
    from dualhuman_builder.sim.generate import generate_scene
    from dualhuman_builder.sim.scenes import SceneParams

    return generate_scene(SceneParams(type="session", seed=3, duration=DURATION, fps=FPS))


def _joins(scene) -> list[int]:
    """Frames where a meeting starts or ends (inside the take)."""
    from dualhuman_builder.sim.session import interactions

    n = scene.sequence.num_frames
    frames = {int(round(v * FPS)) for r in interactions(scene) for v in (r["start_s"], r["end_s"])}
    return sorted(f for f in frames if 2 <= f < n - 2)


@pytest.mark.slow
def test_session_meets_the_contract_and_records_its_meetings(session, tmp_path):
    from dualhuman_builder.sim.scenes import SCENE_TYPES, Scene, contract_failures
    from dualhuman_builder.sim.session import interactions

    assert session.sequence.num_frames == int(DURATION * FPS)
    assert contract_failures(session.stats) == []
    meetings = interactions(session)
    assert len(meetings) >= 1 and all(m["type"] in SCENE_TYPES for m in meetings)
    assert set(session.sequence.labels) == {m["type"] for m in meetings}
    for a, b in zip(meetings, meetings[1:]):
        assert a["end_s"] < b["start_s"]  # walks between meetings
    # every contact phase lies in its meeting, and the bodies touch there and nowhere outside a meeting
    min_d = np.minimum(*(np.nan_to_num(d.astype(np.float32), nan=np.inf).min(1) for d in session.distances))
    t = session.times
    inside = np.zeros(len(t), bool)
    for m in meetings:
        assert m["contact_phases"] and all(m["start_s"] <= a < b <= m["end_s"] for a, b in m["contact_phases"])
        assert session.phases[f"{m['index']:02d} {m['type']}"] == pytest.approx((m["start_s"], m["end_s"]))
        inside |= (t >= m["start_s"]) & (t <= m["end_s"])
    assert (min_d[~inside] > 0.02).all()
    # the intervals survive a save and load
    back = Scene.load(session.save(tmp_path / "session.npz"))
    assert interactions(back) == meetings


@pytest.mark.slow
def test_session_joins_are_continuous(session):
    """At each meeting's start and end, no jump in the root's position or velocity, nor in any joint."""
    joins = _joins(session)
    assert joins
    for track in session.sequence.actors:
        root = np.asarray(track.transl, np.float64)
        joints = np.asarray(track.joints(), np.float64)
        step = np.linalg.norm(np.diff(root, axis=0), axis=-1)  # step[f]: frame f -> f + 1
        accel = np.linalg.norm(np.diff(root, 2, axis=0), axis=-1)  # accel[f]: about frame f + 1
        joint_step = np.linalg.norm(np.diff(joints, axis=0), axis=-1).max(1)
        for f in joins:
            assert step[f - 1] < 0.005, (track.actor, f, step[f - 1])  # standing at every join: < 5 mm per frame
            assert accel[f - 2:f].max() < 0.002, (track.actor, f)  # and no change of velocity
            assert joint_step[f - 1] < 0.01, (track.actor, f, joint_step[f - 1])


def test_session_refuses_what_it_cannot_hold():
    from dualhuman_builder.sim.generate import generate_scene
    from dualhuman_builder.sim.scenes import SceneParams

    with pytest.raises(ValueError, match="at least"):
        generate_scene(SceneParams(type="session", seed=0, duration=5.0, fps=FPS))
    with pytest.raises(ValueError, match="approach distance"):
        generate_scene(SceneParams(type="session", seed=0, approach_distance=1.0, fps=FPS))


def test_sim_url_names_a_session():
    from dualhuman_builder.capture.sources import parse_source_url
    from dualhuman_builder.sim.scenes import ALL_TYPES
    from dualhuman_builder.sim.source import SimSource

    parts, query = parse_source_url("sim://session?seed=3&duration=600", SimSource.PARAMS)
    assert parts.netloc == "session" and parts.netloc in ALL_TYPES and query["duration"] == "600"

"""The contact correction stops measuring frames it cannot improve: an embrace's palms, which move
each other and oscillate about the wanted gap, are left within tolerance instead of being
re-measured on every pass, and a scene of a high fps is measured on a coarser grid in time away from
frames found too close. Both keep the quality contract."""

from __future__ import annotations

import re

from dualhuman_builder.sim.scenes import SceneParams, contract_failures, make_scene


def _measured(lines: list[str]) -> list[int]:
    return [int(m.group(1)) for line in lines if (m := re.search(r"pass \d+: .*, (\d+) frames measured", line))]


def test_an_embrace_is_not_remeasured_on_every_pass(body_model):
    """Hug seed 0 at 8 fps: its four palms and the torsos pull on each other, so their gap errors
    change sign from pass to pass; once within tolerance they are left, and the last passes measure
    only the few release frames still too close."""
    lines: list[str] = []
    sc = make_scene(SceneParams(type="hug", seed=0, fps=8.0), model=body_model, log=lines.append)
    assert contract_failures(sc.stats) == [] and sc.stats["draws"] == 1
    measured = _measured(lines)
    assert measured, "the log names the frames each correction pass measured"
    assert max(measured[-3:]) <= measured[0] / 3


def test_a_high_fps_scene_is_measured_on_a_coarser_grid(body_model):
    """Handshake seed 0 at 30 fps: after the first pass, which measures every frame of the contact,
    the passes measure fewer frames (frames near one found too close are still all measured)."""
    lines: list[str] = []
    sc = make_scene(SceneParams(type="handshake", seed=0, fps=30.0), model=body_model, log=lines.append)
    assert contract_failures(sc.stats) == [] and sc.stats["draws"] == 1
    measured = _measured(lines)
    assert len(measured) >= 2 and all(m < measured[0] for m in measured[1:])


def test_a_second_swivel_pass_adds_its_turn_once():
    """An elbow already swivelled -1.2 rad at a frame, turned a further -0.7 there by the next pass,
    ends at -1.9 rad, not at -3.1 (the earlier swivel counted twice flipped a hugging arm's humerus
    by 165 degrees at the release); frames the pass left alone keep their swivel, and the turn is
    smoothed over its neighbours without falling below it."""
    import numpy as np

    from dualhuman_builder.sim.scenes import add_swivel_turns

    first, moved = add_swivel_turns(None, np.eye(1, 30, 20)[0] * -1.2)
    assert first[20] == -1.2 and moved[19] and moved[21] and not moved[0]
    turns = np.zeros(30)
    turns[20] = -0.7
    second, moved = add_swivel_turns(first, turns)
    assert second[20] == -1.9 and second[0] == first[0] == 0.0
    assert -1.9 < second[19] < first[19] < 0 and set(np.flatnonzero(moved)) <= set(range(14, 27))

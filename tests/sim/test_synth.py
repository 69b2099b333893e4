"""Synthetic datasets (dualhuman_builder.sim.synth, `dualhuman synth`): the plan is reproducible and
varied, the hold-outs hold out, the ground-truth path exports verified data marked as ground truth,
a second call resumes and other arguments are refused; the full path makes the first stages."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st

from dualhuman_builder.sim.synth import (APPROACH_M, APPROACH_SPREAD_M, STATURE_M, TEMPO, SynthError, SynthOptions,
                                         load_plan, make_synthetic, plan_bytes, plan_splits, plan_synthetic)  # fmt: skip

FPS = 7.5
#: Two short takes, one of each type: the held-out type's take is the test split.
GT = SynthOptions(takes=2, seed=3, types=("handshake", "high_five"), fps=FPS, long_share=0.0,
                  hold_out_types=("high_five",))


def test_same_seed_same_plan_other_seed_other_plan():
    a, b = plan_synthetic(SynthOptions(takes=12, seed=5)), plan_synthetic(SynthOptions(takes=12, seed=5))
    assert plan_bytes(a) == plan_bytes(b)
    c = plan_synthetic(SynthOptions(takes=12, seed=6))
    assert [t["seed"] for t in c["takes"]] != [t["seed"] for t in a["takes"]]
    assert [x["stature_m"] for x in c["actors"]] != [x["stature_m"] for x in a["actors"]]


def test_plan_varies_within_its_documented_ranges():
    plan = plan_synthetic(SynthOptions(takes=40, seed=2, preset="mixed", long_share=0.1, actors=8))
    takes = plan["takes"]
    assert sum(t["type"] == "session" for t in takes) == 4
    counts = {}
    for t in takes:
        counts[t["type"]] = counts.get(t["type"], 0) + 1
        assert t["actors"][0] != t["actors"][1]
        assert TEMPO[0] <= t["tempo"] <= TEMPO[1]
        if t["type"] in APPROACH_M:
            assert abs(t["approach_distance_m"] - APPROACH_M[t["type"]]) <= APPROACH_SPREAD_M
        else:
            assert t["approach_distance_m"] is None
        assert t["split"] is None
    interactions = [v for k, v in counts.items() if k != "session"]
    # shuffled rounds; a dance turn may wait for a day whose first actor is the taller
    assert len(interactions) == 6 and max(interactions) - min(interactions) <= 3
    days = plan["days"]
    assert len(days) == 7  # 40 takes, 6 a day
    assert sum(d["preset"] == "realistic" for d in days) == 3  # mixed: half the days, rounded down
    assert len({t["seed"] for t in takes}) == 40 and len({t["tempo"] for t in takes}) > 30
    genders = {a["gender"] for a in plan["actors"]}
    assert genders == {"female", "male"}
    for a in plan["actors"]:
        lo, hi = STATURE_M[a["gender"]]
        assert lo <= a["stature_m"] <= hi
    statures = {t["actors"][0]: None for t in takes}
    assert len(statures) > 3
    by_name = {a["name"]: a["stature_m"] for a in plan["actors"]}
    for t in takes:  # the taller partner leads a dance turn
        if t["type"] == "dance_turn":
            assert by_name[t["actors"][0]] >= by_name[t["actors"][1]]


def test_a_studio_day_shares_its_pair_devices_preset_and_calibration_take():
    plan = plan_synthetic(SynthOptions(takes=13, seed=9, preset="mixed", takes_per_day=4))
    days = {d["day"]: d for d in plan["days"]}
    assert len(days) == 4 and len({d["device_seed"] for d in days.values()}) == 4
    assert len({d["calibration_take"] for d in days.values()} | {t["take"] for t in plan["takes"]}) == 17
    for k, t in enumerate(plan["takes"]):
        d = days[t["day"]]
        assert t["day"] == plan["days"][k // 4]["day"]
        assert t["actors"] == d["actors"] and t["device_seed"] == d["device_seed"] and t["preset"] == d["preset"]
        assert t["mounts_from"] == d["calibration_take"]
    assert len({t["seed"] for t in plan["takes"]}) == 13  # each take its own scene
    assert plan["arguments"]["takes_per_day"] == 4 and plan["arguments"]["actors"] == 8  # two per day
    with pytest.raises(SynthError, match="a studio day has 1 to 1000 takes") as e:
        plan_synthetic(SynthOptions(takes=3, takes_per_day=0))
    assert "--takes-per-day" in e.value.fix


def test_hold_outs_put_actors_and_types_in_test_only():
    plan = plan_synthetic(SynthOptions(takes=30, seed=1, actors=10, hold_out_actors=2, hold_out_types=("hug",),
                                       long_share=0.1))  # fmt: skip
    held = set(plan["split"]["held_out_actors"])
    assert len(held) == 2 and {a["name"] for a in plan["actors"] if a["held_out"]} == held
    for t in plan["takes"]:
        touches = bool(held & set(t["actors"])) or t["type"] in ("hug", "session")
        assert t["split"] == ("test" if touches else "train"), t
    train = [t for t in plan["takes"] if t["split"] == "train"]
    assert train and not any(held & set(t["actors"]) for t in train) and all(t["type"] != "hug" for t in train)
    assert plan["split"]["train"] == len(train) and plan["split"]["train"] + plan["split"]["test"] == 30
    assert set(plan_splits(plan)) == {t["take"] for t in plan["takes"]}


@pytest.mark.parametrize("options, words", [
    (dict(takes=0), "1 to"),
    (dict(takes=2, types=("hug", "wave")), "unknown interaction type 'wave'"),
    (dict(takes=2, types=("session",)), "not an interaction type"),
    (dict(takes=2, types=("calibration",)), "not an interaction type"),
    (dict(takes=2, hold_out_types=("kick",)), "unknown interaction type"),
    (dict(takes=2, types=("hug",), hold_out_types=("handshake",)), "not among the drawn types"),
    (dict(takes=2, preset="noisy"), "unknown device error preset"),
    (dict(takes=2, actors=4, hold_out_actors=4), "cannot hold out 4 of 4"),
    (dict(takes=3, types=("hug",), hold_out_types=("hug",)), "train split would be empty"),
    (dict(takes=2, long_duration=5.0), "out of range"),
    (dict(takes=2, max_draws=0), "max draws 0 is out of range"),
])  # fmt: skip
def test_invalid_options_are_refused_with_a_fix(options, words):
    with pytest.raises(SynthError, match=words) as e:
        plan_synthetic(SynthOptions(**options))
    assert e.value.fix


def test_max_draws_is_refused_on_the_full_path(tmp_path):
    with pytest.raises(SynthError, match="--max-draws bounds the ground-truth path") as e:
        make_synthetic(tmp_path / "ws", SynthOptions(takes=2, max_draws=3), path="full")
    assert "--path ground-truth" in e.value.fix and not (tmp_path / "ws").exists()


def test_hold_outs_that_leave_test_empty_are_refused():
    # one take and a large pool: for some seed the held-out actor is in no take
    refused = []
    for seed in range(20):
        try:
            plan_synthetic(SynthOptions(takes=1, seed=seed, actors=20, hold_out_actors=1, long_share=0.0))
        except SynthError as e:
            assert e.fix
            refused.append(e.message)
    assert any("the test split would be empty" in m for m in refused)


@given(st.fixed_dictionaries({}, optional={
    "takes": st.one_of(st.integers(-3, 40), st.floats(allow_nan=True), st.booleans(), st.text(max_size=3)),
    "seed": st.one_of(st.integers(-5, 2**70), st.floats(), st.none()),
    "types": st.one_of(st.lists(st.sampled_from(["hug", "push", "session", "x", ""]), max_size=4).map(tuple),
                       st.text(max_size=4)),
    "preset": st.sampled_from(["ideal", "mixed", "realistic", "", "ideal "]),
    "fps": st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-2, 300)),
    "long_share": st.floats(allow_nan=True, allow_infinity=True),
    "long_duration": st.floats(allow_nan=True, allow_infinity=True),
    "actors": st.one_of(st.none(), st.integers(-2, 50), st.floats()),
    "hold_out_actors": st.one_of(st.integers(-2, 60), st.floats()),
    "hold_out_types": st.lists(st.sampled_from(["hug", "push", "x"]), max_size=3).map(tuple),
    "speed": st.floats(allow_nan=True, allow_infinity=True),
}))  # fmt: skip
def test_any_options_give_a_plan_or_a_clear_error(kwargs):
    kwargs.setdefault("takes", 3)
    try:
        plan = plan_synthetic(SynthOptions(**kwargs))
    except SynthError as e:
        assert e.fix
        return
    assert len(plan["takes"]) == kwargs["takes"]
    json.dumps(plan, allow_nan=False)  # finite numbers only


@given(st.binary(max_size=300) | st.sampled_from([b"[" * 100000, b'{"format": "dualhuman-synth-plan"}',
                                                 b'{"format": "dualhuman-synth-plan", "version": 1, "arguments": 3}',
                                                 b"\xff\xfe", b"null", b'"x"']))  # fmt: skip
def test_a_broken_plan_file_is_a_clear_error(tmp_path_factory, data):
    root = tmp_path_factory.mktemp("plan")
    (root / "synth.json").write_bytes(data)
    try:
        plan = load_plan(root)
    except SynthError as e:
        assert e.fix
        return
    assert isinstance(plan, dict) and isinstance(plan["arguments"], dict)


@pytest.fixture(scope="module")
def ground_truth(tmp_path_factory, body_model) -> tuple[Path, Path, object]:
    """Two tiny takes through the ground-truth path (the held-out type in test), made by two worker
    processes (the resume test then reads their files in this process)."""
    from dualhuman_builder.batch.synth import make_synthetic as make_in_workers

    root = tmp_path_factory.mktemp("gt")
    result = make_in_workers(root / "ws", GT, path="ground-truth", export=root / "out", model=body_model, jobs=2,
                             log=lambda m: None, progress=lambda m: None)  # fmt: skip
    return root / "ws", root / "out", result


def test_ground_truth_export_verifies_and_says_ground_truth(ground_truth):
    from dualhuman_builder.export.verify import verify_export

    ws, out, result = ground_truth
    assert sorted(result.made) == ["S0001", "S0002"] and not result.failed
    assert verify_export(out) == []
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["source"] == "ground-truth" and manifest["synth"]["arguments"]["seed"] == GT.seed
    assert "Ground truth, not fitted data" in (out / "README.md").read_text()  # the dataset card says it too
    plan = load_plan(ws)
    for t in plan["takes"]:
        doc = json.loads((out / "sequences" / t["take"] / "sequence.json").read_text())
        assert doc["meta"]["source"] == "ground-truth" and doc["has"]["contacts"] and doc["labels"] == [t["type"]]
        assert doc["subjects"] == t["actors"]
        assert manifest["sequences"][t["take"]]["split"] == t["split"]
    test = (out / "splits" / "test.txt").read_text().split()
    assert test == [t["take"] for t in plan["takes"] if t["type"] == "high_five"]
    assert manifest["split"]["given"] == 2


def test_ground_truth_resumes_and_refuses_other_arguments(ground_truth, body_model):
    ws, out, _ = ground_truth
    plan_before = (ws / "synth.json").read_bytes()
    lines = []
    again = make_synthetic(ws, GT, path="ground-truth", export=out, model=body_model, log=lambda m: None,
                           progress=lines.append)  # fmt: skip
    assert again.made == [] and sorted(again.skipped) == ["S0001", "S0002"]
    assert len(lines) == 2 and all("made before" in x for x in lines)
    assert (ws / "synth.json").read_bytes() == plan_before
    other = SynthOptions(**{**GT.__dict__, "seed": GT.seed + 1})
    with pytest.raises(SynthError, match="seed 3 -> 4") as e:
        make_synthetic(ws, other, path="ground-truth", export=out, model=body_model, log=lambda m: None)
    assert "another workspace" in e.value.fix
    assert (ws / "synth.json").read_bytes() == plan_before


def test_ground_truth_path_needs_an_export_folder(tmp_path):
    with pytest.raises(SynthError, match="needs its folder"):
        make_synthetic(tmp_path / "ws", GT, path="ground-truth", export=None)


def test_cli_plans_resumes_and_reports_errors(ground_truth):
    import dualhuman_builder.cli.synth  # noqa: F401  (registers the command)
    from dualhuman_builder.cli import main
    from dualhuman_builder.cli.synth import MAX_DRAWS as cli_max_draws
    from dualhuman_builder.cli.synth import SYNTH_TYPES
    from dualhuman_builder.sim.scenes import MAX_DRAWS, SCENE_TYPES

    assert SYNTH_TYPES == SCENE_TYPES and cli_max_draws == MAX_DRAWS
    ws, out, _ = ground_truth
    args = ["synth", str(ws), "--takes", "2", "--seed", "3", "--types", "handshake,high_five", "--fps", str(FPS),
            "--long-share", "0", "--hold-out-types", "high_five"]  # fmt: skip
    r = CliRunner().invoke(main, [*args, "--path", "ground-truth", "--export", str(out)])
    assert r.exit_code == 0, r.output
    assert r.output.count(": made before") == 2 and "0 made, 2 made before" in r.output
    assert "1 train, 1 test" in r.output and "source ground-truth" in r.output
    assert "studio day" not in r.output  # no devices on the ground-truth path
    r = CliRunner().invoke(main, [*args, "--plan-only"])
    assert r.exit_code == 0 and "over 1 studio day(s)" in r.output
    r = CliRunner().invoke(main, [*args[:-1], "handshake", "--plan-only"])
    assert r.exit_code == 2 and "other arguments" in r.output and "hold_out_types" in r.output
    r = CliRunner().invoke(main, ["synth", "--help"], terminal_width=80)
    assert r.exit_code == 0 and "--hold-out-types" in r.output and max(map(len, r.output.splitlines())) <= 80
    r = CliRunner().invoke(main, ["synth", str(ws.parent / "new"), "--takes", "2", "--types", "hug,wave"])
    assert r.exit_code == 2 and "unknown interaction type 'wave'" in r.output and "fix:" in r.output
    assert not (ws.parent / "new").exists()


@pytest.mark.slow
def test_full_path_makes_the_first_stages_and_resumes(tmp_path, body_model):
    from dualhuman_builder.batch.plan import RunOptions, make_plan
    from dualhuman_builder.workspace import Workspace

    options = SynthOptions(takes=1, seed=4, types=("high_five",), fps=FPS, long_share=0.0, preset="realistic",
                           speed=8.0)
    root = tmp_path / "ws"
    first = make_synthetic(root, options, model=body_model, log=lambda m: None, progress=lambda m: None)
    assert first.made == ["S0001"] and first.calibrations == ["C001"] and not first.failed
    t = first.plan["takes"][0]
    with Workspace.open(root) as ws:
        assert list(ws.take("S0001").actors) == t["actors"] and ws.take("S0001").meta["preset"] == "realistic"
        for stage in ("scene", "devices", "capture"):
            assert ws.stage_record(stage, "S0001", "high_five")["status"] == "done"
            assert ws.stage_record(stage, "C001", "calibration")["status"] == "done"
        scene = ws.stage_record("scene", "S0001", "high_five")["params"]
        assert scene["tempo"] == t["tempo"] and scene["approach_distance"] == t["approach_distance_m"]
        # the day's takes share one draw of the devices (so their tracker mounts), not their scenes
        devices = [ws.stage_record("devices", k, q)["params"] for k, q in (("S0001", "high_five"), ("C001", "calibration"))]
        assert devices[0] == devices[1] == {"seed": t["device_seed"], "preset": "realistic"}
        assert ws.take("C001").meta["calibration"] and list(ws.take("C001").actors) == t["actors"]
        assert [a.labels for a in ws.annotations("S0001")] == [("high_five",)]
        plan = make_plan(ws, RunOptions(takes=("S0001",)))  # `dualhuman run` goes on from here
        assert [x.key for x in plan.tasks][:2] == [("C001", "sync"), ("S0001", "sync")]
        assert plan.tasks[1].after == [("C001", "sync")]
        assert plan.skipped[("C001", "fit")].startswith("a calibration take")
    with pytest.raises(SynthError, match="no take of the plan has a complete fit") as e:  # resumed; nothing to export
        make_synthetic(root, options, export=tmp_path / "out", model=body_model, log=lambda m: None,
                       progress=lambda m: None)
    assert "dualhuman run" in e.value.fix
    lines = []
    again = make_synthetic(root, options, model=body_model, log=lambda m: None, progress=lines.append)
    assert again.made == [] and again.skipped == ["S0001"] and all("made before" in x for x in lines[:2])


def test_a_take_whose_scene_is_refused_is_reported_failed_and_the_others_go_on(ground_truth, body_model):
    from dualhuman_builder.batch.synth import GROUND_TRUTH_TASK, _in_workers
    from dualhuman_builder.batch.worker import TASK_KINDS
    from dualhuman_builder.sim.scenes import GENERATOR_VERSION, MAX_DRAWS
    from dualhuman_builder.sim.synth import SynthResult, _ground_truth_item, _register_actors, ground_truth_files
    from dualhuman_builder.workspace import Workspace

    ws_root, _, _ = ground_truth
    plan = load_plan(ws_root)
    bad = {**plan["takes"][0], "take": "BAD", "approach_distance_m": 0.2}  # nearer than any handshake reaches
    result, lines = SynthResult(plan), []
    with Workspace.open(ws_root) as ws:
        actors = _register_actors(ws, plan, body_model, log=lambda m: None)
        made = list(_in_workers(1, ws, {"takes": [bad, plan["takes"][1]]}, actors, None, lambda m: None))
        items = [_ground_truth_item(ws, t, m, lines.append, "[k/2]", result) for t, m in made]
    assert "approach distance 0.20 m is closer" in result.failed["BAD"] and "FAILED" in lines[0]
    assert items[0] is None and items[1].seq_id == plan["takes"][1]["take"] and result.skipped == [items[1].seq_id]
    assert "made before" in lines[1]
    assert TASK_KINDS[GROUND_TRUTH_TASK] == "dualhuman_builder.batch.synth:ground_truth_task"
    # the failure is recorded and answered again without drawing, until more draws are asked for
    shapes = [actors[a][1] for a in bad["actors"]]
    memo = ws_root / "synth" / "scenes" / f"BAD-g{GENERATOR_VERSION}.failed.json"
    assert json.loads(memo.read_text())["max_draws"] == MAX_DRAWS
    again = ground_truth_files(ws_root, bad, shapes, model=None, log=lambda m: None)
    assert "failed before" in again["failed"] and "approach distance 0.20 m" in again["failed"]
    more = ground_truth_files(ws_root, bad, shapes, model=body_model, log=lambda m: None, max_draws=MAX_DRAWS + 1)
    assert "failed before" not in more["failed"] and json.loads(memo.read_text())["max_draws"] == MAX_DRAWS + 1
    other = {**bad, "approach_distance_m": 0.25}  # other parameters are drawn afresh
    assert "failed before" not in ground_truth_files(ws_root, other, shapes, model=body_model, log=lambda m: None)["failed"]


def test_export_synth_split_needs_a_plan(tmp_path):
    from click.testing import CliRunner

    from dualhuman_builder.cli import main
    from dualhuman_builder.workspace import Workspace

    Workspace.init(tmp_path / "ws").close()
    r = CliRunner().invoke(main, ["export", "build", str(tmp_path / "ws"), str(tmp_path / "out"), "--synth-split"])
    assert r.exit_code == 2 and "synth.json" in r.output

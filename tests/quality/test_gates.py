"""Quality gates: injected tracker loss and penetration are flagged and stored, gates of stages not
done are skipped, `status` shows the flags, `export` leaves the flagged take out unless
--include-flagged, the config is checked, and the catalog's version 3 -> 4 migration."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st
from quality_ws import build, make_workspace, qws  # noqa: F401  (qws: a fixture)

import dualhuman_builder.cli.quality  # noqa: F401  (registers `gates` and `review`)
from dualhuman_builder.cli import main
from dualhuman_builder.errors import FormatError
from dualhuman_builder.quality.gates import (
    GATE_NAMES,
    check_take,
    default_config,
    flickers,
    foot_slide_mm_s,
    load_config,
    stored_flags,
)
from dualhuman_builder.workspace import Workspace
from dualhuman_builder.workspace import catalog as catalog_module


def _flat(res) -> str:
    """A command's output with rich's line wrapping undone."""
    return " ".join(res.output.split())


def test_injected_tracker_loss_and_penetration_are_flagged_and_stored(qws):
    flags = check_take(qws, "BAD")
    by = {(f.gate, f.subject): f for f in flags}
    assert {f.gate for f in flags} == {"tracker_loss", "penetration"}, flags
    loss = by[("tracker_loss", "ALICE-PELVIS")]
    assert loss.stage == "fuse" and loss.value == pytest.approx(0.4) and loss.threshold == 0.2
    assert "40.0 %" in loss.message and "3 jumps rejected" in loss.message
    pen = [f for f in flags if f.gate == "penetration"]
    assert sorted((f.value, f.threshold) for f in pen) == [(0.03, 0.01), (14.0, 10.0)]
    assert check_take(qws, "GOOD") == []
    assert check_take(qws, "RAW") == []  # nothing ran: every gate skipped, none failed
    stored = stored_flags(qws)
    assert set(stored) == {"BAD", "GOOD", "RAW"}
    assert len(stored["BAD"]["flags"]) == 4 and stored["BAD"]["outdated"] == []
    assert stored["GOOD"]["flags"] == [] and set(stored["GOOD"]["evaluated"]) == set(GATE_NAMES) - {"sync_warnings", "root_drift"}
    assert stored["GOOD"]["skipped"] == {"sync_warnings": "sync has not run", "root_drift": "sync has not run"}
    assert stored["RAW"]["evaluated"] == [] and stored["RAW"]["skipped"]["render_completeness"] == "render has not run"
    # checking again replaces the take's flags: with looser thresholds the take is clean
    assert check_take(qws, "BAD", {"tracker_loss": {"max_share": 0.5}, "penetration": {"max_mm": 20, "max_share": 0.05}}) == []
    assert stored_flags(qws, "BAD")["BAD"]["flags"] == []


def test_a_gate_whose_stage_is_stale_is_skipped_and_old_flags_show_as_outdated(qws, body_model):
    check_take(qws, "BAD")
    build(qws, body_model, "BAD", bad=True)  # the same results again: nothing re-runs
    assert stored_flags(qws, "BAD")["BAD"]["outdated"] == []
    qws.run_stage("fuse", lambda out: out.path("fuse.json").write_text("{}") and {}, take="BAD", force=True)
    v = stored_flags(qws, "BAD")["BAD"]
    assert v["outdated"] == ["contacts", "fit", "fuse", "render"]  # fuse ran again, the others went stale
    flags = check_take(qws, "BAD")
    v = stored_flags(qws, "BAD")["BAD"]
    assert flags == [] and v["evaluated"] == ["tracker_loss"] and v["outdated"] == []
    assert v["skipped"]["penetration"] == "fit is stale" and v["skipped"]["render_completeness"] == "render is stale"


def test_an_unreadable_artifact_is_a_flag_not_a_crash(qws):
    rec = qws.stage_record("fuse", "BAD")
    path = qws.root / rec["artifacts"]["fuse.json"]["path"]
    path.write_bytes(b"\xff" * path.stat().st_size)  # damaged in place, same size
    flags = [f for f in check_take(qws, "BAD") if f.gate == "tracker_loss"]
    assert len(flags) == 1 and flags[0].value is None and "could not evaluate" in flags[0].message
    assert "status" in flags[0].message and "--verify" in flags[0].message


def test_render_completeness_counts_missing_images(qws):
    rec = qws.stage_record("render", "GOOD")
    (qws.root / rec["artifacts"]["views/view00/depth/00005.exr"]["path"]).unlink()
    flags = check_take(qws, "GOOD")
    assert [(f.gate, f.value) for f in flags] == [("render_completeness", pytest.approx(1 / 6, abs=1e-4))]
    assert "1 of 6 images missing (first: views/view00/depth/00005.exr" in flags[0].message


def test_export_leaves_the_flagged_take_out_unless_include_flagged(tmp_path, body_model):
    from dualhuman_builder.export.verify import verify_export

    with make_workspace(tmp_path / "ws", body_model, stages=("fuse", "fit")) as qws:
        check_take(qws, "BAD")
        check_take(qws, "GOOD")
    runner = CliRunner()
    out = tmp_path / "export"
    res = runner.invoke(main, ["export", str(qws.root), str(out)], terminal_width=300)
    assert res.exit_code == 0, res.output
    assert "take 'BAD' left out: flagged by the quality gates: tracker_loss (fuse): alice: tracker ALICE-PELVIS" in _flat(res)
    assert "--include-flagged" in _flat(res)
    manifest = json.loads((out / "manifest.json").read_text())
    assert list(manifest["sequences"]) == ["GOOD"]
    assert {f["gate"] for f in manifest["quality"]["left_out"]["BAD"]} == {"tracker_loss", "penetration"}
    assert manifest["quality"]["included"] == {} and manifest["quality"]["unchecked"] == []
    assert verify_export(out) == []
    res = runner.invoke(main, ["export", str(qws.root), str(out), "--include-flagged"], terminal_width=300)
    assert res.exit_code == 0, res.output
    assert "take 'BAD' exported although flagged" in _flat(res)
    manifest = json.loads((out / "manifest.json").read_text())
    assert sorted(manifest["sequences"]) == ["BAD", "GOOD"] and list(manifest["quality"]["included"]) == ["BAD"]
    assert manifest["quality"]["left_out"] == {} and verify_export(out) == []
    # only flagged takes to export: a clear error that says how to export them anyway
    res = runner.invoke(main, ["export", str(qws.root), str(tmp_path / "e2"), "--take", "BAD"], terminal_width=300)
    assert res.exit_code == 2 and "every fitted take is flagged" in _flat(res) and "--include-flagged" in _flat(res)


def test_status_and_gates_commands_show_the_flags(qws, tmp_path):
    runner = CliRunner()
    res = runner.invoke(main, ["gates", str(qws.root)], terminal_width=300)
    assert res.exit_code == 0, res.output
    assert "BAD: 4 flag(s)" in _flat(res) and "GOOD: clean" in _flat(res) and "3 take(s) checked, 1 flagged" in _flat(res)
    assert runner.invoke(main, ["gates", str(qws.root), "--fail-on-flags"]).exit_code == 1
    res = runner.invoke(main, ["status", str(qws.root)], terminal_width=300)
    assert res.exit_code == 0, res.output
    assert "flagged BAD: 4 flag(s)" in _flat(res) and "penetration (fit): the bodies overlap by up to 14.0 mm" in _flat(res)
    assert "GOOD:" not in _flat(res)
    doc = json.loads(runner.invoke(main, ["status", str(qws.root), "--json"]).output)
    assert len(doc["quality"]["BAD"]["flags"]) == 4 and doc["quality"]["GOOD"]["flags"] == []
    cfg = tmp_path / "loose.toml"
    cfg.write_text("[tracker_loss]\nmax_share = 0.5\n[penetration]\nenabled = false\n")
    res = runner.invoke(main, ["gates", str(qws.root), "--take", "BAD", "--config", str(cfg), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["BAD"]["skipped"]["penetration"] == "disabled in the config"
    assert "flagged" not in _flat(runner.invoke(main, ["status", str(qws.root)]))
    cfg.write_text("[penetration]\nmax_depth = 3\n")
    res = runner.invoke(main, ["gates", str(qws.root), "--config", str(cfg)])
    assert res.exit_code == 2 and "gate 'penetration' has no key 'max_depth'" in _flat(res)
    res = runner.invoke(main, ["gates", str(qws.root), "--take", "NOPE"])
    assert res.exit_code == 2 and "no take 'NOPE'" in _flat(res)


def test_the_bundled_config_documents_every_gate():
    from importlib import resources

    cfg = default_config()
    assert set(cfg) == set(GATE_NAMES) and all(cfg[g]["enabled"] is True for g in GATE_NAMES)
    text = resources.files("dualhuman_builder.quality").joinpath("gates.toml").read_text()
    for gate in GATE_NAMES:  # each gate's table says which stage it reads
        line = next(ln for ln in text.splitlines() if ln.startswith(f"[{gate}]"))
        assert "# stage " in line
    with pytest.raises(FormatError, match=r"penetration.max_mm = -1 must be a finite number >= 0"):
        load_config({"penetration": {"max_mm": -1}})
    with pytest.raises(FormatError, match="no gate named 'typo'"):
        load_config({"typo": {}})


@given(st.binary(max_size=300) | st.text(max_size=200).map(lambda s: s.encode("utf-8", "surrogatepass")))
def test_any_config_file_loads_or_gives_a_clear_error(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("cfg") / "gates.toml"
    path.write_bytes(data)
    try:
        cfg = load_config(path)
    except FormatError as e:
        assert e.message and e.message.startswith(("quality gate config", "cannot read"))
        return
    assert set(cfg) == set(GATE_NAMES)


def test_flickers_count_short_runs_and_inner_gaps():
    on = np.array([0, 0, 1, 1, 1, 1, 0, 1, 1, 1, 1, 0, 0, 0, 1, 0, 0], bool)
    assert flickers(on, 3) == 2  # the one-frame gap and the one-frame touch
    assert flickers(np.array([1, 0, 0, 0, 0], bool), 3) == 1  # a short touch at the start still counts
    assert flickers(np.array([0, 1, 1, 1, 1, 0], bool), 3) == 0  # short gaps at the ends do not
    assert flickers(np.zeros(0, bool), 3) == 0


def test_foot_slide_is_the_horizontal_speed_of_feet_in_stance():
    fps, T = 30.0, 60
    joints = np.zeros((T, 22, 3))
    joints[:, :, 1] = 0.05
    joints[:, 10, 0] = np.arange(T) * 0.002  # the left foot slides 60 mm/s on the floor
    assert foot_slide_mm_s(joints, fps, 0.15, 0.03) == pytest.approx(30.0)  # the right foot stands still: half the pairs
    joints[:, 11, 1] = 0.05 + 0.3 * (np.arange(T) >= 30)  # the right foot lifts after 1 s: out of stance up there
    assert foot_slide_mm_s(joints, fps, 0.15, 0.03) == pytest.approx(60.0 * 59 / (59 + 29))
    joints[:, 10, 0] = np.arange(T) * 0.01  # 300 mm/s: too fast to be stance
    assert foot_slide_mm_s(joints[:, :, :], fps, 0.15, 0.03) == pytest.approx(0.0)
    assert foot_slide_mm_s(joints[:1], fps, 0.15, 0.03) is None


def test_a_version_3_catalog_gets_the_quality_tables_when_opened_for_writing(tmp_path):
    root = tmp_path / "ws"
    (root / "artifacts").mkdir(parents=True)
    conn = sqlite3.connect(root / "catalog.sqlite")
    conn.executescript(catalog_module.SCHEMA + catalog_module.MIGRATIONS[1] + ";" + catalog_module.MIGRATIONS[2] + """;
        INSERT INTO meta VALUES ('format_version', '3'), ('created_with', 'dualhuman-builder 0.1');
        INSERT INTO takes (id, name, created_at) VALUES (1, 'T1', 'now');""")
    conn.close()
    with Workspace.open(root, readonly=True) as ro:  # read-only: left as it is, and no verdicts
        assert stored_flags(ro) == {}
        assert not ro.conn.execute("SELECT 1 FROM sqlite_master WHERE name = 'quality_flags'").fetchone()
    res = CliRunner().invoke(main, ["status", str(root)])
    assert res.exit_code == 0, res.output
    with Workspace.open(root) as w:
        assert w.conn.execute("SELECT value FROM meta WHERE key = 'format_version'").fetchone()[0] == "4"
        assert check_take(w, "T1") == [] and stored_flags(w)["T1"]["evaluated"] == []

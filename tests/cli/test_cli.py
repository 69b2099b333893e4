"""The CLI end to end through click's runner (real workspaces on disk, real body model)."""

import json

from click.testing import CliRunner
from conftest import snapshot

from dualhuman_builder import cli
from dualhuman_builder.resources import RIGS_DIR


def run(*args):
    return CliRunner().invoke(cli.main, [str(a) for a in args], catch_exceptions=False)


def test_help_reads_like_a_manual():
    r = run("--help")
    assert r.exit_code == 0
    for command in ("init", "status", "doctor", "demo", "body", "actor", "rig"):
        assert command in r.output
    r = run("status", "--help")
    assert "--verify" in r.output and "Read-only" in r.output
    r = run("fit", "--help")
    assert r.exit_code == 0 and "--relaxed-hands" in r.output and "--no-collision" in r.output and "--exact-contacts" in r.output


def test_workspace_commands(tmp_path):
    ws = tmp_path / "ws"
    r = run("init", ws)
    assert r.exit_code == 0 and "created workspace" in r.output
    assert "reusing workspace" in run("init", ws).output
    r = run("actor", "add", ws, "alice", "--height", "1.68", "--gender", "female")
    assert r.exit_code == 0 and "alice: 1.680 m, female" in r.output
    assert "alice" in run("actor", "list", ws).output
    r = run("rig", "add", ws, RIGS_DIR / "studio.toml")
    assert r.exit_code == 0 and "rig 'studio' stored" in r.output
    assert "studio" in run("rig", "list", ws).output
    r = run("status", ws, "--json")
    assert r.exit_code == 0 and json.loads(r.output) == {"rows": [], "problems": []}


def test_errors_are_specific_and_change_nothing(tmp_path):
    r = run("status", tmp_path / "missing")
    assert r.exit_code == 2
    assert "error: no such workspace folder" in r.output and "fix: create one with `dualhuman init" in r.output
    ws = tmp_path / "ws"
    run("init", ws)
    bad = tmp_path / "bad.toml"
    bad.write_text((RIGS_DIR / "studio.toml").read_text().replace('"Head"', '"Skull"', 1))
    before = snapshot(ws)
    r = run("rig", "add", ws, bad)
    assert r.exit_code == 2 and "unknown MVN segment 'Skull'" in r.output and str(bad) in r.output
    bad.write_text((RIGS_DIR / "studio.toml").read_text().replace('name = "studio"', ""))
    r = run("rig", "add", ws, bad)  # square brackets in messages survive the terminal markup
    assert r.exit_code == 2 and "needs a [rig] table with a non-empty name" in r.output
    r = run("actor", "add", ws, "giant", "--height", "250")
    assert r.exit_code == 2 and "not a human height in metres" in r.output
    assert snapshot(ws) == before


def test_rig_check_and_body_commands():
    r = run("rig", "check", RIGS_DIR / "studio.toml")
    assert r.exit_code == 0 and "rig 'studio' is valid: 4 sources, 2 actors" in r.output
    r = run("body", "warm", "--check")
    assert r.exit_code == 0 and "anny cache is built" in r.output
    r = run("body", "info", "--mapping", "--regions")
    assert r.exit_code == 0
    assert "13,718 / 27,420" in r.output and "watertight" in r.output and "RightUpperArm" in r.output
    assert "left_hand" in r.output

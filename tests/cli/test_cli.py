"""The CLI end to end through click's runner (real workspaces on disk, real body model)."""

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import click
import pytest
from click.testing import CliRunner
from conftest import snapshot

from dualhuman_builder import cli
from dualhuman_builder.pipeline import STAGE_NAMES
from dualhuman_builder.resources import RIGS_DIR
from dualhuman_builder.workspace import Workspace

REPO = Path(__file__).resolve().parents[2]
CUDA_WARNING = "Could not find or load the NVIDIA CUDA driver"

#: What a help text must not contain: measured speeds and timings, the machines they came from.
BENCHMARK_FIGURES = re.compile(r"pairs/s|frames/s|\d\s*x faster|\d\s*% faster|\bH[12]00\b|cProfile|\d+(\.\d+)? ?(ms|s)\)")


def run(*args, **kw):
    return CliRunner().invoke(cli.main, [str(a) for a in args], catch_exceptions=False, **kw)


def _commands(group: click.Group, path=()):
    for name, cmd in group.commands.items():
        yield (*path, name)
        if isinstance(cmd, click.Group):
            yield from _commands(cmd, (*path, name))


def test_help_reads_like_a_manual():
    r = run("--help")
    assert r.exit_code == 0
    for command in ("init", "status", "doctor", "demo", "body", "actor", "rig"):
        assert command in r.output
    r = run("status", "--help")
    assert "--verify" in r.output and "--long" in r.output and "Read-only" in r.output
    r = run("fit", "--help")
    assert r.exit_code == 0 and "--relaxed-hands" in r.output and "--no-collision" in r.output and "--exact-contacts" in r.output


def test_every_help_works_fits_80_columns_and_quotes_no_benchmark():
    paths = list(_commands(cli.main))
    assert len(paths) > 30 and ("body", "warm") in paths and ("export", "humanml3d") in paths
    for path in [(), *paths]:
        r = run(*path, "--help", terminal_width=80)
        assert r.exit_code == 0, (path, r.output)
        assert r.output.startswith("Usage: "), path
        assert not BENCHMARK_FIGURES.search(r.output), (path, BENCHMARK_FIGURES.search(r.output))
        long = [line for line in r.output.splitlines() if len(line) > 80]
        assert not long, (path, long)


def test_thin_entry_points_show_the_help():
    for argv in ([str(REPO / "cli.py")], ["-m", "dualhuman_builder"], [str(REPO / "cli.py"), "body"]):
        proc = subprocess.run([sys.executable, *argv, "--help"], capture_output=True, text=True, cwd=REPO, timeout=120)
        assert proc.returncode == 0, proc.stderr
        assert "Usage: " in proc.stdout and proc.stderr == ""


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
    assert r.exit_code == 0 and json.loads(r.output) == {"rows": [], "problems": [], "quality": {}}


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
    assert "anny cache is built" in r.output
    from dualhuman_builder.kernel_cache import kernel_cache_status

    kernels = "built" if kernel_cache_status()["built"] else "not built"  # out of date while kernels are edited
    assert r.exit_code == (0 if kernels == "built" else 1) and f"warp kernel cache is {kernels} in" in r.output
    r = run("body", "info", "--mapping", "--regions")
    assert r.exit_code == 0
    assert "13,718 / 27,420" in r.output and "watertight" in r.output and "RightUpperArm" in r.output
    assert "left_hand" in r.output


# ------------------------------------------------------------------------------------------ status
BOX_DRAWING = set("┏┓┗┛┃━┡┩╇┳┻│─└┘┌┐├┤┼")


def _write(name):
    def compute(out):
        out.path(name).write_text("x")

    return compute


def _boom(out):
    raise RuntimeError("renderer ran out of memory")


def _status_workspace(root: Path, long_sequence: str | None = None) -> Path:
    """Two takes as the demo leaves them, with a failed render and a sync still running."""
    with Workspace.init(root) as ws:
        for take, seq, frames in (("CALIB", "calibration", (0, 288)), ("DEMO", long_sequence or "handshake", (0, 120))):
            ws.add_take(take)
            ws.add_sequence(take, seq, *frames)
            for stage in ("scene", "devices", "capture"):
                ws.run_stage(stage, _write("a"), take=take, sequence=seq, params={})
        for stage in ("sync", "fuse", "fit", "contacts"):
            ws.run_stage(stage, _write("a"), take="DEMO", params={})
        try:
            ws.run_stage("render", _boom, take="DEMO", params={})
        except RuntimeError:
            pass
        ws.run_stage("sync", _write("a"), take="CALIB", params={})
        ws.conn.execute("UPDATE stage_runs SET status = 'running', pid = ? WHERE stage = 'sync' AND take_id = "
                        "(SELECT id FROM takes WHERE name = 'CALIB')", (os.getpid(),))  # alive: this process
    return root


def _cell(lines: list[str], row_start: str, stage: str) -> str:
    """The mark in the status grid under ``stage`` on the line that starts with ``row_start``."""
    header = next(line for line in lines if " ".join(STAGE_NAMES) in line)
    col = re.search(rf"\b{stage}\b", header).start() + (len(stage) - 1) // 2
    row = next(line for line in lines if line.startswith(row_start))
    return row[col] if col < len(row) else " "


def test_status_fits_80_columns_without_table_drawing(tmp_path):
    ws = _status_workspace(tmp_path / "ws")
    r = run("status", ws, env={"COLUMNS": "80"})
    assert r.exit_code == 0, r.output
    lines = r.output.splitlines()
    assert "…" not in r.output and not BOX_DRAWING & set(r.output) and "\x1b[" not in r.output
    assert max(len(line) for line in lines) <= 80, r.output
    assert lines[0] == f"workspace {ws}"
    # per take its take-level stages, per sequence (indented) its sequence-level ones
    assert [_cell(lines, "DEMO ", s) for s in STAGE_NAMES] == [" ", " ", " ", "✓", "✓", "✓", "✓", "✗", "·"]
    assert [_cell(lines, "  handshake", s) for s in STAGE_NAMES] == ["✓", "✓", "✓", " ", " ", " ", " ", " ", " "]
    assert _cell(lines, "CALIB ", "sync") == "▶" and _cell(lines, "CALIB ", "fit") == "·"
    assert "0-120" in next(line for line in lines if line.startswith("  handshake"))
    assert "✓ done  ~ stale  ✗ failed  ▶ running  ! interrupted  · not run" in r.output
    # what needs a look, with the error's first line (its traceback only with --long and --json)
    assert "DEMO render: failed: RuntimeError: renderer ran out of memory" in lines and "CALIB sync: running" in lines
    assert "_boom" not in r.output


def test_status_long_json_and_narrow_names(tmp_path):
    ws = _status_workspace(tmp_path / "ws")
    r = run("status", ws, "--long", env={"COLUMNS": "80"})
    assert r.exit_code == 0 and "…" not in r.output
    assert max(len(x) for x in r.output.splitlines() if not x.startswith("      ")) <= 80  # but the errors
    with Workspace.open(ws, readonly=True) as w:
        fit_hash = w.stage_record("fit", "DEMO")["params_hash"][:8]
    assert re.search(rf"^  fit +done +{fit_hash}  \d{{4}}-\d\d-\d\d \d\d:\d\d:\d\d  1 artifact$", r.output, re.MULTILINE), r.output
    assert "DEMO/handshake  frames 0-120" in r.output and "CALIB\n  sync      running  " in r.output
    assert "\n      RuntimeError: renderer ran out of memory\n" in r.output and "in _boom" in r.output
    # --json keeps its shape: every run's state, hash, end time, error and artifact count
    doc = json.loads(run("status", ws, "--json").output)
    assert set(doc) == {"rows", "problems", "quality"} and [(x["take"], x["sequence"]) for x in doc["rows"]] == [
        ("CALIB", None), ("CALIB", "calibration"), ("DEMO", None), ("DEMO", "handshake")]
    render = doc["rows"][2]["stages"]["render"]
    assert set(render) == {"state", "hash", "ended_at", "error", "artifacts"} and render["state"] == "failed"
    # a sequence name too long for the grid: names go on their own line, no line passes 80 columns
    ws2 = _status_workspace(tmp_path / "ws2", long_sequence="handshake_then_a_long_hug_then_a_pat_on_the_back")
    r = run("status", ws2, env={"COLUMNS": "80"})
    lines = r.output.splitlines()
    assert max(len(x) for x in lines) <= 80 and "…" not in r.output, r.output
    i = lines.index("  handshake_then_a_long_hug_then_a_pat_on_the_back  0-120")
    assert set(lines[i + 1].split()) == {"✓"}


def test_status_piped_is_plain_text(tmp_path):
    ws = _status_workspace(tmp_path / "ws")
    env = {k: v for k, v in os.environ.items() if k != "COLUMNS"}
    for encoding, done, failed in (("utf-8", "✓", "✗"), ("ascii", "+", "x")):
        proc = subprocess.run([sys.executable, "-m", "dualhuman_builder", "status", str(ws)], capture_output=True,
                              timeout=120, env={**env, "PYTHONIOENCODING": encoding})  # fmt: skip
        out = proc.stdout.decode(encoding)
        assert proc.returncode == 0 and proc.stderr == b"", proc.stderr
        assert "\x1b[" not in out and not BOX_DRAWING & set(out) and "…" not in out
        lines = out.splitlines()
        assert max(len(x) for x in lines) <= 80
        assert _cell(lines, "DEMO ", "fit") == done and _cell(lines, "DEMO ", "render") == failed


# ------------------------------------------------------------------------------------------ warp
def test_warp_starts_without_the_cuda_driver_warning_but_keeps_other_lines():
    from dualhuman_builder.warp_runtime import cuda_driver_problem

    if cuda_driver_problem() is not None:  # what the toolkit hides: warp's own start prints it here
        bare = subprocess.run([sys.executable, "-c", "import warp; warp.init()"], capture_output=True, text=True,
                              timeout=300)  # fmt: skip
        assert CUDA_WARNING in bare.stderr, bare.stderr
    code = ("import os\n"
            "from dualhuman_builder.warp_runtime import init_warp, stderr_without\n"
            "init_warp()\n"
            "import anny.skinning.warp_skinning  # anny starts warp again as it is imported\n"
            "with stderr_without('NVIDIA CUDA driver'):\n"
            "    os.write(2, b'Warp CUDA warning: Could not find or load the NVIDIA CUDA driver.\\n"
            "Warp CUDA error: a real one\\n')\n"
            "    print('from Python', file=__import__('sys').stderr)\n")  # fmt: skip
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == "Warp CUDA error: a real one\nfrom Python\n"
    # a command that starts warp
    proc = subprocess.run([sys.executable, str(REPO / "cli.py"), "body", "warm", "--check"], capture_output=True,
                          text=True, timeout=300)  # fmt: skip
    assert "warp kernel cache is" in proc.stdout and proc.stderr == "", proc.stderr


CONTACTS_ONE_FRAME = """
import numpy as np
from dualhuman_builder.body.model import get_body_model
from dualhuman_builder.contacts.compute import contacts_from_vertices
from dualhuman_builder.contacts.topology import default_topology
rest = get_body_model().rest().vertices[0].detach().cpu().numpy()
r = contacts_from_vertices(rest[None], rest[None] + np.array([0.3, 0, 0]), default_topology(), workers=1)
assert r.labels.any()
"""


@pytest.mark.slow
def test_body_warm_builds_the_kernel_cache_that_the_stages_then_load(tmp_path):
    from dualhuman_builder.kernel_cache import (
        ANNY_WARP_MODULE,
        RECORD_NAME,
        kernel_cache_dir,
        toolkit_warp_modules,
    )

    mine = kernel_cache_dir()  # this machine's (scripts/setup.sh built it): a copy compiles little or nothing
    cache = tmp_path / "warp" / mine.name
    shutil.copytree(mine, cache)
    (cache / RECORD_NAME).unlink(missing_ok=True)
    env = {**os.environ, "WARP_CACHE_PATH": str(cache.parent)}

    def warm(*args):
        return subprocess.run([sys.executable, "-m", "dualhuman_builder", "body", "warm", *args], capture_output=True,
                              text=True, env=env, timeout=900)  # fmt: skip

    r = warm("--check")
    assert r.returncode == 1 and "anny cache is built" in r.stdout and "warp kernel cache is not built" in r.stdout
    r = warm()
    assert r.returncode == 0 and r.stderr == "", r.stderr  # nothing left to compile on first use, no warning
    assert "warp kernel cache built in " in r.stdout and str(cache) in r.stdout
    record = json.loads((cache / RECORD_NAME).read_text())
    assert set(record["modules"]) == {ANNY_WARP_MODULE, *toolkit_warp_modules()} and record["missing"] == []
    assert all((cache / d).is_dir() for dirs in record["modules"].values() for d in dirs)
    r = warm("--check")
    assert r.returncode == 0 and "warp kernel cache is built" in r.stdout, r.stdout
    # a fresh process running the contacts stage's queries finds every kernel in the cache
    before = sorted(p.name for p in cache.iterdir())
    proc = subprocess.run([sys.executable, "-c", CONTACTS_ONE_FRAME], capture_output=True, text=True, env=env,
                          timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in cache.iterdir()) == before
    # a module lost from the cache is noticed
    shutil.rmtree(cache / record["modules"]["dualhuman_builder.geometry.narrow"][0])
    r = warm("--check")
    assert r.returncode == 1 and "1 module(s) gone" in r.stdout


def test_the_scene_type_choices_are_the_generators():
    from dualhuman_builder.cli.sim import SCENE_TYPES
    from dualhuman_builder.sim.scenes import ALL_TYPES

    assert tuple(SCENE_TYPES) == tuple(ALL_TYPES)


def test_fit_passes_the_solver_and_its_step_to_the_fit(tmp_path, monkeypatch):
    """``fit --solver take --take-step runs`` reaches :class:`FitConfig` as both fields (the stage itself
    is tested in tests/fit); the step defaults to ``shared``."""
    from dualhuman_builder.fit import stage

    seen = []

    class Done:
        skipped, artifacts = True, {}

    monkeypatch.setattr(stage, "run_fit", lambda ws, take, cfg, **kw: seen.append(cfg) or Done())
    monkeypatch.setattr(cli.stages, "_made_stale", lambda res: None)
    ws = tmp_path / "ws"
    run("init", ws)
    run("fit", ws, "--take", "T", "--solver", "take", "--take-step", "runs")
    run("fit", ws, "--take", "T", "--solver", "take")
    assert [(c.solver, c.take_step) for c in seen] == [("take", "runs"), ("take", "shared")]

"""`dualhuman run` with the local executor: every pending stage in order, failures retried then
recorded with the rest going on, a worker killed mid-stage retried, a killed driver resumed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import pytest
from batch_helpers import (
    FPS,
    TAKES,
    artifact_hashes,
    assert_consistent,
    two_takes,  # noqa: F401  (a fixture)
    wait_for_staging,
    workspace,  # noqa: F401  (a fixture)
)
from click.testing import CliRunner

from dualhuman_builder.batch import RunOptions, make_plan, run_workspace
from dualhuman_builder.workspace import Workspace


def test_the_plan_holds_the_pending_stages_in_order_and_skips_what_is_done(workspace):
    with Workspace.open(workspace, readonly=True) as ws:
        plan = make_plan(ws, RunOptions(until="fit"))
    assert [t.key for t in plan.tasks] == [(t, s) for t in TAKES for s in ("sync", "fuse", "fit")]
    assert [t.after for t in plan.tasks if t.take == "T1"] == [[], [("T1", "sync")], [("T1", "fuse")]]
    assert plan.done == {(t, s) for t in TAKES for s in ("scene", "devices", "capture")}


def test_each_take_syncs_with_its_own_calibration_take_and_an_unknown_one_is_a_clear_error(ws):
    from dualhuman_builder.batch.plan import stage_call, take_mounts_from
    from dualhuman_builder.errors import DualhumanError
    from dualhuman_builder.resources import RIGS_DIR

    ws.add_rig(RIGS_DIR / "sim.toml")
    ws.add_take("C1", rig="sim", actors=[], meta={"calibration": True})
    ws.add_take("C2", rig="sim", actors=[])  # a calibration take only because a take names it
    ws.add_take("A", rig="sim", actors=[], meta={"mounts_from": "C1"})
    ws.add_take("B", rig="sim", actors=[], meta={"mounts_from": "C2"})
    plan = make_plan(ws, RunOptions(takes=("B",), until="fit"))
    assert [t.key for t in plan.tasks] == [("C2", "sync"), ("B", "sync"), ("B", "fuse"), ("B", "fit")]
    assert plan.tasks[1].after == [("C2", "sync")] and ("C2", "fit") in plan.skipped
    assert [take_mounts_from(ws, t, RunOptions()) for t in ("A", "B", "C1")] == ["C1", "C2", None]
    assert take_mounts_from(ws, "B", RunOptions(mounts_from="C1")) == "C1"  # the command's option wins
    assert stage_call("sync", RunOptions()) is not None
    ws.add_take("X", rig="sim", actors=[], meta={"mounts_from": "GONE"})
    with pytest.raises(DualhumanError, match="no calibration take 'GONE'.*take 'X' names it"):
        make_plan(ws, RunOptions(takes=("X",)))


def test_a_local_run_does_every_pending_stage_and_a_second_run_nothing(workspace):
    events = []
    summary = run_workspace(workspace, RunOptions(until="fuse", fps=FPS), on_event=lambda *e: events.append(e[:3]))
    assert {k: o.state for k, o in summary.outcomes.items() if o.state != "done"} == {
        (t, s): "ran" for t in TAKES for s in ("sync", "fuse")}  # fmt: skip
    starts = [(t, s) for kind, t, s in events if kind == "start"]
    for t in TAKES:  # a take's stages run in order
        assert starts.index((t, "sync")) < starts.index((t, "fuse"))
    assert_consistent(workspace)
    again = run_workspace(workspace, RunOptions(until="fuse", fps=FPS))
    assert {o.state for o in again.outcomes.values()} == {"done"}


def test_a_failing_stage_is_tried_again_then_recorded_failed_and_the_other_takes_go_on(workspace):
    from dualhuman_builder.cli import main
    from dualhuman_builder.cli import run as _  # noqa: F401  (registers `run`)

    (next((workspace / "artifacts" / "T1").rglob("take.mcap"))).unlink()  # its recording is gone
    r = CliRunner().invoke(main, ["run", str(workspace), "--until", "fuse", "--fps", str(FPS)])
    assert r.exit_code == 1, r.output
    assert "T1 sync: failed, trying again" in r.output and "T1 fuse: skipped: sync failed" in r.output
    assert "failed T1 sync" in r.output and "ran 2, done before 6, failed 1, skipped 1" in r.output
    with Workspace.open(workspace, readonly=True) as ws:
        rec = ws.stage_record("sync", "T1")
        assert rec["status"] == "failed" and "take.mcap" in rec["error"]
        assert ws.stage_record("fuse", "T1") is None
        assert all(ws.stage_record(s, "T2")["status"] == "done" for s in ("sync", "fuse"))


def test_after_stage_can_stop_a_take(workspace):
    summary = run_workspace(workspace, RunOptions(until="fuse", fps=FPS),
                            after_stage=lambda ws, take, stage: "tracker loss over the gate" if take == "T1" else None)  # fmt: skip
    assert summary.outcomes[("T1", "sync")].state == "ran"
    assert (summary.outcomes[("T1", "fuse")].state, summary.outcomes[("T1", "fuse")].error) == (
        "skipped", "tracker loss over the gate")  # fmt: skip
    assert summary.outcomes[("T2", "fuse")].state == "ran"


@pytest.mark.slow
def test_a_worker_killed_mid_stage_is_retried_and_nothing_partial_counts(workspace):
    result = {}
    run = threading.Thread(target=lambda: result.update(s=run_workspace(workspace, RunOptions(takes=("T1",), until="fit", fps=FPS))))
    run.start()
    pid = wait_for_staging(workspace, "T1", "fit")
    with Workspace.open(workspace, readonly=True) as ws:
        rec = ws.stage_record("fit", "T1")
        assert rec["status"] == "running" and rec["pid"] == pid
    os.kill(pid, signal.SIGKILL)
    run.join(300)
    out = result["s"].outcomes[("T1", "fit")]
    assert (out.state, out.tries) == ("ran", 2)
    assert_consistent(workspace)
    with Workspace.open(workspace, readonly=True) as ws:
        assert ws.stage_record("fit", "T1")["status"] == "done"


@pytest.mark.slow
def test_a_killed_driver_leaves_nothing_done_that_is_not_and_the_next_run_resumes(workspace):
    cmd = [sys.executable, "-c", "from dualhuman_builder.cli import main, run; main()", "run", str(workspace), "--take", "T1", "--until", "fit", "--fps", str(FPS)]
    driver = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    worker = wait_for_staging(workspace, "T1", "fit")
    driver.kill()
    driver.wait()
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and os.path.exists(f"/proc/{worker}"):  # the worker ends with its driver
        time.sleep(0.05)
    assert not os.path.exists(f"/proc/{worker}")
    with Workspace.open(workspace, readonly=True) as ws:
        assert ws.stage_record("fit", "T1")["status"] != "done"
        assert ws.stage_record("fuse", "T1")["status"] == "done"
    summary = run_workspace(workspace, RunOptions(takes=("T1",), until="fit", fps=FPS))
    assert summary.outcomes[("T1", "fit")].state == "ran" and summary.outcomes[("T1", "fuse")].state == "done"
    assert_consistent(workspace)
    assert artifact_hashes(workspace)[("T1", "fit")]

"""The Ray executor: a local Ray cluster (``ray.init(num_cpus=2)``) gives the local executor's
artifacts; a Ray worker killed mid-stage is retried; an address that does not answer fails fast."""

from __future__ import annotations

import os
import shutil
import signal
import socket
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

from dualhuman_builder.batch import RunOptions, run_workspace
from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.workspace import Workspace

ray = pytest.importorskip("ray")


@pytest.fixture(scope="module")
def cluster():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


def test_an_address_that_does_not_answer_is_a_clear_error_within_seconds(ws):
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    t0 = time.monotonic()
    with pytest.raises(DualhumanError, match=f"no Ray cluster answers at 127.0.0.1:{port}") as e:
        from dualhuman_builder.batch.executors import RayExecutor

        RayExecutor(ws.root, f"127.0.0.1:{port}", retries=1)
    assert time.monotonic() - t0 < 10 and "ray start --head" in e.value.fix


def test_a_ray_address_that_does_not_answer_fails_the_command_with_exit_2(two_takes, tmp_path):
    from click.testing import CliRunner

    from dualhuman_builder.cli import main
    from dualhuman_builder.cli import run as _  # noqa: F401  (registers `run`)

    ws = tmp_path / "ws"
    shutil.copytree(two_takes, ws)
    r = CliRunner().invoke(main, ["run", str(ws), "--executor", "ray", "--address", "192.0.2.1:6379"])  # TEST-NET: no answer
    assert r.exit_code == 2 and "no Ray cluster answers at 192.0.2.1:6379" in r.output, r.output


def test_ray_and_the_local_executor_give_identical_artifacts_and_ray_writes_no_catalog_from_workers(cluster, two_takes, tmp_path):
    local, remote = tmp_path / "local", tmp_path / "ray"
    shutil.copytree(two_takes, local)
    shutil.copytree(two_takes, remote)
    a = run_workspace(local, RunOptions(until="fuse", fps=FPS))
    b = run_workspace(remote, RunOptions(until="fuse", fps=FPS), executor="ray")
    assert a.failed == b.failed == []
    assert {k: o.state for k, o in b.outcomes.items()} == {k: o.state for k, o in a.outcomes.items()}
    ha, hb = artifact_hashes(local), artifact_hashes(remote)
    assert ha == hb and set(ha) == {(t, s) for t in TAKES for s in ("sync", "fuse")}
    assert_consistent(remote)
    with Workspace.open(remote, readonly=True) as ws:  # the driver recorded what the shadow runs did
        assert all(ws.stage_record("fuse", t)["status"] == "done" for t in TAKES)


@pytest.mark.slow
def test_a_ray_worker_killed_mid_stage_is_retried(cluster, two_takes, tmp_path):
    ws = tmp_path / "ws"
    shutil.copytree(two_takes, ws)
    result = {}
    run = threading.Thread(target=lambda: result.update(
        s=run_workspace(ws, RunOptions(takes=("T1",), until="fit", fps=FPS), executor="ray")))  # fmt: skip
    run.start()
    pid = wait_for_staging(ws, "T1", "fit")
    with Workspace.open(ws, readonly=True) as w:  # the catalog does not even know it runs
        assert w.stage_record("fit", "T1") is None
    os.kill(pid, signal.SIGKILL)
    run.join(300)
    assert result["s"].outcomes[("T1", "fit")].state == "ran"
    assert_consistent(ws)
    with Workspace.open(ws, readonly=True) as w:
        assert w.stage_record("fit", "T1")["status"] == "done"

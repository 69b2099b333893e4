"""One `dualhuman run` per workspace: a second refuses with the holder's pid; a killed holder
frees the workspace at once."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dualhuman_builder.batch import RunOptions, run_workspace, workspace_lock
from dualhuman_builder.batch.run import LOCK_NAME, lock_holder
from dualhuman_builder.errors import WorkspaceError

HOLD = """
import sys, time
from dualhuman_builder.batch import workspace_lock
with workspace_lock(sys.argv[1]):
    print("locked", flush=True)
    time.sleep(600)
"""


def test_a_second_run_refuses_while_another_holds_the_workspace_and_a_killed_one_frees_it(ws):
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(ws.root)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        t0 = time.monotonic()
        with pytest.raises(WorkspaceError, match=f"another `dualhuman run` is running on this workspace \\(pid {holder.pid}"):
            run_workspace(ws.root, RunOptions())
        assert time.monotonic() - t0 < 5  # it refuses, it does not wait
    finally:
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait()
    summary = run_workspace(ws.root, RunOptions())  # the system dropped the killed holder's lock
    assert summary.outcomes == {} and not summary.failed


def test_the_lock_is_held_per_open_not_per_process(ws):
    with workspace_lock(ws.root), pytest.raises(WorkspaceError, match="another `dualhuman run`"):
        run_workspace(ws.root, RunOptions())
    assert run_workspace(ws.root, RunOptions()).outcomes == {}


@given(st.binary(max_size=300))
def test_whatever_the_lock_file_holds_reading_it_gives_a_dict(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("lock") / LOCK_NAME
    path.write_bytes(data)
    assert isinstance(lock_holder(path), dict)

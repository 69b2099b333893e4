"""Helpers of the batch tests: artifact hashes from the catalog, the pid of a running stage, the
workspace's consistency."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import pytest

TAKES = ("T1", "T2")
FPS = 7.5


def artifact_hashes(root: Path, stages=("sync", "fuse", "fit")) -> dict:
    """``{(take, stage): {artifact: sha256}}`` from the catalog."""
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(root, readonly=True) as ws:
        return {(t, s): {n: a["sha256"] for n, a in r["artifacts"].items()}
                for t in ws.takes() for s in stages if (r := ws.stage_record(s, t)) is not None}  # fmt: skip


def wait_for_staging(root: Path, take: str, stage: str, timeout: float = 120.0) -> int:
    """The pid of the process running ``stage`` of ``take`` (its staging folder is named after it)."""
    parent = root / "artifacts" / take / "_take"
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for p in parent.glob(f".{stage}.staging-*") if parent.is_dir() else []:
            return int(p.name.split("-")[1])
        time.sleep(0.02)
    raise AssertionError(f"{stage} of {take} never started")


def assert_consistent(root: Path) -> None:
    """Every artifact matches the catalog, and no staging or replaced folder is left."""
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(root, readonly=True) as ws:
        assert ws.verify() == []
    assert not [p for p in (root / "artifacts").rglob(".*") if ".staging-" in p.name or ".old-" in p.name]


@pytest.fixture(scope="session")
def two_takes(tmp_path_factory, body_model) -> Path:
    """Two tiny simulated takes (a 3.2 s high five at 7.5 fps, recorded at 8x real time), made once per test
    session (imported by the test modules: a ``conftest.py`` here would shadow ``tests/conftest.py``)."""
    from dualhuman_builder.resources import RIGS_DIR
    from dualhuman_builder.sim.stage import DEFAULT_ACTORS, ensure_actors, simulate_take
    from dualhuman_builder.workspace import Workspace

    root = tmp_path_factory.mktemp("batch") / "ws"
    with Workspace.init(root) as ws:
        ws.add_rig(RIGS_DIR / "sim.toml")
        shapes = ensure_actors(ws, DEFAULT_ACTORS, body_model, log=lambda s: None)
        for seed, take in enumerate(TAKES):
            simulate_take(ws, take, "high_five", {"type": "high_five", "seed": seed, "fps": FPS}, DEFAULT_ACTORS, shapes,
                          speed=8.0, model=body_model, log=lambda s: None)  # fmt: skip
    return root


@pytest.fixture
def workspace(two_takes, tmp_path) -> Path:
    """A fresh copy of the two-take workspace."""
    dst = tmp_path / "ws"
    shutil.copytree(two_takes, dst)
    return dst

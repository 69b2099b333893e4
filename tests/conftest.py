"""Shared fixtures: the body model is built once per test run (anny's cache makes that < 1 s)."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, settings

# Property-based tests (decoders, file readers): a bounded, reproducible example count in the suite;
# the long fuzz run is benchmarks/fuzz.py. No deadline: this machine's speed drifts.
settings.register_profile("suite", max_examples=200, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
settings.load_profile("suite")


@pytest.fixture(scope="session")
def body_model():
    from dualhuman_builder.body.model import get_body_model

    return get_body_model()


@pytest.fixture
def ws(tmp_path):
    from dualhuman_builder.workspace import Workspace

    with Workspace.init(tmp_path / "ws") as w:
        yield w


def snapshot(folder):
    """{relative path: bytes} of every file under ``folder``, to prove a command changed nothing."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}

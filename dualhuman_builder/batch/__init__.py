"""Batch runs: every pending stage of every take of a workspace, on a local process pool or a Ray
cluster (``dualhuman run``; guide: docs/guides/running-at-scale.md).

    from dualhuman_builder.batch import RunOptions, run_workspace
    summary = run_workspace("WS", RunOptions(until="fit", retries=1), executor="local")
"""

from dualhuman_builder.batch.plan import RunOptions, make_plan
from dualhuman_builder.batch.run import (
    Outcome,
    RunSummary,
    after_stage,
    run_workspace,
    workspace_lock,
)

__all__ = ["Outcome", "RunOptions", "RunSummary", "after_stage", "make_plan", "run_workspace", "workspace_lock"]

"""Workspaces: the SQLite catalog of actors, rigs, takes and sequences, and the stage runner."""

from dualhuman_builder.workspace.catalog import CATALOG_NAME, CATALOG_VERSION
from dualhuman_builder.workspace.runner import Stage, StageOutput, StageResult
from dualhuman_builder.workspace.workspace import Actor, SequenceInfo, Take, Workspace

__all__ = ["CATALOG_NAME", "CATALOG_VERSION", "Actor", "SequenceInfo", "Stage", "StageOutput", "StageResult",
           "Take", "Workspace"]  # fmt: skip

"""Workspaces: the SQLite catalog of actors, rigs, takes and sequences, and the stage runner."""

from dualhuman_builder.workspace.catalog import CATALOG_NAME, CATALOG_VERSION
from dualhuman_builder.workspace.stages import StageOutput, StageResult
from dualhuman_builder.workspace.workspace import STAGES, Actor, SequenceInfo, Take, Workspace

__all__ = ["CATALOG_NAME", "CATALOG_VERSION", "STAGES", "Actor", "SequenceInfo", "StageOutput", "StageResult",
           "Take", "Workspace"]  # fmt: skip

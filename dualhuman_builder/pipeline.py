"""The stage registry: exactly the workspace stages that run, in the order data flows through them.

Each stage declares itself (:class:`~dualhuman_builder.workspace.runner.Stage`: name, per take or
per sequence, artifacts, the stages it reads, the command that runs it) in its own package; this
module only lists them. ``dualhuman status`` shows its columns in this order.

============  ========  =================================================================
stage         per       runner
============  ========  =================================================================
``scene``     sequence  :func:`dualhuman_builder.sim.stage.run_scene`
``devices``   sequence  :func:`dualhuman_builder.sim.stage.run_devices`
``capture``   sequence  :func:`dualhuman_builder.capture.stage.run_capture`
``sync``      take      :func:`dualhuman_builder.sync.stage.run_sync`
``fuse``      take      :func:`dualhuman_builder.fit.stage.run_fuse`
``fit``       take      :func:`dualhuman_builder.fit.stage.run_fit`
``contacts``  take      :func:`dualhuman_builder.contacts.stage.run_contacts`
``render``    take      :func:`dualhuman_builder.render.stage.run_render`
``sheet``     take      :func:`dualhuman_builder.render.sheet.run_sheet`
============  ========  =================================================================

The dataset export (``dualhuman export``) is not a stage of a take: it gathers the takes whose
``fit`` is done into a folder outside the workspace's artifacts.
"""

from __future__ import annotations

from dualhuman_builder.capture.stage import CAPTURE
from dualhuman_builder.contacts.stage import CONTACTS
from dualhuman_builder.fit.stage import FIT, FUSE
from dualhuman_builder.render.sheet import SHEET
from dualhuman_builder.render.stage import RENDER
from dualhuman_builder.sim.stage import DEVICES, SCENE
from dualhuman_builder.sync.stage import SYNC
from dualhuman_builder.workspace.runner import Stage

STAGES: tuple[Stage, ...] = (SCENE, DEVICES, CAPTURE, SYNC, FUSE, FIT, CONTACTS, RENDER, SHEET)
STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES)


def stage(name: str) -> Stage:
    """The declaration of stage ``name``; ValueError naming the stages when there is none."""
    for s in STAGES:
        if s.name == name:
            return s
    raise ValueError(f"no stage named {name!r}; the stages are {', '.join(STAGE_NAMES)}")

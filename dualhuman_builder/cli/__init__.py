"""`dualhuman`: the command line. Wiring only: every command calls a library function that can be
used from Python as well; heavy imports happen inside commands so that `--help` is instant.

One module per command group, in pipeline order: :mod:`.workspace` (init, status, actor, rig),
:mod:`.body`, :mod:`.sim` (scene, sim), :mod:`.capture` (capture, log, replay, import),
:mod:`.stages` (sync, fuse, fit, contacts, render, sheet), :mod:`.export` (annotate, export),
:mod:`.quality` (gates, review), :mod:`.run` (run), :mod:`.synth` (synth), :mod:`.models` (train,
evaluate, refine, models), :mod:`.estimate` (estimate), :mod:`.tools` (doctor, demo); :mod:`.console` formats tables and errors.
"""

from dualhuman_builder.cli import (  # noqa: F401  (registers the commands)
    body, capture, estimate, export, models, quality, run, sim, stages, synth, tools, workspace)
from dualhuman_builder.cli.app import main

__all__ = ["main"]

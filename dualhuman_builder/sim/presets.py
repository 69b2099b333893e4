"""Device error presets of a simulated take: which errors the suits, trackers and tracker clock get.

* ``ideal``: the simulators' defaults (:class:`~dualhuman_builder.sim.suit.SuitErrorModel`,
  :class:`~dualhuman_builder.sim.trackers.TrackerErrorModel`,
  :data:`~dualhuman_builder.sim.trackers.DEFAULT_TRACKER_CLOCK`): the same streams for the same
  seed, take after take;
* ``realistic``: every error parameter drawn once per take within the ranges documented (with a
  source per number) in :mod:`dualhuman_builder.sim.suit` and :mod:`dualhuman_builder.sim.trackers`
  (:meth:`SuitErrorModel.realistic`, :meth:`TrackerErrorModel.realistic`,
  :func:`~dualhuman_builder.sim.trackers.realistic_tracker_clock`), so that no estimator can know
  the generator's constants.

:func:`draw_device_errors` returns the models and ``drawn``, a JSON-able record of every drawn
parameter. It is stored with the take for evaluation only; sync and fit never read it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.sim.kinematics import DeviceClock
from dualhuman_builder.sim.suit import SuitErrorModel

#: The device error presets a simulated take can be made with.
PRESETS = ("ideal", "realistic")


class PresetError(DualhumanError, ValueError):
    """An unknown device error preset."""


def check_preset(preset: str) -> str:
    """``preset`` if it is one of :data:`PRESETS`, else :class:`PresetError`."""
    if preset not in PRESETS:
        raise PresetError(f"unknown device error preset {preset!r}", fix=f"choose one of {', '.join(PRESETS)}")
    return preset


@dataclass(frozen=True)
class DeviceErrors:
    """The error models of one take's devices: ``suit`` (both suits; each suit's realisation still
    differs by its character), ``trackers`` (every tracker), ``tracker_clock`` (the lighthouse
    system's clock against the suits'); ``preset`` their preset; ``drawn`` a JSON-able dict of
    every parameter (for evaluation; never read by sync or fit)."""

    suit: SuitErrorModel
    trackers: object  # TrackerErrorModel
    tracker_clock: DeviceClock
    preset: str
    drawn: dict


def _jsonable(value):
    if dataclasses.is_dataclass(value):
        return {f.name: _jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (tuple, list, np.ndarray)):
        return [_jsonable(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else str(float(value))
    return value if value is None or isinstance(value, str) else str(value)


def draw_device_errors(preset: str, seed: int) -> DeviceErrors:
    """The device errors of a take with device seed ``seed`` under ``preset`` (:data:`PRESETS`).
    ``ideal`` ignores the seed (the realisations still follow it, in the simulators); ``realistic``
    draws the suit's, the trackers' and the tracker clock's parameters from three independent
    streams of ``seed``, so the same seed always draws the same parameters."""
    from dualhuman_builder.sim import trackers as trk

    check_preset(preset)
    if preset == "ideal":
        suit, trackers, clock = SuitErrorModel(), trk.TrackerErrorModel(), trk.DEFAULT_TRACKER_CLOCK
    else:
        streams = np.random.SeedSequence([int(seed), 0x9E5E7]).spawn(3)
        r_suit, r_trk, r_clock = (np.random.default_rng(s) for s in streams)
        suit = SuitErrorModel.realistic(r_suit)
        trackers = trk.TrackerErrorModel.realistic(r_trk)
        clock = trk.realistic_tracker_clock(r_clock)
    drawn = {"preset": preset, "seed": int(seed), "suit": _jsonable(suit), "trackers": _jsonable(trackers),
             "tracker_clock": _jsonable(clock)}  # fmt: skip
    return DeviceErrors(suit=suit, trackers=trackers, tracker_clock=clock, preset=preset, drawn=drawn)

"""The priors sync places on a suit and its trackers, each from a published figure or from a reading of
one, never from the simulator's constants (the simulated studio draws its own per take,
:mod:`dualhuman_builder.sim.presets`).

The figures and their sources are collected in ``docs/reference/capture-errors.md`` of the shared
reference and in ``docs/design/sync.md``; each constant names its own here.
"""

from __future__ import annotations

import math

#: Random-walk std per horizontal axis of the suit's root position after one minute, m. No public
#: figure states MVN's in-place drift; "several cm per minute" is the common reading of contact-aided
#: inertial dead reckoning (Roetenberg, Luinge & Slycke 2009; Schepers, Giuberti & Bellusci 2018).
#: The prior takes the top of that reading (10 cm), so that it never holds a suit that drifts more
#: than a typical one against the trackers' evidence.
ROOT_DRIFT_M_PER_SQRT_MIN = 0.10
#: The same per second: the form :func:`~dualhuman_builder.sync.mount.calibrate_mounts` takes.
ROOT_DRIFT_M_PER_SQRT_S = ROOT_DRIFT_M_PER_SQRT_MIN / math.sqrt(60.0)

#: Std per axis of each suit segment's constant sensor-to-segment misalignment, deg: the typical
#: error of an N-pose/T-pose calibration (Miezal, Taetz & Bleser, Sensors 16(7):1132, 2016).
MISALIGNMENT_DEG = 2.0

#: Std per axis of a tracker's mount offset around its rig site, m: a strap placed by hand on a
#: marked site lands within a couple of centimetres of it (assumption of ours, stated in
#: ``docs/decisions/0011-heading-from-tracker-constellation.md``).
SITE_M = 0.02

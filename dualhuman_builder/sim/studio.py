"""The simulated studio: every device of ``rigs/sim.toml`` driven by one ground-truth scene.

Per actor ``i`` of the scene: an MVN suit streaming as character ``i`` (23 segments, 240 Hz),
VIVE-style trackers at the rig's sites (serial -> MVN segment, 250 Hz); plus one MTi-style IMU on
Xbus strapped to actor 0's pelvis (400 Hz) and one on CAN strapped to actor 1's pelvis (100 Hz) —
the load of the capture benchmark. Error models come from the take's preset
(:mod:`.presets`: ``ideal``, the simulators' defaults, or ``realistic``, drawn per take from the
device seed); every realisation is seeded from the studio seed, so the same scene, seed and
preset give bit-identical streams. Each actor's trackers are occluded by the partner's body.

Clocks (scene time ``t`` in seconds, see :class:`~dualhuman_builder.sim.kinematics.DeviceClock`):
the suits are the reference (offset 0, no drift); trackers run 0.25 s ahead and drift +30 ppm
under ``ideal`` (``realistic`` draws their clock per take); the IMUs carry their own offsets. The host clock is the same for all (receive time), so
:meth:`SimStudio.samples` merges everything by ``host_time_ns``, as a live recorder sees it.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Union

from dualhuman_builder.capture.samples import ImuSample, SuitFrame, TrackerSample
from dualhuman_builder.sim.imu import ImuStream, simulate_imu
from dualhuman_builder.sim.kinematics import DeviceClock, KinematicSpline
from dualhuman_builder.sim.presets import DeviceErrors, draw_device_errors
from dualhuman_builder.sim.suit import SuitStream, simulate_suit
from dualhuman_builder.sim.trackers import TrackerStream, simulate_trackers

Sample = Union[SuitFrame, TrackerSample, ImuSample]

#: IMU clocks: own offsets (s) and drifts (ppm), as free-running MTi crystals.
XBUS_CLOCK = DeviceClock(offset_s=12.5, drift_ppm=-20.0, latency_s=0.001, jitter_s=0.0002)
CAN_CLOCK = DeviceClock(offset_s=3.75, drift_ppm=15.0, latency_s=0.0015, jitter_s=0.0003)


@dataclass(frozen=True)
class StudioConfig:
    """Rates (Hz) and where the two IMUs sit; ``trackers[i]``: serial -> MVN segment for actor
    ``i`` (None: the rig's)."""

    suit_hz: float = 240.0
    tracker_hz: float = 250.0
    xbus_hz: float = 400.0
    can_hz: float = 100.0
    xbus_site: tuple[int, str] = (0, "Pelvis")
    can_site: tuple[int, str] = (1, "Pelvis")
    trackers: tuple[dict, dict] | None = None


@dataclass
class SimStudio:
    """The streams of one simulated take: ``suits[i]`` and ``trackers[i]`` per actor, ``imus``
    by device name (``mti-xbus``, ``mti-can``)."""

    suits: list[SuitStream]
    trackers: list[TrackerStream]
    imus: dict[str, ImuStream]
    config: StudioConfig = field(default_factory=StudioConfig)
    #: The device errors the streams were made with (:func:`~.presets.draw_device_errors`).
    devices: DeviceErrors | None = None

    def streams(self) -> list:
        return [*self.suits, *self.trackers, *self.imus.values()]

    def samples(self) -> Iterator[Sample]:
        """Every sample of every device, merged in host receive-time order (stable)."""
        keyed = (((s.host_time_ns, n, s) for s in stream) for n, stream in enumerate(self.streams()))
        for _, _, s in heapq.merge(*keyed, key=lambda x: (x[0], x[1])):
            yield s

    def counts(self) -> dict[str, int]:
        out = {f"suit/{s.character}": len(s) for s in self.suits}
        for tr in self.trackers:
            out.update({f"vive/{serial}": int(tr.valid.shape[1]) for serial in tr.serials})
        out.update({f"imu/{k}": len(v) for k, v in self.imus.items()})
        return out


def rig_tracker_sites(rig_path: str | Path | None = None) -> tuple[dict, dict]:
    """Tracker serial -> segment of the two actors of ``rig_path`` (default ``rigs/sim.toml``)."""
    from dualhuman_builder.resources import RIGS_DIR
    from dualhuman_builder.rig import load_rig

    rig = load_rig(rig_path or RIGS_DIR / "sim.toml")
    by_char = {a.character: dict(a.trackers) for a in rig.actors}
    if 0 not in by_char or 1 not in by_char:
        raise ValueError(f"{rig.path}: the simulated studio needs actors with characters 0 and 1")
    return by_char[0], by_char[1]


def simulate_studio(sequence, seed: int = 0, config: StudioConfig = StudioConfig(), progress=None,
                    preset: str = "ideal", contacts=None) -> SimStudio:  # fmt: skip
    """Simulate every device on the two actors of ``sequence`` (an
    :class:`~dualhuman_builder.tracks.InteractionSequence`, e.g. ``scene.sequence``) with device
    seed ``seed`` and the device errors of ``preset`` (:data:`~.presets.PRESETS`; an unknown one
    raises :class:`~.presets.PresetError`). ``contacts``: optional per-actor ``(F, V)`` per-vertex
    contact labels or signed distances to the partner (``scene.distances``; see
    :func:`~.suit.segment_loads`), which make the suits' soft-tissue error larger on the segments
    in contact where the preset models it."""
    from dualhuman_builder.sim.groundtruth import segment_kinematics

    devices = draw_device_errors(preset, seed)
    sites = config.trackers or rig_tracker_sites()
    splines = [KinematicSpline(segment_kinematics(track)) for track in sequence.actors]
    loads = [None] * len(splines)
    if contacts is not None and devices.suit.soft_tissue_deg > 0 and devices.suit.soft_tissue_contact_gain > 0:
        from dualhuman_builder.sim.suit import segment_loads

        loads = [segment_loads(c) for c in contacts]
    suits, trackers = [], []
    for i, spline in enumerate(splines):
        if progress:
            progress(f"actor {i}: suit at {config.suit_hz:g} Hz, {len(sites[i])} trackers at {config.tracker_hz:g} Hz")
        suits.append(simulate_suit(spline, character=i, rate_hz=config.suit_hz, seed=seed, errors=devices.suit,
                                   contact=loads[i]))  # fmt: skip
        partner = splines[1 - i] if len(splines) == 2 else None
        trackers.append(simulate_trackers(spline, sites[i], rate_hz=config.tracker_hz, seed=seed + 1000 * (i + 1),
                                          errors=devices.trackers, clock=devices.tracker_clock, occluder=partner))  # fmt: skip
    imus = {}
    for name, (actor, segment), rate, clock in (("mti-xbus", config.xbus_site, config.xbus_hz, XBUS_CLOCK),
                                                ("mti-can", config.can_site, config.can_hz, CAN_CLOCK)):  # fmt: skip
        if progress:
            progress(f"{name}: on actor {actor}'s {segment} at {rate:g} Hz")
        imus[name] = simulate_imu(splines[actor], segment, rate_hz=rate, seed=seed + 7 + len(imus), clock=clock,
                                  device=name)  # fmt: skip
    return SimStudio(suits, trackers, imus, config, devices)

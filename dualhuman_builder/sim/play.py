"""Play a simulated studio onto real transports, all devices together in real time (or N x).

:func:`play_studio` starts one player per transport (:mod:`.devices`), each in its own thread,
all scheduled by the host receive times of their samples, so the devices keep the timing a
recorder would see from a live studio:

* MVN: both suits as characters 0 and 1 on one UDP address (type 02 + 25 datagrams, large poses
  split), default ``127.0.0.1:9763``;
* trackers: one bridge datagram per sample on one UDP address, default ``127.0.0.1:8051``;
* the Xbus MTi: MTData2 frames on a serial port — ``"pty"`` opens a pseudo-terminal whose slave
  path a host opens like a USB adapter (the simulated MTi answers configuration messages there;
  what nobody reads is dropped and counted in ``pty.dropped_bytes``), anything else is a pyserial
  URL or device path;
* the CAN MTi: MTi-600 frames on a python-can bus ``"INTERFACE:CHANNEL"`` (``virtual:NAME`` is
  in-process only; ``socketcan:vcan0`` reaches other processes).

Each transport can be left out (None). Faults (:class:`~.devices.Faults`) apply to every player,
each with its own seed derived from ``faults.seed``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Callable

from dualhuman_builder.sim.devices import (CanPlayer, Faults, Player, PlayReport, PtyMaster, SerialPlayer, UdpPlayer,
                                           mvn_packets, tracker_packets)  # fmt: skip
from dualhuman_builder.sim.studio import SimStudio


@dataclass
class StudioPlay:
    """The running players by transport name and, for ``xbus="pty"``, the slave path to open."""

    players: dict[str, Player] = field(default_factory=dict)
    pty_path: str | None = None
    pty: PtyMaster | None = None
    _close: list = field(default_factory=list)

    def join(self, timeout: float | None = None) -> dict[str, PlayReport]:
        return {name: p.join(timeout) for name, p in self.players.items()}

    def stop(self) -> None:
        for p in self.players.values():
            p.stop()

    def close(self) -> None:
        self.stop()
        for p in self.players.values():
            p.join()
            p.close()
        for c in self._close:
            c()
        self._close.clear()

    def __enter__(self) -> "StudioPlay":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _address(text: str, default_port: int) -> tuple[str, int]:
    host, _, port = text.rpartition(":") if ":" in text else (text, "", str(default_port))
    try:
        return host or "127.0.0.1", int(port)
    except ValueError:
        raise ValueError(f"{text!r} is not HOST:PORT") from None


def play_studio(studio: SimStudio, *, mvn: str | None = "127.0.0.1:9763", trackers: str | None = "127.0.0.1:8051",
                xbus: str | None = None, can_bus: str | None = None, speed: float = 1.0,
                faults: Faults | None = None, log: Callable[[str], None] | None = None) -> StudioPlay:  # fmt: skip
    """Start playing ``studio`` (see the module docstring); returns at once with the players
    running. ``speed`` N plays N times faster (``math.inf``: as fast as possible)."""
    import can
    import serial

    play = StudioPlay()

    def seeded(k: int) -> Faults | None:
        return None if faults is None else dataclasses.replace(faults, seed=faults.seed * 16 + k)

    try:
        if mvn:
            p = UdpPlayer(_address(mvn, 9763), speed=speed, faults=seeded(1))
            for suit in studio.suits:
                p.add(mvn_packets(suit, clock="host"))
            play.players["mvn"] = p
        if trackers:
            p = UdpPlayer(_address(trackers, 8051), speed=speed, faults=seeded(2))
            for tr in studio.trackers:
                p.add(tracker_packets(tr, clock="host"))
            play.players["trackers"] = p
        imu_x, imu_c = studio.imus.get("mti-xbus"), studio.imus.get("mti-can")
        if xbus and imu_x is not None:
            if xbus == "pty":
                port = PtyMaster(drop_when_full=True)  # nobody reading yet: bytes drop, as on a real line
                play.pty_path = port.slave_path
                play.pty = port
            else:
                port = serial.serial_for_url(xbus, baudrate=921600, timeout=0)
            play._close.append(port.close)
            play.players["xbus"] = SerialPlayer(port, speed=speed, faults=seeded(3), linger_s=0.2,
                                                respond=not xbus.startswith("loop://")).add_samples(imu_x, clock="host")  # fmt: skip
        if can_bus and imu_c is not None:
            interface, _, channel = can_bus.partition(":")
            if not channel:
                raise ValueError(f"{can_bus!r} is not INTERFACE:CHANNEL (e.g. virtual:dualhuman or socketcan:vcan0)")
            bus = can.Bus(interface=interface, channel=channel, receive_own_messages=False)
            play._close.append(bus.shutdown)
            play.players["can"] = CanPlayer(bus, speed=speed, faults=seeded(4)).add_samples(imu_c, clock="host")
    except BaseException:
        play.close()
        raise
    Player.share_clock(play.players.values())  # one physical time for every device of the studio
    for name, p in play.players.items():
        if log:
            rate = "as fast as possible" if math.isinf(speed) else f"{speed:g}x real time"
            log(f"{name}: {len(p.packets)} packets, {rate}")
        p.start()
    return play

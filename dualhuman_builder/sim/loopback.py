"""A simulated studio on real loopback transports, for recording a ``sim://`` take end to end.

``dualhuman capture --source sim://handshake?seed=3`` does not shortcut anything: the scene's
simulated devices (:mod:`dualhuman_builder.sim.studio`) are played onto a UDP port for the two
suits (characters 0 and 1), another for the twelve trackers, a pseudo-terminal for the Xbus MTi
(which answers the configuration dialogue) and a python-can ``virtual`` bus for the CAN MTi, and
the live sources (:mod:`~dualhuman_builder.capture.mvn_udp`, :mod:`~dualhuman_builder.capture.vive_udp`,
:mod:`~dualhuman_builder.capture.xbus_serial`, :mod:`~dualhuman_builder.capture.mti_can`) read them
exactly as they would read a real studio. The actors are those of ``rigs/sim.toml``.
"""

from __future__ import annotations

import uuid
from typing import Callable

from dualhuman_builder.capture.sources import Source, open_source
from dualhuman_builder.rig import Rig, RigActor, RigSource


class LoopbackStudio:
    """Open the loopback sources, start the players of ``studio`` (the
    :class:`~dualhuman_builder.sim.studio.SimStudio` of ``scene``; ``url`` names them, as
    :meth:`dualhuman_builder.sim.source.SimSource.loopback_studio` opens them). ``sources``:
    ``[(name, Source)]`` to record; ``actors``: the rig's actors; :meth:`finished` is True once
    every player is done (plus ``grace_s`` so the last datagrams are read). ``speed``: playback
    multiple of real time; ``faults``: :class:`~dualhuman_builder.sim.devices.Faults` for every player."""

    def __init__(self, url: str, scene, studio, *, speed: float = 1.0, faults=None,
                 progress: Callable[[str], None] | None = None, grace_s: float = 0.3, xbus: bool = True,
                 can_bus: bool = True):  # fmt: skip
        from dualhuman_builder.resources import RIGS_DIR
        from dualhuman_builder.rig import load_rig
        from dualhuman_builder.sim.play import play_studio

        self.url = url
        self.scene, self.studio = scene, studio
        self.rig: Rig = load_rig(RIGS_DIR / "sim.toml")
        self.grace_s = grace_s
        self.sources: list[tuple[str, Source]] = []
        self.play = None
        self._done_at: float | None = None
        try:
            mvn = self._open("suits", "mvn+udp://127.0.0.1:0")
            vive = self._open("trackers", "vive+udp://127.0.0.1:0")
            channel = f"dualhuman-sim-{uuid.uuid4().hex[:8]}"
            if can_bus:
                self._open("floor-imu", f"mti+can://virtual/{channel}?device=mti-can")
            self.play = play_studio(self.studio, mvn=f"127.0.0.1:{mvn.port}", trackers=f"127.0.0.1:{vive.port}",
                                    xbus="pty" if xbus else None, can_bus=f"virtual:{channel}" if can_bus else None,
                                    speed=speed, faults=faults, log=progress)  # fmt: skip
            if xbus:
                self._open("prop-imu", f"xbus://{self.play.pty_path}?device=mti-xbus")
        except BaseException:
            self.close()
            raise
        self.actors: list[RigActor] = [RigActor(a.name, "suits", a.character, dict(a.trackers)) for a in self.rig.actors]

    def _open(self, name: str, url: str) -> Source:
        src = open_source(url)
        self.sources.append((name, src))
        return src

    @property
    def rig_text(self) -> str:
        lines = [f"# simulated studio for {self.url}, played on loopback", self.rig.text]
        lines += [f"# {name} = {src.url}" for name, src in self.sources]
        return "\n".join(lines)

    def finished(self) -> bool:
        import time

        if self.play is None:
            return True
        if any(p.running for p in self.play.players.values()):
            return False
        if self._done_at is None:
            self._done_at = time.monotonic()
        return time.monotonic() - self._done_at >= self.grace_s

    def reports(self):
        """The players' :class:`~dualhuman_builder.sim.devices.PlayReport` by transport."""
        return {} if self.play is None else self.play.join()

    def close(self) -> None:
        if self.play is not None:
            self.play.close()
        for _, src in self.sources:
            src.close()

    def rig_sources(self) -> tuple[RigSource, ...]:
        return tuple(RigSource(n, s.url) for n, s in self.sources)

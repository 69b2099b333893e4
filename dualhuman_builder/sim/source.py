"""``sim://`` — the simulated studio as an in-process source (no transport; the fast path for tests).

``sim://TYPE?seed=N[&fps=30][&tempo=1][&duration=S][&approach=M][&devices=N][&preset=ideal]``
    generates the ground-truth scene ``TYPE`` (:data:`~dualhuman_builder.sim.scenes.SCENE_TYPES`)
    with ``seed`` and yields every simulated device's samples in host receive-time order, decoded,
    in-process. ``devices`` seeds the device errors (default: the scene seed); ``preset`` chooses
    them (:data:`~dualhuman_builder.sim.presets.PRESETS`: ``ideal``, the default, or ``realistic``).
``sim:///PATH/TO/SCENE.npz[?devices=N][&preset=realistic]``
    the same from a scene saved by ``dualhuman scene make``.

The scheme is registered into capture's source registry through the ``dualhuman_builder.sources``
entry point (``pyproject.toml``). Recording a ``sim://`` source (``dualhuman capture --source
sim://...``) does not iterate this class: :attr:`SimSource.PLAYS_STUDIO` makes the recorder play
the simulated studio onto real loopback transports and record them through the live sources
(:meth:`SimSource.loopback_studio`, :mod:`dualhuman_builder.sim.loopback`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterator

from dualhuman_builder.capture.sources import RawPacket, Source, SourceError, number_param, parse_source_url


class SimSource(Source):
    """The simulated studio (:mod:`dualhuman_builder.sim.studio`) playing a ground-truth scene.

    ``scene``: the :class:`~dualhuman_builder.sim.scenes.Scene`; ``studio``: the
    :class:`~dualhuman_builder.sim.studio.SimStudio` whose samples are yielded."""

    kind = "sim"
    PARAMS = ("seed", "fps", "tempo", "duration", "approach", "devices", "preset")
    PLAYS_STUDIO = True

    @classmethod
    def loopback_studio(cls, url: str, *, speed: float = 1.0, faults=None, progress=None):
        """The studio of ``url`` on loopback transports: a
        :class:`~dualhuman_builder.sim.loopback.LoopbackStudio`."""
        from dualhuman_builder.sim.loopback import LoopbackStudio

        sim = cls(url, progress=progress)
        return LoopbackStudio(url, sim.scene, sim.studio, speed=speed, faults=faults, progress=progress)

    def __init__(self, url: str, progress: Callable[[str], None] | None = None):
        from dualhuman_builder.sim.presets import PRESETS
        from dualhuman_builder.sim.generate import generate_scene
        from dualhuman_builder.sim.scenes import ALL_TYPES, Scene, SceneParams
        from dualhuman_builder.sim.studio import simulate_studio

        super().__init__(url)
        parts, query = parse_source_url(url, self.PARAMS)
        preset = query.get("preset", "ideal")
        if preset not in PRESETS:
            raise SourceError(f"unknown device error preset {preset!r} in {url!r}",
                              fix=f"write preset={' or preset='.join(PRESETS)}")  # fmt: skip
        if parts.netloc:
            if parts.netloc not in ALL_TYPES:
                raise SourceError(f"unknown scene type {parts.netloc!r} in {url!r}",
                                  fix=f"choose one of {', '.join(ALL_TYPES)}")  # fmt: skip
            params = SceneParams(type=parts.netloc, seed=number_param(query, "seed", int, 0),
                                 fps=number_param(query, "fps", float, 30.0),
                                 tempo=number_param(query, "tempo", float, 1.0),
                                 duration=number_param(query, "duration", float, None),
                                 approach_distance=number_param(query, "approach", float, None))  # fmt: skip
            try:
                self.scene = generate_scene(params, log=progress)
            except ValueError as e:
                raise SourceError(f"{url!r}: {e}", fix="adjust the sim:// parameters") from None
        elif parts.path:
            path = Path(parts.path)
            if not path.is_file():
                raise SourceError(f"no scene file {path}", fix="make one with `dualhuman scene make --out FILE`")
            self.scene = Scene.load(path)
        else:
            raise SourceError(f"{url!r} names neither a scene type nor a scene file",
                              fix="write sim://handshake?seed=3 or sim:///path/to/scene.npz")  # fmt: skip
        seed = number_param(query, "devices", int, self.scene.params.seed)
        self.studio = simulate_studio(self.scene.sequence, seed=seed, progress=progress, preset=preset,
                                      contacts=None if preset == "ideal" else self.scene.distances)  # fmt: skip

    def read(self, timeout: float) -> list[RawPacket]:
        raise SourceError("sim:// runs in-process and has no raw packets to read",
                          fix="iterate the source for samples, or record it with `dualhuman capture --source sim://...`, "
                              "which plays it on loopback transports")  # fmt: skip

    def __iter__(self) -> Iterator:
        return self.studio.samples()

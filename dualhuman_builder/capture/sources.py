"""Capture sources behind one small interface, named by URL (in rigs and on the command line).

A source is opened from its URL, iterated for typed samples
(:mod:`dualhuman_builder.capture.samples`: ``SuitFrame``, ``TrackerSample``, ``ImuSample``) and
closed; it is a context manager. So far the registry holds the simulated studio:

``sim://TYPE?seed=N[&fps=30][&tempo=1][&duration=S][&approach=M][&devices=N]``
    generates the ground-truth scene ``TYPE`` (:data:`~dualhuman_builder.sim.scenes.SCENE_TYPES`)
    with ``seed`` and yields every simulated device's samples in host receive-time order, decoded,
    in-process (no transport: the fast path for tests). ``devices`` seeds the device errors
    (default: the scene seed).
``sim:///PATH/TO/SCENE.npz[?devices=N]``
    the same from a scene saved by ``dualhuman scene make``.

The live device families (``mvn+udp``, ``xbus``, ``mti+can``, ``vive+udp``, ``vive+usb``) are
named in :data:`dualhuman_builder.rig.SOURCE_SCHEMES` and join this registry with the capture
stage.
"""

from __future__ import annotations

import abc
from pathlib import Path
from typing import Callable, Iterator
from urllib.parse import parse_qsl, urlsplit

from dualhuman_builder.errors import DualhumanError


class SourceError(DualhumanError):
    """A source URL that cannot be opened."""


class Source(abc.ABC):
    """Iterate to get samples; ``close()`` (or ``with``) releases the device."""

    url: str

    @abc.abstractmethod
    def __iter__(self) -> Iterator:
        """The typed samples, in the order the host received them."""

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _number(query: dict, key: str, kind, default):
    if key not in query:
        return default
    try:
        return kind(query[key])
    except ValueError:
        raise SourceError(f"{key}={query[key]!r} is not a {kind.__name__}", fix=f"give {key} as a number") from None


class SimSource(Source):
    """The simulated studio (:mod:`dualhuman_builder.sim.studio`) playing a ground-truth scene.

    ``scene``: the :class:`~dualhuman_builder.sim.scenes.Scene`; ``studio``: the
    :class:`~dualhuman_builder.sim.studio.SimStudio` whose samples are yielded."""

    def __init__(self, url: str, progress: Callable[[str], None] | None = None):
        from dualhuman_builder.sim.scenes import SCENE_TYPES, Scene, SceneParams, make_scene
        from dualhuman_builder.sim.studio import simulate_studio

        self.url = url
        parts = urlsplit(url)
        query = dict(parse_qsl(parts.query, keep_blank_values=True))
        known = {"seed", "fps", "tempo", "duration", "approach", "devices"}
        unknown = sorted(set(query) - known)
        if unknown:
            raise SourceError(f"unknown sim:// parameter(s) {', '.join(unknown)} in {url!r}",
                              fix=f"use only {', '.join(sorted(known))}")  # fmt: skip
        if parts.netloc:
            if parts.netloc not in SCENE_TYPES:
                raise SourceError(f"unknown scene type {parts.netloc!r} in {url!r}",
                                  fix=f"choose one of {', '.join(SCENE_TYPES)}")  # fmt: skip
            params = SceneParams(type=parts.netloc, seed=_number(query, "seed", int, 0),
                                 fps=_number(query, "fps", float, 30.0), tempo=_number(query, "tempo", float, 1.0),
                                 duration=_number(query, "duration", float, None),
                                 approach_distance=_number(query, "approach", float, None))  # fmt: skip
            self.scene = make_scene(params, log=progress)
        elif parts.path:
            path = Path(parts.path)
            if not path.is_file():
                raise SourceError(f"no scene file {path}", fix="make one with `dualhuman scene make --out FILE`")
            self.scene = Scene.load(path)
        else:
            raise SourceError(f"{url!r} names neither a scene type nor a scene file",
                              fix="write sim://handshake?seed=3 or sim:///path/to/scene.npz")  # fmt: skip
        seed = _number(query, "devices", int, self.scene.params.seed)
        self.studio = simulate_studio(self.scene.sequence, seed=seed, progress=progress)

    def __iter__(self) -> Iterator:
        return self.studio.samples()


SOURCES: dict[str, Callable[..., Source]] = {"sim": SimSource}


def open_source(url: str, **kwargs) -> Source:
    """Open the source ``url`` names (see the module docstring for the schemes)."""
    from dualhuman_builder.rig import SOURCE_SCHEMES

    scheme = urlsplit(url).scheme
    if scheme in SOURCES:
        return SOURCES[scheme](url, **kwargs)
    if scheme in SOURCE_SCHEMES:
        raise SourceError(f"the {scheme}:// source is not available in this version",
                          fix="record with a sim:// source for now; live devices come with the capture stage")  # fmt: skip
    raise SourceError(f"unknown source scheme {scheme!r} in {url!r}", fix=f"use one of {', '.join(SOURCE_SCHEMES)}")

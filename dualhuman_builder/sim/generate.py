"""One entry to every scene type: the interactions and the calibration motion (:mod:`.scenes`), and the
long ``session`` (:mod:`.session`), which is made of interaction scenes and so sits above them."""

from __future__ import annotations

from typing import Callable

from dualhuman_builder.sim.scenes import SESSION_TYPE, Scene, SceneParams, make_scene
from dualhuman_builder.sim.session import make_session


def generate_scene(params: SceneParams, model=None, log: Callable[[str], None] | None = None,
                   max_draws: int | None = None) -> Scene:  # fmt: skip
    """The scene of ``params`` (any of :data:`~dualhuman_builder.sim.scenes.ALL_TYPES`); see
    :func:`~dualhuman_builder.sim.scenes.make_scene` and :func:`~dualhuman_builder.sim.session.make_session`
    for what each makes and raises. ``max_draws`` (None: the default): of an interaction scene,
    :func:`~dualhuman_builder.sim.scenes.make_scene`'s; a session's scenes keep the default."""
    if params.type == SESSION_TYPE:
        return make_session(params, model=model, log=log)
    return make_scene(params, model=model, log=log, **({} if max_draws is None else {"max_draws": max_draws}))
